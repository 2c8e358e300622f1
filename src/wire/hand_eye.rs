//! The hand-eye problem `A_i X = X B_i` of a rigid station and its solution, as
//! `POST /calibration/hand-eye` and `brokenray calibrate-hand-eye` read and write them
//! (`docs/interface.md`, "HTTP API", `POST /api/v1/calibration/hand-eye`).

use super::{FieldProblem, PoseIn, PoseOut, Rejection, SigmaOut};
use crate::geometry::{Pose, PoseCov};
use crate::vision::{HandEyeOptions, HandEyeSolution, solve_hand_eye};
use serde::{Deserialize, Serialize};

/// One motion of the station: `a` seen by the first sensor, `b` by the second.
#[derive(Debug, Clone, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct HandEyePairIn {
    /// Motion `A_i`.
    pub a: PoseIn,
    /// Motion `B_i`.
    pub b: PoseIn,
}

/// The noise of the measured motions, for weighting the refinement.
#[derive(Debug, Clone, Copy, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct HandEyeSigmaIn {
    /// Rotation (arc-seconds).
    pub rotation_arcsec: f64,
    /// Translation (mm).
    pub translation_mm: f64,
}

/// `A_i X = X B_i`: the motions, at least three about non-parallel axes.
#[derive(Debug, Clone, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct HandEyeIn {
    /// The motions.
    pub pairs: Vec<HandEyePairIn>,
    /// Their noise (default 10 arc-seconds, 0.1 mm).
    pub sigma: Option<HandEyeSigmaIn>,
}

/// How one pair agrees with X.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct PairResidualOut {
    /// Rotation of `A_i X (X B_i)^-1` (arc-seconds).
    pub rotation_arcsec: f64,
    /// Translation of `A_i X (X B_i)^-1` (mm).
    pub translation_mm: f64,
}

/// The fit's residuals.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct HandEyeResidualsOut {
    /// Per pair, in input order.
    pub pairs: Vec<PairResidualOut>,
    /// RMS of the rotation residuals (arc-seconds).
    pub rms_rotation_arcsec: f64,
    /// RMS of the translation residuals (mm).
    pub rms_translation_mm: f64,
}

/// The rotation spread of the input motions.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct SpreadOut {
    /// Smallest rotation of a motion (degrees).
    pub min_rotation_deg: f64,
    /// Largest rotation of a motion (degrees).
    pub max_rotation_deg: f64,
    /// Largest angle between two motion axes (degrees, up to 90).
    pub max_axis_angle_deg: f64,
}

/// The solved station link.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct HandEyeOut {
    /// X.
    pub x: PoseOut,
    /// X's sigmas (from the weighted fit, scaled by its variance factor).
    pub sigma: SigmaOut,
    /// X's covariance, 36 numbers row-major, `[rho_mm; phi_rad]`: ready for
    /// `PUT /links/{name}/calibration`.
    pub covariance: Vec<f64>,
    /// How the pairs agree with X.
    pub residuals: HandEyeResidualsOut,
    /// The input motions' spread.
    pub spread: SpreadOut,
    /// Park and Martin's closed form, before refinement.
    pub closed_form: PoseOut,
    /// Refinement iterations.
    pub iterations: usize,
}

impl From<&HandEyeSolution> for HandEyeOut {
    fn from(s: &HandEyeSolution) -> Self {
        let cov = PoseCov {
            pose: s.x,
            cov: s.covariance,
        };
        Self {
            x: PoseOut::from(&s.x),
            sigma: SigmaOut::from(&cov),
            covariance: s.covariance.transpose().iter().copied().collect(),
            residuals: HandEyeResidualsOut {
                pairs: s
                    .residuals
                    .iter()
                    .map(|r| PairResidualOut {
                        rotation_arcsec: r.rotation_arcsec,
                        translation_mm: r.translation_mm,
                    })
                    .collect(),
                rms_rotation_arcsec: s.rms_rotation_arcsec,
                rms_translation_mm: s.rms_translation_mm,
            },
            spread: SpreadOut {
                min_rotation_deg: s.spread.min_rotation_deg,
                max_rotation_deg: s.spread.max_rotation_deg,
                max_axis_angle_deg: s.spread.max_axis_angle_deg,
            },
            closed_form: PoseOut::from(&s.closed_form),
            iterations: s.iterations,
        }
    }
}

impl HandEyeIn {
    /// Validates the poses and solves; every invalid pose is named, a refusal says why.
    pub fn solve(&self) -> Result<HandEyeOut, Rejection> {
        let mut problems = Vec::new();
        let mut pairs: Vec<(Pose, Pose)> = Vec::with_capacity(self.pairs.len());
        for (i, p) in self.pairs.iter().enumerate() {
            match (p.a.to_pose("a"), p.b.to_pose("b")) {
                (Ok(a), Ok(b)) => pairs.push((a, b)),
                (a, b) => {
                    problems.extend(a.err().into_iter().chain(b.err()).map(|e| e.at(i)));
                }
            }
        }
        let mut options = HandEyeOptions::default();
        if let Some(s) = self.sigma {
            // A measurement's noise, from a thousandth of an arc-second (or a nanometre) to
            // a hundred degrees (or a hundred metres): beyond, the weights overflow.
            for (field, v, lo, hi) in [
                ("sigma.rotation_arcsec", s.rotation_arcsec, 1e-3, 3.6e5),
                ("sigma.translation_mm", s.translation_mm, 1e-6, 1e5),
            ] {
                if !(v.is_finite() && (lo..=hi).contains(&v)) {
                    problems.push(FieldProblem::new(
                        field,
                        format!("must lie in [{lo}, {hi}], not {v}"),
                    ));
                }
            }
            options.sigma_rotation_arcsec = s.rotation_arcsec;
            options.sigma_translation_mm = s.translation_mm;
        }
        if !problems.is_empty() {
            return Err(Rejection::Invalid {
                message: format!("{} invalid pose(s) or setting(s)", problems.len()),
                problems,
            });
        }
        let solution = solve_hand_eye(&pairs, &options)?;
        Ok(HandEyeOut::from(&solution))
    }
}
