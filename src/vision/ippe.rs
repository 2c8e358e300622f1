//! IPPE (Collins and Bartoli, IJCV 2014): the initialiser for planar markers.
//!
//! The homography from the marker plane to the normalized image is estimated (normalized DLT);
//! its Jacobian at the plane's origin determines the rotation up to the two-fold ambiguity of a
//! plane seen in perspective. Both rotations are returned, each with its least-squares
//! translation, so that refinement can keep the better and report how close the other came.

use super::sqpnp::nearest_rotation;
use crate::geometry::{Mat3, Vec3};
use nalgebra::{Matrix2, SMatrix, Vector2};

/// The two candidate `camera_from_plane` poses of points `(X, Y, 0)` centred on the origin.
pub(super) fn candidates(
    plane_xy: &[Vector2<f64>],
    normalized: &[Vector2<f64>],
) -> Vec<(Mat3, Vec3)> {
    let Some(h) = homography(plane_xy, normalized) else {
        return Vec::new();
    };
    if h[(2, 2)].abs() < f64::EPSILON {
        return Vec::new();
    }
    let h = h / h[(2, 2)];
    let v = Vector2::new(h[(0, 2)], h[(1, 2)]);
    let jac = Matrix2::new(
        h[(0, 0)] - h[(2, 0)] * v.x,
        h[(0, 1)] - h[(2, 1)] * v.x,
        h[(1, 0)] - h[(2, 0)] * v.y,
        h[(1, 1)] - h[(2, 1)] * v.y,
    );
    // R_v turns the optical axis onto the ray through the image of the plane's origin.
    let ray = Vec3::new(v.x, v.y, 1.0).normalize();
    let axis = Vec3::z().cross(&ray);
    let r_v = if axis.norm() < 1e-15 {
        Mat3::identity()
    } else {
        let angle = ray.z.clamp(-1.0, 1.0).acos();
        nalgebra::Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), angle)
            .into_inner()
    };
    let b =
        SMatrix::<f64, 2, 3>::new(1.0, 0.0, -v.x, 0.0, 1.0, -v.y) * r_v.fixed_view::<3, 2>(0, 0);
    let Some(b_inv) = b.try_inverse() else {
        return Vec::new();
    };
    let a = b_inv * jac;
    // Largest singular value of the 2x2 A, in closed form.
    let frob2 = a.norm_squared();
    let det = a.determinant();
    let gamma = ((frob2 + (frob2 * frob2 - 4.0 * det * det).max(0.0).sqrt()) / 2.0).sqrt();
    if gamma.is_nan() || gamma <= 0.0 {
        return Vec::new();
    }
    let r22 = a / gamma;
    // Complete the first two columns to orthonormal 3-vectors: two choices of sign.
    let w0 = (1.0 - r22[(0, 0)].powi(2) - r22[(1, 0)].powi(2))
        .max(0.0)
        .sqrt();
    let w1_abs = (1.0 - r22[(0, 1)].powi(2) - r22[(1, 1)].powi(2))
        .max(0.0)
        .sqrt();
    let dot_top = r22[(0, 0)] * r22[(0, 1)] + r22[(1, 0)] * r22[(1, 1)];
    // c0 . c1 = dot_top + w0 w1 = 0.
    let w1 = if w0 > 1e-12 { -dot_top / w0 } else { w1_abs };
    let mut out = Vec::with_capacity(2);
    for sign in [1.0, -1.0] {
        let c0 = Vec3::new(r22[(0, 0)], r22[(1, 0)], sign * w0);
        let c1 = Vec3::new(r22[(0, 1)], r22[(1, 1)], sign * w1);
        let c2 = c0.cross(&c1);
        let local = nearest_rotation(&Mat3::from_columns(&[c0, c1, c2]));
        let rotation = r_v * local;
        out.push((rotation, translation(&rotation, plane_xy, normalized)));
    }
    out
}

/// The least-squares translation for a rotation: `t = -(sum Q_i)^-1 sum Q_i R X_i`.
fn translation(rotation: &Mat3, plane_xy: &[Vector2<f64>], normalized: &[Vector2<f64>]) -> Vec3 {
    let mut sum_q = Mat3::zeros();
    let mut sum_qrx = Vec3::zeros();
    for (x, n) in plane_xy.iter().zip(normalized) {
        let v = Vec3::new(n.x, n.y, 1.0);
        let q = Mat3::identity() - v * v.transpose() / v.norm_squared();
        sum_q += q;
        sum_qrx += q * (rotation * Vec3::new(x.x, x.y, 0.0));
    }
    sum_q
        .try_inverse()
        .map_or_else(Vec3::zeros, |inv| -(inv * sum_qrx))
}

/// The homography `H` with `[x, y, 1] ~ H [X, Y, 1]`, by the normalized DLT with `h33 = 1`
/// (an 8x8 solve; `h33` vanishes only when the plane passes through the camera centre, a view
/// that determines no pose).
pub(super) fn homography(from: &[Vector2<f64>], to: &[Vector2<f64>]) -> Option<Mat3> {
    let t_from = normalizer(from)?;
    let t_to = normalizer(to)?;
    let mut ata = SMatrix::<f64, 8, 8>::zeros();
    let mut atb = SMatrix::<f64, 8, 1>::zeros();
    for (p, q) in from.iter().zip(to) {
        let p = t_from * Vec3::new(p.x, p.y, 1.0);
        let q = t_to * Vec3::new(q.x, q.y, 1.0);
        let rows = [
            ([p.x, p.y, 1.0, 0.0, 0.0, 0.0, -q.x * p.x, -q.x * p.y], q.x),
            ([0.0, 0.0, 0.0, p.x, p.y, 1.0, -q.y * p.x, -q.y * p.y], q.y),
        ];
        for (row, rhs) in rows {
            let r = SMatrix::<f64, 8, 1>::from_column_slice(&row);
            ata += r * r.transpose();
            atb += r * rhs;
        }
    }
    let h = ata.cholesky()?.solve(&atb);
    let h_n = Mat3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0);
    Some(t_to.try_inverse()? * h_n * t_from)
}

/// Hartley's normalization: centroid to the origin, mean distance sqrt(2).
fn normalizer(points: &[Vector2<f64>]) -> Option<Mat3> {
    let n = points.len() as f64;
    let c = points.iter().fold(Vector2::zeros(), |acc, p| acc + p) / n;
    let mean_dist = points.iter().map(|p| (p - c).norm()).sum::<f64>() / n;
    if mean_dist.is_nan() || mean_dist <= 0.0 {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / mean_dist;
    Some(Mat3::new(s, 0.0, -s * c.x, 0.0, s, -s * c.y, 0.0, 0.0, 1.0))
}
