//! Helpers shared by the integration tests: random poses and covariances, seeded.
#![allow(dead_code)]

pub mod paper;

use brokenray::geometry::{Mat6, Pose, Rotation, Twist, Vec3, se3_exp};
use nalgebra::{Quaternion, Translation3};
use rand::Rng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, StandardNormal};

/// A pose with a uniformly random rotation and a translation within +-`reach_mm` per axis.
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
