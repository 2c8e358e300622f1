//! Station calibration: `A_i X = X B_i` (hand-eye), Park and Martin's closed form, then
//! Gauss-Newton on all pairs.
//!
//! A rigid station (two cameras, or a camera and a marker) is moved through motions; the first
//! sensor sees the motion `A_i`, the second `B_i`, and the unknown `X` (the station's calibrated
//! link) satisfies `A_i X = X B_i`. Rotations first: with `alpha_i = Log(R_A_i)` and
//! `beta_i = Log(R_B_i)`, `alpha_i = R_X beta_i`, so `R_X` is the orthogonal polar factor of
//! `M^T`, `M = sum beta_i alpha_i^T` (`R_X = (M^T M)^-1/2 M^T`). Then the translation by linear least
//! squares of `(R_A_i - I) t_X = R_X t_B_i - t_A_i`. Then both together by Gauss-Newton on the
//! residuals `Log(A_i X B_i^-1 X^-1)`, weighted by the given measurement sigmas, which also gives
//! X's covariance (scaled by the fit's own variance factor).
//!
//! Motions whose rotation is too small to define an axis, pairs whose two rotations differ in
//! angle, and sets whose axes are all nearly parallel are refused with the reason.

use super::VisionError;
use super::sqpnp::nearest_rotation;
use crate::geometry::{
    ARCSEC_PER_RAD, Mat3, Mat6, Pose, Rotation, Twist, Vec3, se3_exp, se3_log, so3_log,
};
use nalgebra::Translation3;

/// Fewest motions accepted.
pub const MIN_MOTIONS: usize = 3;

/// Thresholds and the weighting of the refinement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HandEyeOptions {
    /// A motion must rotate at least this much for its axis to count (degrees).
    pub min_motion_deg: f64,
    /// Two axes must be at least this far apart somewhere in the set (degrees).
    pub min_axis_spread_deg: f64,
    /// `A_i` and `B_i` must rotate by the same angle within this (degrees).
    pub angle_tolerance_deg: f64,
    /// Every pair must fit the solution's translation within this (mm), or ten of its
    /// translation sigmas where that is more.
    pub translation_tolerance_mm: f64,
    /// Translation noise of a measured motion (mm), for weighting.
    pub sigma_translation_mm: f64,
    /// Rotation noise of a measured motion (arc-seconds), for weighting.
    pub sigma_rotation_arcsec: f64,
}

impl Default for HandEyeOptions {
    fn default() -> Self {
        Self {
            min_motion_deg: 0.5,
            min_axis_spread_deg: 5.0,
            angle_tolerance_deg: 0.5,
            translation_tolerance_mm: 5.0,
            sigma_translation_mm: 0.1,
            sigma_rotation_arcsec: 10.0,
        }
    }
}

/// How well one pair agrees with the solution.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PairResidual {
    /// Rotation angle of `A_i X (X B_i)^-1` (arc-seconds).
    pub rotation_arcsec: f64,
    /// Translation of `A_i X (X B_i)^-1` (mm).
    pub translation_mm: f64,
}

/// The rotation spread of the input motions: what the data could observe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionSpread {
    /// Smallest rotation of a motion (degrees).
    pub min_rotation_deg: f64,
    /// Largest rotation of a motion (degrees).
    pub max_rotation_deg: f64,
    /// Largest angle between two motion axes (degrees, 0 to 90).
    pub max_axis_angle_deg: f64,
}

/// A solved `X` with its fit.
#[derive(Debug, Clone, PartialEq)]
pub struct HandEyeSolution {
    /// The calibrated transform.
    pub x: Pose,
    /// Its covariance (left perturbation `[rho (mm); phi (rad)]`).
    pub covariance: Mat6,
    /// Per pair.
    pub residuals: Vec<PairResidual>,
    /// RMS of the rotation residuals (arc-seconds).
    pub rms_rotation_arcsec: f64,
    /// RMS of the translation residuals (mm).
    pub rms_translation_mm: f64,
    /// The closed-form start before refinement.
    pub closed_form: Pose,
    /// The input motions' spread.
    pub spread: MotionSpread,
    /// Gauss-Newton iterations.
    pub iterations: usize,
}

/// Solves `A_i X = X B_i` for the pairs `(A_i, B_i)`.
pub fn solve_hand_eye(
    pairs: &[(Pose, Pose)],
    options: &HandEyeOptions,
) -> Result<HandEyeSolution, VisionError> {
    if pairs.len() < MIN_MOTIONS {
        return Err(VisionError::NotEnoughPoints {
            given: pairs.len(),
            needed: MIN_MOTIONS,
        });
    }
    let mut alphas = Vec::with_capacity(pairs.len());
    let mut betas = Vec::with_capacity(pairs.len());
    let (mut min_deg, mut max_deg) = (f64::INFINITY, 0.0f64);
    for (index, (a, b)) in pairs.iter().enumerate() {
        let alpha = so3_log(&a.rotation);
        let beta = so3_log(&b.rotation);
        let (a_deg, b_deg) = (alpha.norm().to_degrees(), beta.norm().to_degrees());
        let smaller = a_deg.min(b_deg);
        if smaller.is_nan() || smaller < options.min_motion_deg {
            return Err(VisionError::MotionTooSmall {
                index,
                angle_deg: smaller,
                min_deg: options.min_motion_deg,
            });
        }
        if (a_deg - b_deg).abs() > options.angle_tolerance_deg {
            return Err(VisionError::InconsistentMotion {
                index,
                a_deg,
                b_deg,
                tolerance_deg: options.angle_tolerance_deg,
            });
        }
        min_deg = min_deg.min(a_deg);
        max_deg = max_deg.max(a_deg);
        alphas.push(alpha);
        betas.push(beta);
    }
    let mut largest_axis_deg = 0.0f64;
    for i in 0..alphas.len() {
        for j in i + 1..alphas.len() {
            let c = alphas[i]
                .normalize()
                .dot(&alphas[j].normalize())
                .abs()
                .min(1.0);
            largest_axis_deg = largest_axis_deg.max(c.acos().to_degrees());
        }
    }
    if largest_axis_deg < options.min_axis_spread_deg {
        return Err(VisionError::ParallelAxes {
            largest_deg: largest_axis_deg,
            min_deg: options.min_axis_spread_deg,
        });
    }
    let spread = MotionSpread {
        min_rotation_deg: min_deg,
        max_rotation_deg: max_deg,
        max_axis_angle_deg: largest_axis_deg,
    };

    let closed_form = park_martin(pairs, &alphas, &betas);
    let (x, covariance, iterations) = refine(pairs, closed_form, options);
    let residuals: Vec<PairResidual> = pairs
        .iter()
        .map(|(a, b)| {
            let e = a * x * (x * b).inverse();
            PairResidual {
                rotation_arcsec: e.rotation.angle() * ARCSEC_PER_RAD,
                translation_mm: e.translation.vector.norm(),
            }
        })
        .collect();
    // Every pair must fit the solution within the angle tolerance: one that does not is a
    // motion measured wrong, and the rest would be bent towards it.
    if let Some((index, r)) = residuals
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.rotation_arcsec.total_cmp(&b.1.rotation_arcsec))
        && r.rotation_arcsec / 3600.0 > options.angle_tolerance_deg
    {
        return Err(VisionError::PairDoesNotFit {
            index,
            residual_deg: r.rotation_arcsec / 3600.0,
            tolerance_deg: options.angle_tolerance_deg,
        });
    }
    // And within the translation's: a motion whose translations disagree by centimetres is
    // measured wrong however well its rotation fits.
    let translation_tolerance_mm = options
        .translation_tolerance_mm
        .max(10.0 * options.sigma_translation_mm);
    if let Some((index, r)) = residuals
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.translation_mm.total_cmp(&b.1.translation_mm))
        && (r.translation_mm.is_nan() || r.translation_mm > translation_tolerance_mm)
    {
        return Err(VisionError::TranslationDoesNotFit {
            index,
            residual_mm: r.translation_mm,
            tolerance_mm: translation_tolerance_mm,
        });
    }
    if !covariance.iter().all(|v| v.is_finite()) {
        return Err(VisionError::CalibrationRefused {
            reason: "the solution's covariance cannot be computed from these motions and \
                     sigmas (give sigmas of a measurement's real size)"
                .to_owned(),
        });
    }
    let rms = |of: fn(&PairResidual) -> f64| {
        (residuals.iter().map(|r| of(r).powi(2)).sum::<f64>() / residuals.len() as f64).sqrt()
    };
    let rms_rotation_arcsec = rms(|r| r.rotation_arcsec);
    let rms_translation_mm = rms(|r| r.translation_mm);
    Ok(HandEyeSolution {
        x,
        covariance,
        residuals,
        rms_rotation_arcsec,
        rms_translation_mm,
        closed_form,
        spread,
        iterations,
    })
}

fn park_martin(pairs: &[(Pose, Pose)], alphas: &[Vec3], betas: &[Vec3]) -> Pose {
    let m: Mat3 = betas
        .iter()
        .zip(alphas)
        .fold(Mat3::zeros(), |acc, (b, a)| acc + b * a.transpose());
    let r_x = nearest_rotation(&m.transpose());
    let mut ctc = Mat3::zeros();
    let mut ctd = Vec3::zeros();
    for (a, b) in pairs {
        let c = a.rotation.to_rotation_matrix().into_inner() - Mat3::identity();
        let d = r_x * b.translation.vector - a.translation.vector;
        ctc += c.transpose() * c;
        ctd += c.transpose() * d;
    }
    let t = ctc.try_inverse().map_or_else(Vec3::zeros, |inv| inv * ctd);
    let rotation = Rotation::from_matrix_eps(&r_x, 1e-15, 100, Rotation::identity());
    Pose::from_parts(Translation3::from(t), rotation)
}

/// Weighted residuals of all pairs at `x`.
fn residual_vector(pairs: &[(Pose, Pose)], x: &Pose, weights: &Twist) -> Vec<f64> {
    let mut out = Vec::with_capacity(6 * pairs.len());
    for (a, b) in pairs {
        let e = se3_log(&(a * x * (x * b).inverse()));
        out.extend(e.iter().zip(weights.iter()).map(|(v, w)| v * w));
    }
    out
}

/// Gauss-Newton over a left perturbation of X (numerical Jacobian: a few pairs, offline).
fn refine(pairs: &[(Pose, Pose)], start: Pose, options: &HandEyeOptions) -> (Pose, Mat6, usize) {
    let sigma_rad = options.sigma_rotation_arcsec / ARCSEC_PER_RAD;
    let weights = Twist::new(
        1.0 / options.sigma_translation_mm,
        1.0 / options.sigma_translation_mm,
        1.0 / options.sigma_translation_mm,
        1.0 / sigma_rad,
        1.0 / sigma_rad,
        1.0 / sigma_rad,
    );
    let steps = Twist::new(1e-4, 1e-4, 1e-4, 1e-7, 1e-7, 1e-7);
    let m = 6 * pairs.len();
    let mut x = start;
    let mut r = residual_vector(pairs, &x, &weights);
    let mut cost: f64 = r.iter().map(|v| v * v).sum();
    let mut jtj = Mat6::zeros();
    let mut iterations = 0;
    for _ in 0..30 {
        iterations += 1;
        let mut jac = nalgebra::DMatrix::<f64>::zeros(m, 6);
        for k in 0..6 {
            let mut d = Twist::zeros();
            d[k] = steps[k];
            let plus = residual_vector(pairs, &(se3_exp(&d) * x), &weights);
            let minus = residual_vector(pairs, &(se3_exp(&(-d)) * x), &weights);
            for i in 0..m {
                jac[(i, k)] = (plus[i] - minus[i]) / (2.0 * steps[k]);
            }
        }
        let jt = jac.transpose();
        jtj = Mat6::from_iterator((&jt * &jac).iter().copied());
        let g = &jt * nalgebra::DVector::from_vec(r.clone());
        let Some(chol) = jtj.cholesky() else {
            break;
        };
        let delta: Twist = chol.solve(&(-Twist::from_iterator(g.iter().copied())));
        let candidate = se3_exp(&delta) * x;
        let r_new = residual_vector(pairs, &candidate, &weights);
        let cost_new: f64 = r_new.iter().map(|v| v * v).sum();
        if cost_new > cost {
            break;
        }
        let decrease = cost - cost_new;
        x = candidate;
        r = r_new;
        cost = cost_new;
        if decrease <= 1e-12 * cost.max(1e-300) || delta.norm() < 1e-12 {
            break;
        }
    }
    let dof = (m as f64 - 6.0).max(1.0);
    let variance_factor = cost / dof;
    let covariance = jtj.try_inverse().map_or_else(
        || Mat6::from_diagonal_element(f64::INFINITY),
        |inv| {
            let c = inv * variance_factor.max(f64::MIN_POSITIVE);
            (c + c.transpose()) * 0.5
        },
    );
    (x, covariance, iterations)
}
