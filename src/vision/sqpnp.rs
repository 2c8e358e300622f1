//! SQPnP (Terzakis and Lourakis, ECCV 2020): the globally sound initialiser for markers with
//! depth.
//!
//! With `v_i = [x_i, y_i, 1]` the normalized ray of point `X_i` and `Q_i = I - v v^T / v^T v` the
//! projector onto the plane orthogonal to it, the object-space error is
//! `sum_i || Q_i (R X_i + t) ||^2`. The optimal translation is linear in `r = vec(R)` (rows),
//! `t = P r`, which leaves the quadratic `r^T Omega r` over rotations. Starting from the
//! eigenvectors of Omega's smallest eigenvalues (both signs, projected onto SO(3)), a local
//! solver finds its minima; the best of them is the global one. The paper's local solver is SQP
//! on the six orthonormality constraints; here it is Newton's method on the rotation manifold,
//! which takes the same steps near a minimum for a 3x3 solve instead of a 15x15 one. Points are
//! centred first for conditioning.

use crate::geometry::{Mat3, Vec3, skew};
use nalgebra::{SMatrix, SVector, Vector2};

type Vec9 = SVector<f64, 9>;
type Mat9 = SMatrix<f64, 9, 9>;

/// Eigenvalues of Omega below this fraction of its largest count as its null space.
const NULL_SPACE_TOLERANCE: f64 = 1e-10;
/// Newton iterations per start.
const NEWTON_MAX_ITERATIONS: usize = 20;
/// Newton stops when its step is below this (rad); Levenberg-Marquardt finishes the job.
const NEWTON_STEP_TOLERANCE: f64 = 1e-10;

/// One minimum of the object-space error: `camera_from_centred` rotation and translation.
#[derive(Debug, Clone, Copy)]
pub(super) struct Minimum {
    /// Rotation.
    pub rotation: Mat3,
    /// Translation (mm) of the centred points.
    pub t_mm: Vec3,
    /// Object-space error (mm^2).
    pub cost: f64,
}

/// The local minima found, best first. `centred` are marker points minus their centroid;
/// `normalized` the undistorted rays `(X/Z, Y/Z)`.
pub(super) fn minima(centred: &[Vec3], normalized: &[Vector2<f64>]) -> Vec<Minimum> {
    let mut sum_q = Mat3::zeros();
    let mut s = SMatrix::<f64, 3, 9>::zeros();
    let mut omega = Mat9::zeros();
    for (x, n) in centred.iter().zip(normalized) {
        let v = Vec3::new(n.x, n.y, 1.0);
        let q = Mat3::identity() - v * v.transpose() / v.norm_squared();
        sum_q += q;
        let xxt = x * x.transpose();
        for j in 0..3 {
            for k in 0..3 {
                let mut col = s.column_mut(3 * j + k);
                col += q.column(j) * x[k];
            }
            for l in 0..3 {
                let mut block = omega.fixed_view_mut::<3, 3>(3 * j, 3 * l);
                block += xxt * q[(j, l)];
            }
        }
    }
    let Some(sum_q_inv) = sum_q.try_inverse() else {
        return Vec::new();
    };
    let p = -(sum_q_inv * s);
    omega += s.transpose() * p;
    let omega = (omega + omega.transpose()) * 0.5;

    let eigen = nalgebra::SymmetricEigen::new(omega);
    let mut order: Vec<usize> = (0..9).collect();
    order.sort_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]));
    let largest = eigen.eigenvalues[order[8]].abs().max(f64::MIN_POSITIVE);
    // The null space, and at least the three smallest: a marker that is nearly planar has
    // three nearly null directions (its third rotation column is barely observed), and the
    // smallest alone can lead to the mirrored solution behind the camera.
    let starts = order
        .iter()
        .enumerate()
        .take_while(|(rank, k)| {
            *rank < 3 || eigen.eigenvalues[**k] <= NULL_SPACE_TOLERANCE * largest
        })
        .map(|(_, k)| *k);

    let mut found: Vec<Minimum> = Vec::new();
    for k in starts {
        let e: Vec9 = eigen.eigenvectors.column(k).into_owned() * 3f64.sqrt();
        for sign in [1.0, -1.0] {
            let start = nearest_rotation(&matrix_of(&(e * sign)));
            let Some(rotation) = newton_on_rotations(&omega, start, &found) else {
                continue;
            };
            let rv = vec_of(&rotation);
            let cost = (rv.transpose() * omega * rv)[(0, 0)].max(0.0);
            let t_mm = p * rv;
            if found.iter().any(|m| (m.rotation - rotation).norm() < 1e-6) {
                continue;
            }
            found.push(Minimum {
                rotation,
                t_mm,
                cost,
            });
        }
    }
    found.sort_by(|a, b| a.cost.total_cmp(&b.cost));
    found
}

fn matrix_of(r: &Vec9) -> Mat3 {
    Mat3::new(r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8])
}

fn vec_of(m: &Mat3) -> Vec9 {
    Vec9::from_column_slice(&[
        m[(0, 0)],
        m[(0, 1)],
        m[(0, 2)],
        m[(1, 0)],
        m[(1, 1)],
        m[(1, 2)],
        m[(2, 0)],
        m[(2, 1)],
        m[(2, 2)],
    ])
}

/// The rotation nearest to `m` in the Frobenius norm (SVD, with the determinant fixed).
pub(super) fn nearest_rotation(m: &Mat3) -> Mat3 {
    let svd = m.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Mat3::identity();
    };
    let d = (u * v_t).determinant().signum();
    u * Mat3::from_diagonal(&Vec3::new(1.0, 1.0, d)) * v_t
}

/// Minimises `r^T Omega r` over rotations from `start` by Newton's method on the manifold,
/// `R <- Exp(w) R`. With `W = [w]x`, `vec(Exp(w) R) = r + vec(W R) + vec(W^2 R) / 2 + ...`, so
/// with `J = d vec(W R) / dw` and `G = mat(Omega r)` the gradient is `2 J^T Omega r` and the Hessian
/// `2 (J^T Omega J + sym(R G^T) - tr(G^T R) I)`: each step is a 3x3 solve, where the SQP of the
/// paper solves the same local problem in the null space of its constraints.
///
/// `None` once it comes within 1e-4 of a minimum in `known` (it would end there).
fn newton_on_rotations(omega: &Mat9, start: Mat3, known: &[Minimum]) -> Option<Mat3> {
    let mut rotation = start;
    for _ in 0..NEWTON_MAX_ITERATIONS {
        if known.iter().any(|m| (m.rotation - rotation).norm() < 1e-4) {
            return None;
        }
        let r = vec_of(&rotation);
        let omega_r = omega * r;
        let mut jac = SMatrix::<f64, 9, 3>::zeros();
        for k in 0..3 {
            let mut e = Vec3::zeros();
            e[k] = 1.0;
            jac.set_column(k, &vec_of(&(skew(&e) * rotation)));
        }
        let gradient = jac.transpose() * omega_r;
        let g = matrix_of(&omega_r);
        let rgt = rotation * g.transpose();
        let hessian_gn = jac.transpose() * omega * jac;
        let hessian = hessian_gn + (rgt + rgt.transpose()) * 0.5
            - Mat3::identity() * (g.transpose() * rotation).trace();
        let step = hessian
            .cholesky()
            .or_else(|| hessian_gn.cholesky())
            .map(|c| -c.solve(&gradient));
        let Some(step) = step else {
            break;
        };
        rotation = nalgebra::Rotation3::new(step).into_inner() * rotation;
        if step.norm() < NEWTON_STEP_TOLERANCE {
            break;
        }
    }
    Some(rotation)
}
