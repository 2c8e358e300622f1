//! Averages of rotations and poses.
//!
//! The chordal L2 mean of rotations minimises `sum_i ||R - R_i||_F^2`: the arithmetic mean of
//! the matrices projected back onto SO(3) by SVD (Hartley et al. 2013, "Rotation averaging").
//! Translations are averaged arithmetically (see [`crate::deformation`]).

use super::{GeometryError, Mat3, Mat6, Pose, PoseCov, Rotation, Twist, se3_log};
use nalgebra::{Rotation3, Translation3};

/// The chordal L2 mean of a set of rotations.
pub fn chordal_mean_rotation(rotations: &[Rotation]) -> Result<Rotation, GeometryError> {
    if rotations.is_empty() {
        return Err(GeometryError::EmptyMean);
    }
    let sum: Mat3 = rotations
        .iter()
        .map(|r| r.to_rotation_matrix().into_inner())
        .fold(Mat3::zeros(), |acc, m| acc + m);
    let mean = sum / rotations.len() as f64;
    let svd = mean.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(GeometryError::NotARotation {
            reason: "the SVD of the mean matrix failed".into(),
        });
    };
    // Project onto SO(3), flipping the smallest singular direction if needed (det = +1).
    let mut d = Mat3::identity();
    if (u * v_t).determinant() < 0.0 {
        // nalgebra sorts singular values in decreasing order: the last is the smallest.
        d[(2, 2)] = -1.0;
    }
    let r = u * d * v_t;
    Ok(Rotation::from_rotation_matrix(
        &Rotation3::from_matrix_unchecked(r),
    ))
}

/// A mean pose with the spread of the samples around it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeanPose {
    /// The mean pose, with the covariance *of the mean* (sample scatter divided by the count).
    pub mean: PoseCov,
    /// How many poses were averaged.
    pub count: usize,
    /// The sample covariance of the individual poses about the mean (left perturbation).
    pub scatter: Mat6,
}

/// The mean of poses: chordal L2 mean of the rotations, arithmetic mean of the translations.
/// The covariance of the mean is the scatter of `Log(T_i * mean^-1)` divided by the count
/// (zero for a single pose, which then carries no estimate of its own spread).
pub fn mean_pose(poses: &[Pose]) -> Result<MeanPose, GeometryError> {
    if poses.is_empty() {
        return Err(GeometryError::EmptyMean);
    }
    let rotations: Vec<Rotation> = poses.iter().map(|p| p.rotation).collect();
    let rotation = chordal_mean_rotation(&rotations)?;
    let t_sum = poses.iter().fold(nalgebra::Vector3::zeros(), |acc, p| {
        acc + p.translation.vector
    });
    let mean = Pose::from_parts(Translation3::from(t_sum / poses.len() as f64), rotation);
    let n = poses.len();
    let mut scatter = Mat6::zeros();
    if n > 1 {
        let inv = mean.inverse();
        for p in poses {
            let e: Twist = se3_log(&(p * inv));
            scatter += e * e.transpose();
        }
        scatter /= (n - 1) as f64;
    }
    Ok(MeanPose {
        mean: PoseCov {
            pose: mean,
            cov: scatter / n as f64,
        },
        count: n,
        scatter,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{rotation_from_euler, so3_exp};
    use approx::assert_relative_eq;
    use nalgebra::Vector3;

    #[test]
    fn mean_of_symmetric_rotations_is_the_centre() {
        let centre = rotation_from_euler([0.3, -0.2, 2.0]).unwrap();
        let d = Vector3::new(0.01, 0.02, -0.015);
        let rotations = [so3_exp(&d) * centre, so3_exp(&(-d)) * centre];
        let mean = chordal_mean_rotation(&rotations).unwrap();
        assert_relative_eq!(mean.angle_to(&centre), 0.0, epsilon = 1e-12);
    }

    #[test]
    fn chordal_mean_minimises_the_chordal_cost() {
        let rotations: Vec<Rotation> = (0..7)
            .map(|i| {
                let f = i as f64;
                rotation_from_euler([0.1 * f, -0.05 * f * f, 0.3 - 0.07 * f]).unwrap()
            })
            .collect();
        let mean = chordal_mean_rotation(&rotations).unwrap();
        let cost = |r: &Rotation| -> f64 {
            rotations
                .iter()
                .map(|ri| {
                    (r.to_rotation_matrix().into_inner() - ri.to_rotation_matrix().into_inner())
                        .norm_squared()
                })
                .sum()
        };
        let best = cost(&mean);
        for axis in [Vector3::x(), Vector3::y(), Vector3::z()] {
            for step in [1e-3, -1e-3] {
                let nudged = so3_exp(&(axis * step)) * mean;
                assert!(
                    cost(&nudged) > best,
                    "a nudge of {step} about {axis:?} lowered the cost"
                );
            }
        }
    }

    #[test]
    fn empty_mean_is_an_error() {
        assert_eq!(mean_pose(&[]).unwrap_err(), GeometryError::EmptyMean);
    }
}
