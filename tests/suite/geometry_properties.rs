//! Property tests of the SE(3) core: group laws, Exp/Log, the adjoint, the Euler convention.

use approx::assert_relative_eq;
use brokenray::geometry::{
    Pose, Rotation, Twist, Vec3, adjoint, euler_from_rotation, quaternion_wxyz,
    rotation_from_euler, rotation_from_matrix, rotation_from_quaternion_wxyz, se3_exp, se3_log,
    so3_exp, so3_log,
};
use nalgebra::{Matrix3, Matrix4, Quaternion, Translation3};
use proptest::prelude::*;

fn rotation_strategy() -> impl Strategy<Value = Rotation> {
    (-1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64, -1.0..1.0f64)
        .prop_filter("non-degenerate quaternion", |(w, x, y, z)| {
            w * w + x * x + y * y + z * z > 1e-2
        })
        .prop_map(|(w, x, y, z)| Rotation::new_normalize(Quaternion::new(w, x, y, z)))
}

fn pose_strategy() -> impl Strategy<Value = Pose> {
    (
        rotation_strategy(),
        -5000.0..5000.0f64,
        -5000.0..5000.0f64,
        -5000.0..5000.0f64,
    )
        .prop_map(|(r, x, y, z)| Pose::from_parts(Translation3::new(x, y, z), r))
}

/// Twists whose rotation angle stays below pi (where Log is the inverse of Exp).
fn twist_strategy() -> impl Strategy<Value = Twist> {
    (
        prop::array::uniform3(-3000.0..3000.0f64),
        prop::array::uniform3(-1.0..1.0f64),
        0.0..3.1f64,
    )
        .prop_map(|(rho, axis, angle)| {
            let axis = Vec3::from(axis);
            let phi = if axis.norm() < 1e-6 {
                Vec3::zeros()
            } else {
                axis.normalize() * angle
            };
            Twist::new(rho[0], rho[1], rho[2], phi.x, phi.y, phi.z)
        })
}

/// The 4x4 matrix `[[R, t], [0, 1]]`, written out independently of nalgebra's Isometry.
fn matrix4(p: &Pose) -> Matrix4<f64> {
    let r = p.rotation.to_rotation_matrix().into_inner();
    let t = p.translation.vector;
    Matrix4::new(
        r[(0, 0)],
        r[(0, 1)],
        r[(0, 2)],
        t.x,
        r[(1, 0)],
        r[(1, 1)],
        r[(1, 2)],
        t.y,
        r[(2, 0)],
        r[(2, 1)],
        r[(2, 2)],
        t.z,
        0.0,
        0.0,
        0.0,
        1.0,
    )
}

fn rx(a: f64) -> Matrix3<f64> {
    let (s, c) = a.sin_cos();
    Matrix3::new(1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c)
}
fn ry(a: f64) -> Matrix3<f64> {
    let (s, c) = a.sin_cos();
    Matrix3::new(c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c)
}
fn rz(a: f64) -> Matrix3<f64> {
    let (s, c) = a.sin_cos();
    Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn inverse_times_pose_is_identity(a in pose_strategy()) {
        let product = matrix4(&a.inverse()) * matrix4(&a);
        prop_assert!((product - Matrix4::identity()).amax() < 1e-9, "{product}");
    }

    #[test]
    fn composition_is_associative(a in pose_strategy(), b in pose_strategy(), c in pose_strategy()) {
        let left = matrix4(&((a * b) * c));
        let right = matrix4(&(a * (b * c)));
        prop_assert!((left - right).amax() < 1e-7);
        // And equal to the plain matrix product.
        prop_assert!((left - matrix4(&a) * matrix4(&b) * matrix4(&c)).amax() < 1e-7);
    }

    #[test]
    fn se3_log_inverts_exp(xi in twist_strategy()) {
        let back = se3_log(&se3_exp(&xi));
        prop_assert!((back - xi).amax() < 1e-7 * (1.0 + xi.amax()), "{xi} -> {back}");
    }

    #[test]
    fn se3_exp_inverts_log(p in pose_strategy()) {
        let back = se3_exp(&se3_log(&p));
        prop_assert!((matrix4(&back) - matrix4(&p)).amax() < 1e-7);
    }

    #[test]
    fn so3_exp_log_round_trip(axis in prop::array::uniform3(-1.0..1.0f64), angle in 0.0..3.1f64) {
        let axis = Vec3::from(axis);
        prop_assume!(axis.norm() > 1e-3);
        let phi = axis.normalize() * angle;
        prop_assert!((so3_log(&so3_exp(&phi)) - phi).amax() < 1e-9);
    }

    #[test]
    fn adjoint_moves_a_perturbation_across_a_pose(t in pose_strategy(), xi in twist_strategy()) {
        let xi = xi * 0.1;
        let lhs = t * se3_exp(&xi) * t.inverse();
        let rhs = se3_exp(&(adjoint(&t) * xi));
        prop_assert!((matrix4(&lhs) - matrix4(&rhs)).amax() < 1e-6 * (1.0 + t.translation.vector.amax()));
    }

    #[test]
    fn euler_round_trip_away_from_gimbal_lock(
        ax in -179.9..180.0f64, ay in -89.0..89.0f64, az in -179.9..180.0f64
    ) {
        let r = rotation_from_euler([ax.to_radians(), ay.to_radians(), az.to_radians()]).unwrap();
        let e = euler_from_rotation(&r);
        prop_assert!(!e.is_degenerate);
        let back = e.to_degrees();
        for (got, want) in back.iter().zip([ax, ay, az]) {
            prop_assert!((got - want).abs() < 1e-8, "{back:?} vs {:?}", [ax, ay, az]);
        }
    }

    #[test]
    fn euler_convention_is_rz_ry_rx_about_fixed_axes(
        ax in -3.1..3.1f64, ay in -1.5..1.5f64, az in -3.1..3.1f64
    ) {
        let ours = rotation_from_euler([ax, ay, az]).unwrap().to_rotation_matrix().into_inner();
        let explicit = rz(az) * ry(ay) * rx(ax);
        prop_assert!((ours - explicit).amax() < 1e-12);
        // Reading the angles back from the explicit product gives the same angles.
        let r = rotation_from_matrix([
            [explicit[(0, 0)], explicit[(0, 1)], explicit[(0, 2)]],
            [explicit[(1, 0)], explicit[(1, 1)], explicit[(1, 2)]],
            [explicit[(2, 0)], explicit[(2, 1)], explicit[(2, 2)]],
        ]).unwrap();
        let e = euler_from_rotation(&r).angles_rad;
        prop_assert!((e[0] - ax).abs() < 1e-9 && (e[1] - ay).abs() < 1e-9 && (e[2] - az).abs() < 1e-9);
    }

    #[test]
    fn quaternion_output_round_trips_with_non_negative_w(r in rotation_strategy()) {
        let q = quaternion_wxyz(&r);
        prop_assert!(q[0] >= 0.0);
        let back = rotation_from_quaternion_wxyz(q).unwrap();
        prop_assert!(back.angle_to(&r) < 1e-9);
    }
}

#[test]
fn a_quarter_turn_about_z_maps_x_to_y() {
    let r = rotation_from_euler([0.0, 0.0, 90f64.to_radians()]).unwrap();
    assert_relative_eq!(r * Vec3::x(), Vec3::y(), epsilon = 1e-15);
}

/// `PoseCov::interpolate` against independent constructions: the ends are the two poses, a pure
/// rotation about a fixed axis turns by the fraction of its angle about that axis (Rodrigues'
/// angle read back from the quaternion), and interpolating halfway to the midpoint equals
/// interpolating a quarter of the way (a geodesic at constant speed). Covariances mix linearly.
mod interpolation {
    use super::*;
    use brokenray::geometry::{Mat6, PoseCov};

    fn with_cov(pose: Pose, scale: f64) -> PoseCov {
        PoseCov {
            pose,
            cov: Mat6::identity() * scale,
        }
    }

    proptest! {
        #[test]
        fn ends_and_constant_speed(t0 in pose_strategy(), t1 in pose_strategy(), a in 0.0..1.0f64) {
            prop_assume!(so3_log(&(t1.rotation * t0.rotation.inverse())).norm() < 3.0);
            let (p0, p1) = (with_cov(t0, 1.0), with_cov(t1, 3.0));
            let start = p0.interpolate(&p1, 0.0);
            let end = p0.interpolate(&p1, 1.0);
            prop_assert!(se3_log(&(start.pose * t0.inverse())).norm() < 1e-9);
            prop_assert!(se3_log(&(end.pose * t1.inverse())).norm() < 1e-6);
            let quarter = p0.interpolate(&p1, 0.25);
            let half_of_half = p0.interpolate(&p0.interpolate(&p1, 0.5), 0.5);
            prop_assert!(se3_log(&(quarter.pose * half_of_half.pose.inverse())).norm() < 1e-6);
            let mixed = p0.interpolate(&p1, a).cov;
            prop_assert!((mixed - Mat6::identity() * (1.0 + 2.0 * a)).norm() < 1e-12);
        }
    }

    #[test]
    fn a_pure_rotation_turns_by_the_fraction_of_its_angle() {
        let axis = Vec3::new(1.0, -2.0, 0.5).normalize();
        let angle = 0.8;
        let t0 = Pose::from_parts(Translation3::new(10.0, 20.0, 30.0), Rotation::identity());
        let turn = Pose::from_parts(
            Translation3::identity(),
            Rotation::from_axis_angle(&nalgebra::Unit::new_normalize(axis), angle),
        );
        let t1 = turn * t0;
        let mid = with_cov(t0, 1.0).interpolate(&with_cov(t1, 1.0), 0.3).pose;
        let delta = mid * t0.inverse();
        let q = delta.rotation.into_inner();
        let turned = 2.0 * q.imag().norm().atan2(q.w);
        assert!((turned - 0.3 * angle).abs() < 1e-12, "turned {turned}");
        assert!((q.imag().normalize() - axis).norm() < 1e-12);
        // The point on the axis through the origin: turning about it moves the origin's image
        // on the same rotation, so the translation is R(0.3 angle) applied to t0's.
        let expected = Rotation::from_axis_angle(&nalgebra::Unit::new_normalize(axis), 0.3 * angle)
            * Vec3::new(10.0, 20.0, 30.0);
        assert!((mid.translation.vector - expected).norm() < 1e-9);
    }
}
