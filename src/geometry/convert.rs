//! Conversions between rotation representations, each validated.
//!
//! Quaternions `[w, x, y, z]`, row-major 3x3 matrices and Euler angles
//! `R = Rz(Az) * Ry(Ay) * Rx(Ax)` (see [`crate::geometry`]). Input that is not finite, a
//! quaternion that is not close to unit length, or a matrix that is not a proper rotation is a
//! typed [`GeometryError`], never a silently "fixed" rotation.

use super::{GeometryError, Mat3, Pose, Rotation, Vec3};
use nalgebra::{Quaternion, Rotation3, Translation3};

/// Arc-seconds in one radian.
pub const ARCSEC_PER_RAD: f64 = 180.0 * 3600.0 / std::f64::consts::PI;

/// How far from 1 a quaternion's norm may be before it is refused (it is normalised otherwise).
pub(super) const QUATERNION_NORM_TOLERANCE: f64 = 1e-3;

/// How far `R^T R` may be from the identity (max abs entry) for a matrix to count as a rotation.
pub(super) const ROTATION_ORTHOGONALITY_TOLERANCE: f64 = 1e-6;

/// The largest translation component a pose may have (mm): 100 km. Every structure this
/// service measures is far smaller; a larger number is a unit mistake or garbage, and letting
/// it in would overflow sums of squares in statistics and rollups.
pub const MAX_TRANSLATION_MM: f64 = 1e8;

/// The largest Euler angle accepted as input (degrees): two full turns either way.
pub const MAX_EULER_DEG: f64 = 720.0;

/// The largest rotation sigma accepted as input (arc-seconds): about 4.8 rad, past any
/// meaningful rotation uncertainty.
pub const MAX_ROTATION_SIGMA_ARCSEC: f64 = 1e6;

/// The largest translation sigma accepted as input (mm), the same as the largest translation.
pub const MAX_TRANSLATION_SIGMA_MM: f64 = MAX_TRANSLATION_MM;

/// Below this `cos(Ay)` the Euler angles are treated as degenerate (gimbal lock).
const GIMBAL_LOCK_COS: f64 = 1e-9;

/// Checks that every number is finite; `what` names the quantity in the error (`t_mm[1]`).
pub fn validate_finite(what: &str, values: &[f64]) -> Result<(), GeometryError> {
    for (i, &value) in values.iter().enumerate() {
        if !value.is_finite() {
            return Err(GeometryError::NonFinite {
                what: format!("{what}[{i}]"),
                value,
            });
        }
    }
    Ok(())
}

/// Checks that every number's magnitude is at most `limit` (plausibility: see
/// [`MAX_TRANSLATION_MM`]); `what` names the quantity in the error.
pub fn check_magnitude(
    what: &str,
    values: &[f64],
    limit: f64,
    unit: &'static str,
) -> Result<(), GeometryError> {
    match values.iter().enumerate().find(|(_, v)| v.abs() > limit) {
        Some((i, &value)) => Err(GeometryError::Implausible {
            what: format!("{what}[{i}]"),
            value,
            limit,
            unit,
        }),
        None => Ok(()),
    }
}

/// A unit quaternion from `[w, x, y, z]`; normalised when its norm is within 1e-3 of 1.
pub fn rotation_from_quaternion_wxyz(q_wxyz: [f64; 4]) -> Result<Rotation, GeometryError> {
    validate_finite("q_wxyz", &q_wxyz)?;
    let q = Quaternion::new(q_wxyz[0], q_wxyz[1], q_wxyz[2], q_wxyz[3]);
    let norm = q.norm();
    if (norm - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
        return Err(GeometryError::QuaternionNotUnit {
            norm,
            tolerance: QUATERNION_NORM_TOLERANCE,
        });
    }
    Ok(Rotation::new_normalize(q))
}

/// The quaternion `[w, x, y, z]` of a rotation, with `w >= 0`.
pub fn quaternion_wxyz(rotation: &Rotation) -> [f64; 4] {
    let q = rotation.quaternion();
    let sign = if q.w < 0.0 { -1.0 } else { 1.0 };
    [sign * q.w, sign * q.i, sign * q.j, sign * q.k]
}

/// A rotation from a row-major 3x3 matrix; refused unless orthonormal (1e-6) with determinant +1.
pub fn rotation_from_matrix(rows: [[f64; 3]; 3]) -> Result<Rotation, GeometryError> {
    for (i, row) in rows.iter().enumerate() {
        validate_finite(&format!("r[{i}]"), row)?;
    }
    let m = Mat3::from_fn(|r, c| rows[r][c]);
    let orthogonality = (m.transpose() * m - Mat3::identity()).amax();
    if orthogonality > ROTATION_ORTHOGONALITY_TOLERANCE {
        return Err(GeometryError::NotARotation {
            reason: format!(
                "R^T R differs from the identity by {orthogonality:.3e} (tolerance {ROTATION_ORTHOGONALITY_TOLERANCE:.0e})"
            ),
        });
    }
    let det = m.determinant();
    if det < 0.0 {
        return Err(GeometryError::NotARotation {
            reason: format!("determinant is {det:.6} (a reflection, not a rotation)"),
        });
    }
    Ok(Rotation::from_rotation_matrix(
        &Rotation3::from_matrix_unchecked(m),
    ))
}

/// Euler angles `[Ax, Ay, Az]` in radians, `R = Rz(Az) Ry(Ay) Rx(Ax)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EulerAngles {
    /// `[Ax, Ay, Az]` in radians.
    pub angles_rad: [f64; 3],
    /// True when `Ay` is at +-90 degrees, where only `Az - Ax` (or `Az + Ax`) is defined; `Ax`
    /// is then reported as 0.
    pub is_degenerate: bool,
}

impl EulerAngles {
    /// The angles in degrees.
    pub fn to_degrees(&self) -> [f64; 3] {
        self.angles_rad.map(f64::to_degrees)
    }
}

/// The rotation `Rz(Az) * Ry(Ay) * Rx(Ax)` for `[Ax, Ay, Az]` in radians.
pub fn rotation_from_euler(angles_rad: [f64; 3]) -> Result<Rotation, GeometryError> {
    validate_finite("euler", &angles_rad)?;
    let limit = MAX_EULER_DEG.to_radians();
    if let Some((i, &value)) = angles_rad.iter().enumerate().find(|(_, a)| a.abs() > limit) {
        return Err(GeometryError::Implausible {
            what: format!("euler[{i}]"),
            value: value.to_degrees(),
            limit: MAX_EULER_DEG,
            unit: "degrees",
        });
    }
    let [ax, ay, az] = angles_rad;
    Ok(Rotation::from_euler_angles(ax, ay, az))
}

/// Maps an angle in (-pi, pi] (atan2 can return -pi for a negative zero).
fn wrap_half_open(angle: f64) -> f64 {
    if angle <= -std::f64::consts::PI {
        angle + 2.0 * std::f64::consts::PI
    } else {
        angle
    }
}

/// The Euler angles of a rotation: Ax, Az in (-pi, pi], Ay in [-pi/2, pi/2]. Never NaN: at
/// gimbal lock `Ax = 0` and the flag is set.
pub fn euler_from_rotation(rotation: &Rotation) -> EulerAngles {
    let m = rotation.to_rotation_matrix().into_inner();
    let cos_ay = m[(0, 0)].hypot(m[(1, 0)]);
    let ay = (-m[(2, 0)]).atan2(cos_ay);
    if cos_ay > GIMBAL_LOCK_COS {
        EulerAngles {
            angles_rad: [
                wrap_half_open(m[(2, 1)].atan2(m[(2, 2)])),
                ay,
                wrap_half_open(m[(1, 0)].atan2(m[(0, 0)])),
            ],
            is_degenerate: false,
        }
    } else {
        // R = Rz(Az) Ry(+-90) Rx(Ax) only fixes Az -+ Ax; report Ax = 0.
        EulerAngles {
            angles_rad: [0.0, ay, wrap_half_open((-m[(0, 1)]).atan2(m[(1, 1)]))],
            is_degenerate: true,
        }
    }
}

/// A pose from a translation (mm) and a rotation, the translation checked for finiteness.
pub fn pose_from_parts(t_mm: [f64; 3], rotation: Rotation) -> Result<Pose, GeometryError> {
    validate_finite("t_mm", &t_mm)?;
    check_magnitude("t_mm", &t_mm, MAX_TRANSLATION_MM, "mm")?;
    Ok(Pose::from_parts(
        Translation3::from(Vec3::from(t_mm)),
        rotation,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn non_unit_quaternion_is_refused() {
        let err = rotation_from_quaternion_wxyz([1.0, 0.1, 0.0, 0.0]).unwrap_err();
        assert!(
            matches!(err, GeometryError::QuaternionNotUnit { .. }),
            "{err}"
        );
    }

    #[test]
    fn nearly_unit_quaternion_is_normalised() {
        let q = rotation_from_quaternion_wxyz([1.0005, 0.0, 0.0, 0.0]).unwrap();
        assert_relative_eq!(q.quaternion().norm(), 1.0, epsilon = 1e-15);
    }

    #[test]
    fn nan_in_a_quaternion_is_named() {
        let err = rotation_from_quaternion_wxyz([1.0, f64::NAN, 0.0, 0.0]).unwrap_err();
        assert_eq!(err.to_string(), "q_wxyz[1] is not a finite number (NaN)");
    }

    #[test]
    fn reflection_is_not_a_rotation() {
        let err =
            rotation_from_matrix([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]).unwrap_err();
        assert!(err.to_string().contains("determinant"), "{err}");
    }

    #[test]
    fn sheared_matrix_is_not_a_rotation() {
        let err =
            rotation_from_matrix([[1.0, 0.01, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]).unwrap_err();
        assert!(err.to_string().contains("R^T R"), "{err}");
    }

    #[test]
    fn output_quaternion_has_non_negative_w() {
        let q = Rotation::new_unchecked(Quaternion::new(-0.5, 0.5, 0.5, 0.5));
        let wxyz = quaternion_wxyz(&q);
        assert_eq!(wxyz, [0.5, -0.5, -0.5, -0.5]);
    }

    #[test]
    fn gimbal_lock_is_reported_not_nan() {
        for ay in [90.0_f64, -90.0] {
            let r = rotation_from_euler([0.3, ay.to_radians(), 1.1]).unwrap();
            let e = euler_from_rotation(&r);
            assert!(e.is_degenerate);
            assert!(e.angles_rad.iter().all(|a| a.is_finite()));
            let back = rotation_from_euler(e.angles_rad).unwrap();
            assert_relative_eq!(back.angle_to(&r), 0.0, epsilon = 1e-7);
        }
    }

    #[test]
    fn half_turn_yaw_reports_plus_180() {
        let r = rotation_from_euler([0.0, 0.0, std::f64::consts::PI]).unwrap();
        let e = euler_from_rotation(&r).to_degrees();
        assert_relative_eq!(e[2], 180.0, epsilon = 1e-9);
    }
}
