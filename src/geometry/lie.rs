//! Exp and Log on SO(3) and SE(3), their left Jacobians, and the adjoint.
//!
//! Tangent order `[rho; phi]`; see the module docs of [`crate::geometry`]. Every map has a series
//! form near zero angle so that no division by a tiny angle happens.

use super::{Mat3, Mat6, Pose, Rotation, Twist, Vec3};
use nalgebra::{Quaternion, Translation3};

/// Below this angle (rad) the closed forms switch to their Taylor series.
const SMALL_ANGLE_RAD: f64 = 1e-5;

/// The skew-symmetric matrix `[v]x` such that `[v]x w = v x w`.
#[inline]
pub fn skew(v: &Vec3) -> Mat3 {
    Mat3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// Exp on SO(3): the rotation by angle `|phi|` about `phi / |phi|`.
pub fn so3_exp(phi: &Vec3) -> Rotation {
    let theta_sq = phi.norm_squared();
    let theta = theta_sq.sqrt();
    let half = 0.5 * theta;
    // sin(theta/2)/theta, with its series near zero.
    let (w, k) = if theta < SMALL_ANGLE_RAD {
        (1.0 - theta_sq / 8.0, 0.5 - theta_sq / 48.0)
    } else {
        (half.cos(), half.sin() / theta)
    };
    Rotation::new_unchecked(Quaternion::new(w, k * phi.x, k * phi.y, k * phi.z))
}

/// Log on SO(3): the rotation vector (rad) with angle in [0, pi].
pub fn so3_log(rotation: &Rotation) -> Vec3 {
    let q = rotation.quaternion();
    // Use the representative with w >= 0 so the angle is in [0, pi].
    let (w, v) = if q.w < 0.0 {
        (-q.w, -q.imag())
    } else {
        (q.w, q.imag())
    };
    let s = v.norm();
    if s < SMALL_ANGLE_RAD {
        // 2 atan(s/w)/s ~= 2/w (1 - s^2/(3 w^2)).
        let w_sq = w * w;
        v * (2.0 / w) * (1.0 - s * s / (3.0 * w_sq))
    } else {
        v * (2.0 * s.atan2(w) / s)
    }
}

/// Coefficients `(a, b)` of `J = I + a [phi]x + b [phi]x^2` for the SO(3) left Jacobian.
fn so3_jacobian_coefficients(theta: f64) -> (f64, f64) {
    let theta_sq = theta * theta;
    if theta < SMALL_ANGLE_RAD {
        (0.5 - theta_sq / 24.0, 1.0 / 6.0 - theta_sq / 120.0)
    } else {
        (
            (1.0 - theta.cos()) / theta_sq,
            (theta - theta.sin()) / (theta_sq * theta),
        )
    }
}

/// The left Jacobian of SO(3): `Exp(phi + d) ~= Exp(J(phi) d) Exp(phi)`.
pub fn so3_left_jacobian(phi: &Vec3) -> Mat3 {
    let (a, b) = so3_jacobian_coefficients(phi.norm());
    let phi_x = skew(phi);
    Mat3::identity() + phi_x * a + phi_x * phi_x * b
}

/// The inverse of the SO(3) left Jacobian (valid for angles below 2 pi).
pub fn so3_left_jacobian_inv(phi: &Vec3) -> Mat3 {
    let theta = phi.norm();
    let theta_sq = theta * theta;
    let c = if theta < SMALL_ANGLE_RAD {
        1.0 / 12.0 + theta_sq / 720.0
    } else {
        1.0 / theta_sq - (1.0 + theta.cos()) / (2.0 * theta * theta.sin())
    };
    let phi_x = skew(phi);
    Mat3::identity() - phi_x * 0.5 + phi_x * phi_x * c
}

/// Exp on SE(3): `[rho; phi] -> (Exp(phi), J(phi) rho)`.
pub fn se3_exp(xi: &Twist) -> Pose {
    let rho = xi.fixed_rows::<3>(0).into_owned();
    let phi = xi.fixed_rows::<3>(3).into_owned();
    let t = so3_left_jacobian(&phi) * rho;
    Pose::from_parts(Translation3::from(t), so3_exp(&phi))
}

/// Log on SE(3), the inverse of [`se3_exp`] (rotation angle in [0, pi]).
pub fn se3_log(pose: &Pose) -> Twist {
    let phi = so3_log(&pose.rotation);
    let rho = so3_left_jacobian_inv(&phi) * pose.translation.vector;
    Twist::new(rho.x, rho.y, rho.z, phi.x, phi.y, phi.z)
}

/// The 6x6 adjoint `Ad(T) = [[R, [t]x R], [0, R]]`, so that `T Exp(xi) T^-1 = Exp(Ad(T) xi)`.
pub fn adjoint(pose: &Pose) -> Mat6 {
    let r = pose.rotation.to_rotation_matrix().into_inner();
    let tx_r = skew(&pose.translation.vector) * r;
    let mut ad = Mat6::zeros();
    ad.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    ad.fixed_view_mut::<3, 3>(0, 3).copy_from(&tx_r);
    ad.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    ad
}

/// Barfoot's `Q(rho, phi)` block of the SE(3) left Jacobian.
fn se3_q(rho: &Vec3, phi: &Vec3) -> Mat3 {
    let theta = phi.norm();
    let theta_sq = theta * theta;
    let (c1, c2, c3) = if theta < 1e-3 {
        // Series of the three coefficients below, accurate to O(theta^4).
        (
            1.0 / 6.0 - theta_sq / 120.0,
            1.0 / 24.0 - theta_sq / 720.0,
            1.0 / 120.0 - theta_sq / 2520.0,
        )
    } else {
        let (s, c) = theta.sin_cos();
        let t3 = theta_sq * theta;
        let t4 = theta_sq * theta_sq;
        let t5 = t4 * theta;
        (
            (theta - s) / t3,
            (theta_sq + 2.0 * c - 2.0) / (2.0 * t4),
            (2.0 * theta - 3.0 * s + theta * c) / (2.0 * t5),
        )
    };
    let rx = skew(rho);
    let px = skew(phi);
    let px_rx = px * rx;
    let rx_px = rx * px;
    let px_rx_px = px_rx * px;
    let px_px = px * px;
    rx * 0.5
        + (px_rx + rx_px + px_rx_px) * c1
        + (px_px * rx + rx_px * px - px_rx_px * 3.0) * c2
        + (px_rx_px * px + px_px * rx * px) * c3
}

/// The left Jacobian of SE(3): `Exp(xi + d) ~= Exp(J(xi) d) Exp(xi)`.
pub fn se3_left_jacobian(xi: &Twist) -> Mat6 {
    let rho = xi.fixed_rows::<3>(0).into_owned();
    let phi = xi.fixed_rows::<3>(3).into_owned();
    let j = so3_left_jacobian(&phi);
    let mut out = Mat6::zeros();
    out.fixed_view_mut::<3, 3>(0, 0).copy_from(&j);
    out.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&se3_q(&rho, &phi));
    out.fixed_view_mut::<3, 3>(3, 3).copy_from(&j);
    out
}

/// The inverse of the SE(3) left Jacobian: `Log(Exp(d) Exp(xi)) ~= xi + J^-1(xi) d`.
pub fn se3_left_jacobian_inv(xi: &Twist) -> Mat6 {
    let rho = xi.fixed_rows::<3>(0).into_owned();
    let phi = xi.fixed_rows::<3>(3).into_owned();
    let j_inv = so3_left_jacobian_inv(&phi);
    let q = se3_q(&rho, &phi);
    let mut out = Mat6::zeros();
    out.fixed_view_mut::<3, 3>(0, 0).copy_from(&j_inv);
    out.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&(-(j_inv * q * j_inv)));
    out.fixed_view_mut::<3, 3>(3, 3).copy_from(&j_inv);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn so3_log_of_half_turn_has_angle_pi() {
        let phi = Vec3::new(0.0, std::f64::consts::PI, 0.0);
        let back = so3_log(&so3_exp(&phi));
        assert_relative_eq!(back.norm(), std::f64::consts::PI, epsilon = 1e-12);
    }

    #[test]
    fn series_and_closed_form_agree_at_the_switch() {
        let phi = Vec3::new(1.0, -2.0, 0.5).normalize() * (SMALL_ANGLE_RAD * 1.0001);
        let phi_small = phi * 0.9998;
        assert_relative_eq!(
            so3_left_jacobian(&phi),
            so3_left_jacobian(&phi_small),
            epsilon = 1e-9
        );
        assert_relative_eq!(
            so3_left_jacobian_inv(&phi),
            so3_left_jacobian_inv(&phi_small),
            epsilon = 1e-9
        );
    }

    #[test]
    fn se3_jacobian_inverse_is_the_inverse() {
        let xi = Twist::new(120.0, -40.0, 900.0, 0.3, -0.2, 0.9);
        let product = se3_left_jacobian(&xi) * se3_left_jacobian_inv(&xi);
        assert_relative_eq!(product, Mat6::identity(), epsilon = 1e-9);
    }

    #[test]
    fn se3_left_jacobian_matches_finite_differences() {
        // Exp(xi + d) Exp(xi)^-1 ~= Exp(J d): compare J column by column.
        let xi = Twist::new(35.0, -12.0, 250.0, 0.4, 0.1, -0.7);
        let j = se3_left_jacobian(&xi);
        let h = 1e-6;
        for k in 0..6 {
            let mut d = Twist::zeros();
            d[k] = h;
            let col = se3_log(&(se3_exp(&(xi + d)) * se3_exp(&xi).inverse())) / h;
            for r in 0..6 {
                assert!(
                    (col[r] - j[(r, k)]).abs() < 1e-4 * (1.0 + j[(r, k)].abs()),
                    "J[{r},{k}] = {} but finite difference gives {}",
                    j[(r, k)],
                    col[r]
                );
            }
        }
    }
}
