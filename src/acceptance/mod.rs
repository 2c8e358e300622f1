//! The acceptance procedure's figures and decisions: a rig signed off the way optical
//! measuring systems are (zero displacement deviation on a still target, displacement
//! deviation for known moves), each figure with its uncertainty, pass or fail against the
//! installation's limits (`docs/interface.md`, "Acceptance").
//!
//! Everything is computed from **raw results** (one per measurement group, their noise
//! independent from group to group) of `G_from_B`, as displacements from the still window's
//! mean `S`: `D = S * G_from_B^-1` (the deformation's formula with `S` as the reference),
//! reported as the rotation vector (arc-seconds, about the still target's axes) and the
//! translation (mm, in the still target's coordinates). Six axes, in that order: rotation x,
//! y, z, then translation x, y, z.
//!
//! * **A window's mean**: the chordal mean of its poses; its random covariance the mean of the
//!   results' random covariances over their count (independent noise averages down); its
//!   systematic covariance their mean (a calibration's error does not).
//! * **Settled**: the window's halves agree: `d^T (C1 + C2)^-1 d` of their means' difference
//!   under the chi-square quantile at [`SETTLED_PROBABILITY`] with 6 degrees of freedom.
//! * **Still** (zero displacement deviation): per axis the rms of the results about the
//!   window's mean with its uncertainty `rms / sqrt(2 (n - 1))`, the largest deviation, the rms
//!   the results' own sigmas expect, and the repeatability test (the scatter's chi-square
//!   against its quantile with `6 (n - 1)` degrees of freedom, as `stats` judges it). It passes
//!   when every axis's rms is within its limit and the scatter is what the sigmas allow.
//! * **A known move**: the displacement of the step's mean from the still mean, measured minus
//!   stated per axis. Its standard uncertainty holds both means' random parts and the part of
//!   the calibrations' error that does not cancel between the two poses: the systematic errors
//!   of the two means are taken as fully correlated (the same calibration), which leaves, per
//!   axis, the difference of their systematic sigmas (a focal length's error scales a depth's
//!   error with the depth: its difference is the error of the move). The decision follows
//!   ISO 14253-1 for an acceptance: a step passes when `|deviation| + 2 u` lies within the
//!   limit on every axis (conformance proven with the expanded uncertainty, k = 2).
//!
//! Pure: no clock, no IO; the times of the windows are handed in. [`procedure`] runs the steps.

pub mod procedure;

pub use procedure::{Offered, Phase, Plan, PlannedMove, Procedure, StepDone, StepFigures};

use crate::chain::chi_square_quantile;
pub use crate::deformation::Displacement;
use crate::deformation::{CalibrationStamp, MeasuredPose};
use crate::geometry::{ARCSEC_PER_RAD, Mat6, Pose, PoseCov, mean_pose, skew, so3_log};

/// Probability with which the halves of a settled window agree (the chi-square quantile the
/// settling is judged by).
pub const SETTLED_PROBABILITY: f64 = 0.999;

/// The coverage factor of the expanded uncertainty a move's decision uses.
pub const COVERAGE_FACTOR: f64 = 2.0;

/// The fewest results a window's figures are computed from.
pub const MIN_RESULTS: usize = 10;

/// Six axes in the order users read them: rotation about x, y, z (arc-seconds), then
/// translation along x, y, z (mm).
pub type Axes = [f64; 6];

/// The limits an installation states (`[acceptance]`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Limits {
    /// The largest rms of a still target's rotation about any axis (arc-seconds).
    pub still_rms_arcsec: f64,
    /// The largest rms of a still target's translation along any axis (mm).
    pub still_rms_mm: f64,
    /// The largest deviation of a known move's rotation about any axis, its expanded
    /// uncertainty included (arc-seconds).
    pub move_arcsec: f64,
    /// The largest deviation of a known move's translation along any axis, its expanded
    /// uncertainty included (mm).
    pub move_mm: f64,
}

impl Limits {
    fn still(&self) -> Axes {
        let (r, t) = (self.still_rms_arcsec, self.still_rms_mm);
        [r, r, r, t, t, t]
    }

    fn moves(&self) -> Axes {
        let (r, t) = (self.move_arcsec, self.move_mm);
        [r, r, r, t, t, t]
    }
}

/// Why figures cannot be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AcceptanceError {
    /// Too few results in a window.
    #[error("{count} raw results in the window: at least {MIN_RESULTS} are needed")]
    TooFew {
        /// How many there were.
        count: usize,
    },
    /// The results' poses or covariances cannot be averaged or inverted.
    #[error("the window's results cannot be averaged: {0}")]
    Degenerate(String),
}

/// The mean of a window of raw results.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowMean {
    /// How many results.
    pub count: usize,
    /// Their mean `G_from_B`.
    pub g_from_b: Pose,
    /// The random covariance of the mean (the results' mean random covariance over `count`).
    pub random_cov: Mat6,
    /// The systematic covariance of the mean (the results' mean systematic covariance).
    pub systematic_cov: Mat6,
}

/// The mean of a window's results.
pub fn window_mean(points: &[MeasuredPose]) -> Result<WindowMean, AcceptanceError> {
    let count = points.len();
    if count < MIN_RESULTS {
        return Err(AcceptanceError::TooFew { count });
    }
    let poses: Vec<Pose> = points.iter().map(|p| p.whole.pose).collect();
    let mean = mean_pose(&poses).map_err(|e| AcceptanceError::Degenerate(e.to_string()))?;
    let n = count as f64;
    let sum = |f: fn(&MeasuredPose) -> Mat6| points.iter().fold(Mat6::zeros(), |acc, p| acc + f(p));
    Ok(WindowMean {
        count,
        g_from_b: mean.mean.pose,
        random_cov: sum(|p| p.random().cov) / (n * n),
        systematic_cov: sum(|p| p.systematic_cov) / n,
    })
}

/// The 6 x 6 covariance of a displacement's axes (radians and mm) from the left-perturbation
/// covariance of `G0_from_G`: `t' = t + rho + phi x t`, the rotation vector takes `phi`
/// (small rotations), so `J = [[0, I], [I, -[t]x]]` maps `(rho, phi)` to (rotation, translation).
fn axes_covariance(p: &PoseCov) -> Mat6 {
    let mut j = Mat6::zeros();
    j.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&crate::geometry::Mat3::identity());
    j.fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&crate::geometry::Mat3::identity());
    j.fixed_view_mut::<3, 3>(3, 3)
        .copy_from(&(-skew(&p.pose.translation.vector)));
    j * p.cov * j.transpose()
}

/// Radians to arc-seconds on the rotation axes, mm kept.
fn to_user_units(a: [f64; 6]) -> Axes {
    [
        a[0] * ARCSEC_PER_RAD,
        a[1] * ARCSEC_PER_RAD,
        a[2] * ARCSEC_PER_RAD,
        a[3],
        a[4],
        a[5],
    ]
}

/// `D = S * G^-1` with the covariance `G`'s part gives it (`S` exact).
fn displacement_of(still: &Pose, g_from_b: &Pose, cov: &Mat6) -> PoseCov {
    PoseCov::exact(*still).compose(
        &PoseCov {
            pose: *g_from_b,
            cov: *cov,
        }
        .inverse(),
    )
}

/// The axes of a displacement in internal units (radians, mm).
fn internal_axes(d: &Pose) -> [f64; 6] {
    let phi = so3_log(&d.rotation);
    let t = d.translation.vector;
    [phi.x, phi.y, phi.z, t.x, t.y, t.z]
}

/// `d^T C^-1 d`, `None` when `C` is singular.
fn mahalanobis(d: &[f64; 6], cov: &Mat6) -> Option<f64> {
    let d = nalgebra::Vector6::from_column_slice(d);
    let chol = cov.cholesky()?;
    Some(d.dot(&chol.solve(&d)))
}

/// Whether a window's two halves agree.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Settling {
    /// `d^T (C1 + C2)^-1 d` of the halves' means.
    pub chi2: f64,
    /// Its quantile at [`SETTLED_PROBABILITY`] (6 degrees of freedom).
    pub threshold: f64,
}

impl Settling {
    /// True when the halves agree.
    pub fn settled(&self) -> bool {
        self.chi2 <= self.threshold
    }
}

/// Whether the results of a window settled: its first and second halves (by time) agree.
pub fn settling(first: &WindowMean, second: &WindowMean) -> Result<Settling, AcceptanceError> {
    let d = PoseCov {
        pose: first.g_from_b,
        cov: first.random_cov,
    }
    .compose(
        &PoseCov {
            pose: second.g_from_b,
            cov: second.random_cov,
        }
        .inverse(),
    );
    let chi2 = mahalanobis(&internal_axes(&d.pose), &axes_covariance(&d))
        .ok_or_else(|| AcceptanceError::Degenerate("the halves' covariance is singular".into()))?;
    Ok(Settling {
        chi2,
        threshold: chi_square_quantile(6, SETTLED_PROBABILITY),
    })
}

/// A still target's figures (the zero displacement deviation).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StillFigures {
    /// How many results.
    pub count: usize,
    /// Per axis the rms of the results about their mean.
    pub rms: Axes,
    /// The standard uncertainty of each rms, `rms / sqrt(2 (n - 1))`.
    pub rms_uncertainty: Axes,
    /// Per axis the largest deviation from the mean (its absolute value).
    pub largest: Axes,
    /// Per axis the rms the results' own random sigmas expect.
    pub expected_rms: Axes,
    /// The limit of each axis's rms.
    pub limit: Axes,
    /// The scatter's chi-square against the results' random covariances.
    pub chi2: f64,
    /// Its degrees of freedom, `6 (n - 1)`.
    pub dof: usize,
    /// Its quantile at [`crate::stats::REPEATABILITY_PROBABILITY`].
    pub threshold: f64,
    /// Every axis within its limit and the scatter within what the sigmas allow.
    pub passed: bool,
}

/// The figures of a still window of results with its mean.
pub fn still_figures(
    points: &[MeasuredPose],
    mean: &WindowMean,
    limits: &Limits,
) -> Result<StillFigures, AcceptanceError> {
    let n = points.len();
    if n < MIN_RESULTS {
        return Err(AcceptanceError::TooFew { count: n });
    }
    let displacements: Vec<(PoseCov, [f64; 6])> = points
        .iter()
        .map(|p| {
            let d = displacement_of(&mean.g_from_b, p.pose(), &p.random().cov);
            let axes = internal_axes(&d.pose);
            (d, axes)
        })
        .collect();
    let nf = n as f64;
    let mut centre = [0.0; 6];
    for (_, a) in &displacements {
        for i in 0..6 {
            centre[i] += a[i] / nf;
        }
    }
    let mut sum_sq = [0.0; 6];
    let mut largest = [0.0_f64; 6];
    let mut mean_cov = Mat6::zeros();
    for (d, a) in &displacements {
        for i in 0..6 {
            let e = a[i] - centre[i];
            sum_sq[i] += e * e;
            largest[i] = largest[i].max(e.abs());
        }
        mean_cov += axes_covariance(d) / nf;
    }
    let info = mean_cov
        .cholesky()
        .ok_or_else(|| AcceptanceError::Degenerate("the results' covariance is singular".into()))?;
    let chi2: f64 = displacements
        .iter()
        .map(|(_, a)| {
            let e = nalgebra::Vector6::from_fn(|i, _| a[i] - centre[i]);
            e.dot(&info.solve(&e))
        })
        .sum();
    let dof = 6 * (n - 1);
    let threshold = chi_square_quantile(dof, crate::stats::REPEATABILITY_PROBABILITY);
    let rms = to_user_units(sum_sq.map(|s| (s / nf).sqrt()));
    let rms_uncertainty = rms.map(|r| r / (2.0 * (nf - 1.0)).sqrt());
    let expected_rms = to_user_units(std::array::from_fn(|i| mean_cov[(i, i)].max(0.0).sqrt()));
    let limit = limits.still();
    let passed = (0..6).all(|i| rms[i] <= limit[i]) && chi2 <= threshold;
    Ok(StillFigures {
        count: n,
        rms,
        rms_uncertainty,
        largest: to_user_units(largest),
        expected_rms,
        limit,
        chi2,
        dof,
        threshold,
        passed,
    })
}

/// A known move's figures (the displacement deviation).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MoveFigures {
    /// How many results the step's mean holds.
    pub count: usize,
    /// The displacement stated.
    pub stated: Axes,
    /// The displacement measured (the step's mean from the still mean).
    pub measured: Axes,
    /// Measured minus stated.
    pub deviation: Axes,
    /// The deviation's standard uncertainty per axis.
    pub uncertainty: Axes,
    /// `deviation / uncertainty` per axis.
    pub z: Axes,
    /// `d^T C^-1 d` of the whole deviation (6 degrees of freedom when the uncertainty
    /// covers it).
    pub nees: f64,
    /// The limit of each axis's `|deviation| + 2 u`.
    pub limit: Axes,
    /// Every axis's `|deviation| + 2 u` within its limit.
    pub passed: bool,
}

/// The figures of a known move: the step's mean against the still mean and the displacement
/// stated.
pub fn move_figures(
    still: &WindowMean,
    step: &WindowMean,
    stated: &Displacement,
    limits: &Limits,
) -> Result<MoveFigures, AcceptanceError> {
    let s = PoseCov {
        pose: still.g_from_b,
        cov: still.random_cov,
    };
    let g = PoseCov {
        pose: step.g_from_b,
        cov: step.random_cov,
    };
    let d = s.compose(&g.inverse());
    let random = axes_covariance(&d);
    // The systematic parts, each carried alone into the displacement, fully correlated.
    let part = |s_cov: Mat6, g_cov: Mat6| {
        axes_covariance(
            &PoseCov {
                pose: still.g_from_b,
                cov: s_cov,
            }
            .compose(
                &PoseCov {
                    pose: step.g_from_b,
                    cov: g_cov,
                }
                .inverse(),
            ),
        )
    };
    let from_still = part(still.systematic_cov, Mat6::zeros());
    let from_step = part(Mat6::zeros(), step.systematic_cov);
    let systematic: [f64; 6] = std::array::from_fn(|i| {
        (from_still[(i, i)].max(0.0).sqrt() - from_step[(i, i)].max(0.0).sqrt()).abs()
    });
    let mut cov = random;
    for (i, s) in systematic.iter().enumerate() {
        cov[(i, i)] += s * s;
    }
    let measured_internal = internal_axes(&d.pose);
    let stated_axes = stated.axes();
    let stated_internal: [f64; 6] = std::array::from_fn(|i| {
        if i < 3 {
            stated_axes[i] / ARCSEC_PER_RAD
        } else {
            stated_axes[i]
        }
    });
    let deviation_internal: [f64; 6] =
        std::array::from_fn(|i| measured_internal[i] - stated_internal[i]);
    let nees = mahalanobis(&deviation_internal, &cov)
        .ok_or_else(|| AcceptanceError::Degenerate("the move's covariance is singular".into()))?;
    let deviation = to_user_units(deviation_internal);
    let uncertainty = to_user_units(std::array::from_fn(|i| cov[(i, i)].max(0.0).sqrt()));
    let limit = limits.moves();
    let passed = (0..6).all(|i| deviation[i].abs() + COVERAGE_FACTOR * uncertainty[i] <= limit[i]);
    Ok(MoveFigures {
        count: step.count,
        stated: stated_axes,
        measured: to_user_units(measured_internal),
        deviation,
        uncertainty,
        z: std::array::from_fn(|i| deviation[i] / uncertainty[i]),
        nees,
        limit,
        passed,
    })
}

crate::words! {
    /// Where an acceptance stands.
    pub enum Standing("acceptance standing") {
        /// Passed, within its reverification interval, and nothing it accepted changed.
        Valid = "valid",
        /// Passed, but its reverification interval is over.
        Due = "due",
        /// Passed, but a calibration or a reset changed what it accepted since.
        NoLongerHolds = "no_longer_holds",
        /// It did not pass.
        Failed = "failed",
    }
}

crate::words! {
    /// What a step of the procedure is.
    pub enum StepKind("acceptance step kind") {
        /// Every target kept still: the zero displacement deviation.
        Still = "still",
        /// A target moved by a stated displacement: the displacement deviation.
        Move = "move",
    }
}

/// How an acceptance recorded at `at_ns` stands at `now_ns`, reverified every `interval_ns`,
/// `changed` when something it accepted changed since.
pub fn standing(
    passed: bool,
    at_ns: i64,
    now_ns: i64,
    interval_ns: i64,
    changed: bool,
) -> Standing {
    if !passed {
        Standing::Failed
    } else if changed {
        Standing::NoLongerHolds
    } else if now_ns >= at_ns.saturating_add(interval_ns) {
        Standing::Due
    } else {
        Standing::Valid
    }
}

/// The calibrations of a window's results when they were all the same.
pub fn common_calibration(
    stamps: impl IntoIterator<Item = Option<CalibrationStamp>>,
) -> Option<CalibrationStamp> {
    let mut stamps = stamps.into_iter();
    let first = stamps.next()??;
    stamps.all(|s| s == Some(first)).then_some(first)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Twist, Vec3, se3_exp};
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};
    use rand_distr::StandardNormal;
    use statrs::distribution::{ChiSquared, ContinuousCDF};

    fn still_pose() -> Pose {
        se3_exp(&Twist::new(-1283.2, -2952.2, 532.5, 0.07, -0.02, 2.87))
    }

    /// A diagonal covariance: 5 arc-seconds and 0.05 mm per result (left perturbation about
    /// the origin, so translation sigmas hold for a pose near it only; the tests draw with
    /// the same covariance they state, which is all that matters).
    fn noise_cov() -> Mat6 {
        let r = (5.0 / ARCSEC_PER_RAD).powi(2);
        let t = 0.05_f64.powi(2);
        Mat6::from_diagonal(&nalgebra::Vector6::new(t, t, t, r, r, r))
    }

    fn draw(rng: &mut StdRng, cov: &Mat6) -> Twist {
        let l = cov.cholesky().expect("positive definite").l();
        l * Twist::from_fn(|_, _| rng.sample::<f64, _>(StandardNormal))
    }

    /// `n` raw results of a target displaced by `d` from `still`, with `cov` noise.
    fn results(rng: &mut StdRng, still: &Pose, d: &Displacement, n: usize) -> Vec<MeasuredPose> {
        let truth = d.g0_from_g().inverse() * still;
        (0..n)
            .map(|_| {
                MeasuredPose::whole(PoseCov {
                    pose: se3_exp(&draw(rng, &noise_cov())) * truth,
                    cov: noise_cov(),
                })
            })
            .collect()
    }

    const LIMITS: Limits = Limits {
        still_rms_arcsec: 10.0,
        still_rms_mm: 0.1,
        move_arcsec: 10.0,
        move_mm: 0.1,
    };

    #[test]
    fn a_displacement_and_its_pose_are_the_same_thing() {
        let d = Displacement {
            rotation_arcsec: [30.0, -1800.0, 7.0],
            translation_mm: [5.0, 0.0, -20.0],
        };
        let back = Displacement::of(&d.g0_from_g());
        for (a, b) in d.axes().iter().zip(back.axes()) {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
    }

    #[test]
    fn known_moves_deviations_stay_within_their_uncertainty_over_many_steps() {
        // 200 steps of a correct rig: the summed NEES is chi-square with 1200 degrees of
        // freedom; its 0.0005 and 0.9995 quantiles bound it.
        let mut rng = StdRng::seed_from_u64(7);
        let still = still_pose();
        let (mut sum, mut steps) = (0.0, 0);
        for k in 0..200 {
            let s = window_mean(&results(&mut rng, &still, &Displacement::ZERO, 60)).unwrap();
            let stated = Displacement {
                rotation_arcsec: [0.0, 0.0, 60.0 * (k % 3) as f64],
                translation_mm: [(k % 5) as f64, 0.0, 20.0],
            };
            let step = window_mean(&results(&mut rng, &still, &stated, 30)).unwrap();
            let m = move_figures(&s, &step, &stated, &LIMITS).unwrap();
            sum += m.nees;
            steps += 1;
        }
        let dof = 6.0 * steps as f64;
        let chi = ChiSquared::new(dof).unwrap();
        assert!(
            (chi.inverse_cdf(0.0005)..=chi.inverse_cdf(0.9995)).contains(&sum),
            "summed NEES {sum:.1} over {dof} degrees of freedom"
        );
    }

    #[test]
    fn a_move_measured_short_by_more_than_its_limit_fails_and_its_z_says_by_how_much() {
        let mut rng = StdRng::seed_from_u64(8);
        let still = still_pose();
        let s = window_mean(&results(&mut rng, &still, &Displacement::ZERO, 400)).unwrap();
        let moved = Displacement {
            rotation_arcsec: [0.0; 3],
            translation_mm: [0.0, 0.0, 20.0],
        };
        let step = window_mean(&results(&mut rng, &still, &moved, 400)).unwrap();
        // Stated 0.3 mm more than the move made: a scale error of 1.5 %.
        let stated = Displacement {
            rotation_arcsec: [0.0; 3],
            translation_mm: [0.0, 0.0, 20.3],
        };
        let m = move_figures(&s, &step, &stated, &LIMITS).unwrap();
        assert!(!m.passed);
        assert!(
            (m.deviation[5] + 0.3).abs() < 5.0 * m.uncertainty[5],
            "{m:?}"
        );
        // Two means of 400 results of 0.05 mm: u = 0.05 sqrt(2/400).
        assert!((m.uncertainty[5] - 0.05 * (2.0_f64 / 400.0).sqrt()).abs() < 1e-4);
        assert!(m.z[5] < -50.0, "{}", m.z[5]);
        let right = move_figures(&s, &step, &moved, &LIMITS).unwrap();
        assert!(right.passed, "{right:?}");
    }

    #[test]
    fn a_still_window_reports_the_rms_its_sigmas_expect_and_fails_a_scatter_they_do_not() {
        let mut rng = StdRng::seed_from_u64(9);
        let still = still_pose();
        let points = results(&mut rng, &still, &Displacement::ZERO, 500);
        let mean = window_mean(&points).unwrap();
        let f = still_figures(&points, &mean, &LIMITS).unwrap();
        assert!(f.passed, "{f:?}");
        for i in 0..6 {
            // 500 results: the rms is within 4 of its standard uncertainties of the expected.
            assert!(
                (f.rms[i] - f.expected_rms[i]).abs() < 4.0 * f.rms_uncertainty[i],
                "axis {i}: {f:?}"
            );
            assert!(f.largest[i] >= f.rms[i]);
        }
        assert_eq!(f.dof, 6 * 499);
        // The same scatter reported with half the sigmas: the repeatability fails.
        let claimed: Vec<MeasuredPose> = points
            .iter()
            .map(|p| {
                MeasuredPose::whole(PoseCov {
                    cov: p.whole.cov / 4.0,
                    ..p.whole
                })
            })
            .collect();
        let f = still_figures(&claimed, &window_mean(&claimed).unwrap(), &LIMITS).unwrap();
        assert!(f.chi2 > f.threshold && !f.passed, "{f:?}");
    }

    #[test]
    fn a_window_whose_halves_disagree_has_not_settled() {
        let mut rng = StdRng::seed_from_u64(10);
        let still = still_pose();
        let a = window_mean(&results(&mut rng, &still, &Displacement::ZERO, 50)).unwrap();
        let b = window_mean(&results(&mut rng, &still, &Displacement::ZERO, 50)).unwrap();
        assert!(settling(&a, &b).unwrap().settled());
        let moving = Displacement {
            rotation_arcsec: [0.0; 3],
            translation_mm: [0.1, 0.0, 0.0],
        };
        let c = window_mean(&results(&mut rng, &still, &moving, 50)).unwrap();
        assert!(!settling(&a, &c).unwrap().settled());
    }

    #[test]
    fn a_systematic_scale_error_is_carried_into_the_move_s_uncertainty() {
        // Systematic sigma along z growing with the depth (the same relative error): 1 mm at
        // the still pose, 1.01 mm at the step's; the move's z uncertainty holds 0.01 mm.
        let still = still_pose();
        let sys = |mm: f64| {
            Mat6::from_diagonal(&nalgebra::Vector6::new(0.0, 0.0, mm * mm, 0.0, 0.0, 0.0))
        };
        let s = WindowMean {
            count: 100,
            g_from_b: still,
            random_cov: Mat6::identity() * 1e-16,
            systematic_cov: sys(1.0),
        };
        let moved = Displacement {
            rotation_arcsec: [0.0; 3],
            translation_mm: [0.0, 0.0, 30.0],
        };
        // A pure translation along z of the still pose's base-frame z: take the translation
        // in G0's frame, so the base-frame systematic part shows along the same axis.
        let step = WindowMean {
            g_from_b: moved.g0_from_g().inverse() * still,
            systematic_cov: sys(1.01),
            ..s
        };
        let m = move_figures(&s, &step, &moved, &LIMITS).unwrap();
        let u_norm = Vec3::from([m.uncertainty[3], m.uncertainty[4], m.uncertainty[5]]).norm();
        assert!((u_norm - 0.01).abs() < 1e-3, "{m:?}");
    }

    #[test]
    fn standing_orders_failure_change_and_age() {
        let day = 86_400_000_000_000;
        assert_eq!(standing(true, 0, day, 2 * day, false), Standing::Valid);
        assert_eq!(standing(true, 0, 2 * day, 2 * day, false), Standing::Due);
        assert_eq!(
            standing(true, 0, day, 2 * day, true),
            Standing::NoLongerHolds
        );
        assert_eq!(standing(false, 0, day, 2 * day, true), Standing::Failed);
    }

    #[test]
    fn a_window_of_mixed_calibrations_has_none_in_common() {
        let a = Some(CalibrationStamp(1));
        assert_eq!(common_calibration([a, a]), a);
        assert_eq!(common_calibration([a, Some(CalibrationStamp(2))]), None);
        assert_eq!(common_calibration([a, None]), None);
        assert_eq!(common_calibration(Vec::new()), None);
    }
}
