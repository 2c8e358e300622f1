//! Helpers shared by the integration tests: random poses and covariances, seeded.
#![allow(dead_code)]

pub mod hostile;
pub mod paper;
pub mod postgres;
pub mod process;

use brokenray::geometry::{Mat6, Pose, Rotation, Twist, Vec3, se3_exp};
use nalgebra::{Quaternion, Translation3};
use rand::Rng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, StandardNormal};

/// A pose with a uniformly random rotation and a translation within +-`reach_mm` per axis.
/// A random rigid motion of up to `mm` and `deg` per axis.
pub fn jolt(rng: &mut StdRng, mm: f64, deg: f64) -> Pose {
    let r = deg.to_radians();
    se3_exp(&Twist::new(
        rng.random_range(-mm..mm),
        rng.random_range(-mm..mm),
        rng.random_range(-mm..mm),
        rng.random_range(-r..r),
        rng.random_range(-r..r),
        rng.random_range(-r..r),
    ))
}

pub fn random_pose(rng: &mut StdRng, reach_mm: f64) -> Pose {
    let q = Quaternion::new(
        rng.sample::<f64, _>(StandardNormal),
        rng.sample::<f64, _>(StandardNormal),
        rng.sample::<f64, _>(StandardNormal),
        rng.sample::<f64, _>(StandardNormal),
    );
    let t = Vec3::new(
        rng.random_range(-reach_mm..reach_mm),
        rng.random_range(-reach_mm..reach_mm),
        rng.random_range(-reach_mm..reach_mm),
    );
    Pose::from_parts(Translation3::from(t), Rotation::new_normalize(q))
}

/// A random symmetric positive-definite covariance with rotation sigmas near `rot_arcsec` and
/// translation sigmas near `trans_mm`, correlated.
pub fn random_covariance(rng: &mut StdRng, rot_arcsec: f64, trans_mm: f64) -> Mat6 {
    let rot_rad = rot_arcsec / brokenray::geometry::ARCSEC_PER_RAD;
    let scale = [trans_mm, trans_mm, trans_mm, rot_rad, rot_rad, rot_rad];
    let a = Mat6::from_fn(|_, _| rng.sample::<f64, _>(StandardNormal));
    let correlated = (a * a.transpose()) / 6.0 + Mat6::identity() * 0.5;
    Mat6::from_fn(|r, c| correlated[(r, c)] * scale[r] * scale[c])
}

/// A draw of `xi ~ N(0, cov)`.
pub fn sample_twist(rng: &mut StdRng, cov: &Mat6) -> Twist {
    let l = cov.cholesky().expect("covariance is positive definite").l();
    let z = Twist::from_fn(|_, _| StandardNormal.sample(rng));
    l * z
}

/// `Exp(xi) * pose` with `xi ~ N(0, cov)`: a draw from a pose's left-perturbation distribution.
pub fn perturb(rng: &mut StdRng, pose: &Pose, cov: &Mat6) -> Pose {
    se3_exp(&sample_twist(rng, cov)) * pose
}

/// The normalized estimation error squared of an estimate against the truth:
/// `e^T cov^-1 e` with `e = Log(estimate * truth^-1)`, the left perturbation of the covariance.
pub fn nees(estimate: &Pose, truth: &Pose, cov: &Mat6) -> f64 {
    let e = brokenray::geometry::se3_log(&(estimate * truth.inverse()));
    let info = cov.try_inverse().expect("an invertible covariance");
    (e.transpose() * info * e)[(0, 0)]
}

/// Asserts that a NEES summed over `trials` 6-dof estimates lies between the chi-square
/// quantiles `tail` and `1 - tail` of `6 * trials` degrees of freedom.
pub fn assert_summed_nees_within(nees_sum: f64, trials: usize, tail: f64) {
    let dof = 6 * trials;
    let lower = brokenray::chain::chi_square_quantile(dof, tail);
    let upper = brokenray::chain::chi_square_quantile(dof, 1.0 - tail);
    assert!(
        (lower..=upper).contains(&nees_sum),
        "summed NEES {nees_sum:.1} outside [{lower:.1}, {upper:.1}] of chi2({dof}) (mean {:.3}, expected 6)",
        nees_sum / trials as f64
    );
}
