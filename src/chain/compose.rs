//! Composition of a path's link poses with covariance propagation.

use super::{Direction, Path};
use crate::geometry::{PoseCov, symmetrize, transform_covariance};

/// Composes a path into `target_from_base` with its covariance, the links treated as
/// independent. `parent_from_child` gives each link's pose (a filtered estimate, a raw sample
/// or a calibration).
///
/// Walking forwards through link `L`: `acc <- L * acc`, `Sigma <- Sigma_L + Ad(L) Sigma Ad(L)^T`.
/// Walking inverted: `acc <- L^-1 * acc`, `Sigma <- Ad(L^-1) (Sigma_L + Sigma) Ad(L^-1)^T`
/// (one covariance transform per step either way).
pub fn compose_path<F>(path: &Path, mut parent_from_child: F) -> PoseCov
where
    F: FnMut(super::LinkId) -> PoseCov,
{
    let mut acc = PoseCov::identity();
    for step in &path.steps {
        let link = parent_from_child(step.link);
        match step.direction {
            Direction::Forward => {
                acc = PoseCov {
                    pose: link.pose * acc.pose,
                    cov: symmetrize(&(link.cov + transform_covariance(&link.pose, &acc.cov))),
                };
            }
            Direction::Inverse => {
                let inv = link.pose.inverse();
                acc = PoseCov {
                    pose: inv * acc.pose,
                    cov: transform_covariance(&inv, &(link.cov + acc.cov)),
                };
            }
        }
    }
    acc
}
