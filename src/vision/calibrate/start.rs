//! Where a camera calibration starts: Zhang's closed form from the views' homographies (or
//! the focal lengths alone with the principal point at the image centre), and each view's
//! pose from its homography refined by PnP.

use super::adjust::Problem;
use super::{CalibrationOptions, Intrinsic, from_params, intrinsics_of, refuse};
use crate::geometry::{Mat3, Pose, Rotation, Vec3};
use crate::vision::{CameraModel, INTRINSICS, VisionError, ippe::homography, pnp, sqpnp};
use nalgebra::{SMatrix, Translation3, Vector2};

/// The starting camera: Zhang's closed form (or the focal lengths alone with the principal
/// point at the centre), then the fixed parameters at their values.
pub(super) fn initial_camera(
    problem: &Problem,
    width_px: u32,
    height_px: u32,
    options: &CalibrationOptions,
) -> Result<CameraModel, VisionError> {
    let (w, h) = (f64::from(width_px), f64::from(height_px));
    // Pixels to a unit scale about the image centre, for conditioning.
    let s = w.max(h);
    let (ccx, ccy) = ((w - 1.0) / 2.0, (h - 1.0) / 2.0);
    let n = Mat3::new(
        1.0 / s,
        0.0,
        -ccx / s,
        0.0,
        1.0 / s,
        -ccy / s,
        0.0,
        0.0,
        1.0,
    );
    let mut homographies = Vec::with_capacity(problem.views.len());
    for (v, view) in problem.views.iter().enumerate() {
        let normalized: Vec<Vector2<f64>> = view
            .points_px
            .iter()
            .map(|p| {
                let q = n * Vec3::new(p.x, p.y, 1.0);
                Vector2::new(q.x, q.y)
            })
            .collect();
        let hv = homography(&problem.plate_xy(v), &normalized).ok_or_else(|| {
            refuse(format!(
                "view {v}: its points do not determine a homography (collinear?)"
            ))
        })?;
        homographies.push(hv);
    }
    let k_normalized = zhang(&homographies)
        .filter(plausible)
        .or_else(|| centred_focal(&homographies))
        .or_else(|| {
            options.initial.map(|c| {
                n * Mat3::new(c.fx_px, 0.0, c.cx_px, 0.0, c.fy_px, c.cy_px, 0.0, 0.0, 1.0)
            })
        })
        .ok_or_else(|| {
            refuse("the views do not determine the focal length: they are nearly parallel; tilt the plate by 20 to 45 degrees about different axes")
        })?;
    let k = n.try_inverse().unwrap_or_else(Mat3::identity) * k_normalized;
    // The distortion starts at zero; the terms beyond the model stay there.
    let mut params = [0.0; INTRINSICS];
    params[..4].copy_from_slice(&[k[(0, 0)], k[(1, 1)], k[(0, 2)], k[(1, 2)]]);
    let in_model = Intrinsic::of_model(options.model);
    for p in options.fixed.iter().filter(|p| in_model.contains(p)) {
        let i = p.index();
        params[i] = match (options.initial, p) {
            (Some(c), _) => intrinsics_of(&c)[i],
            (None, Intrinsic::Cx) => ccx,
            (None, Intrinsic::Cy) => ccy,
            (None, Intrinsic::Fx | Intrinsic::Fy) => {
                return Err(refuse(format!(
                    "{} can be fixed only at a known value: give the initial camera",
                    p.name()
                )));
            }
            (None, _) => 0.0,
        };
    }
    Ok(from_params(&params, width_px, height_px))
}

/// A camera matrix (normalized pixels) with positive focal lengths and its principal point
/// inside the image.
fn plausible(k: &Mat3) -> bool {
    k.iter().all(|v| v.is_finite())
        && k[(0, 0)] > 0.0
        && k[(1, 1)] > 0.0
        && k[(0, 2)].abs() < 0.5
        && k[(1, 2)].abs() < 0.5
        && (k[(0, 0)] / k[(1, 1)] - 1.0).abs() < 0.5
}

/// `v_ij` of Zhang's method: `h_i^T B h_j = v_ij . b`.
fn v_ij(h: &Mat3, i: usize, j: usize) -> SMatrix<f64, 6, 1> {
    let (hi, hj) = (h.column(i), h.column(j));
    SMatrix::<f64, 6, 1>::from_column_slice(&[
        hi[0] * hj[0],
        hi[0] * hj[1] + hi[1] * hj[0],
        hi[1] * hj[1],
        hi[2] * hj[0] + hi[0] * hj[2],
        hi[2] * hj[1] + hi[1] * hj[2],
        hi[2] * hj[2],
    ])
}

/// Zhang's closed form with zero skew; `None` when the views do not determine it.
fn zhang(homographies: &[Mat3]) -> Option<Mat3> {
    let mut vtv = SMatrix::<f64, 6, 6>::zeros();
    for h in homographies {
        let h = h / h.norm();
        let rows = [v_ij(&h, 0, 1), v_ij(&h, 0, 0) - v_ij(&h, 1, 1)];
        for r in rows {
            vtv += r * r.transpose();
        }
    }
    // Zero skew: B12 = 0, weighted like a view.
    let skew_row = SMatrix::<f64, 6, 1>::from_column_slice(&[0.0, 1.0, 0.0, 0.0, 0.0, 0.0]);
    vtv += skew_row * skew_row.transpose() * (vtv.trace() / 6.0).max(1e-12);
    let eigen = vtv.symmetric_eigen();
    let mut order: Vec<usize> = (0..6).collect();
    order.sort_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]));
    // The null vector must be clearly the smallest, or the views leave a family of solutions.
    if eigen.eigenvalues[order[0]] > 1e-3 * eigen.eigenvalues[order[1]] {
        return None;
    }
    let b = eigen.eigenvectors.column(order[0]);
    let (b11, b12, b22, b13, b23, b33) = (b[0], b[1], b[2], b[3], b[4], b[5]);
    let den = b11 * b22 - b12 * b12;
    if den.abs() < 1e-300 {
        return None;
    }
    let v0 = (b12 * b13 - b11 * b23) / den;
    let lambda = b33 - (b13 * b13 + v0 * (b12 * b13 - b11 * b23)) / b11;
    let alpha2 = lambda / b11;
    let beta2 = lambda * b11 / den;
    if alpha2 <= 0.0 || beta2 <= 0.0 {
        return None;
    }
    let (alpha, beta) = (alpha2.sqrt(), beta2.sqrt());
    let u0 = -b13 * alpha2 / lambda;
    Some(Mat3::new(alpha, 0.0, u0, 0.0, beta, v0, 0.0, 0.0, 1.0))
}

/// Focal lengths alone, the principal point at the centre (normalized pixels' origin).
fn centred_focal(homographies: &[Mat3]) -> Option<Mat3> {
    // With omega = diag(a, b, 1): h1' omega h2 = 0 and h1' omega h1 = h2' omega h2.
    let mut ata = nalgebra::Matrix2::<f64>::zeros();
    let mut atb = Vector2::<f64>::zeros();
    for h in homographies {
        let h = h / h.norm();
        let rows = [
            (
                [h[(0, 0)] * h[(0, 1)], h[(1, 0)] * h[(1, 1)]],
                -h[(2, 0)] * h[(2, 1)],
            ),
            (
                [
                    h[(0, 0)].powi(2) - h[(0, 1)].powi(2),
                    h[(1, 0)].powi(2) - h[(1, 1)].powi(2),
                ],
                -(h[(2, 0)].powi(2) - h[(2, 1)].powi(2)),
            ),
        ];
        for (r, rhs) in rows {
            let r = Vector2::new(r[0], r[1]);
            ata += r * r.transpose();
            atb += r * rhs;
        }
    }
    let ab = ata.try_inverse()? * atb;
    if !(ab.x > 0.0 && ab.y > 0.0) {
        return None;
    }
    Some(Mat3::new(
        1.0 / ab.x.sqrt(),
        0.0,
        0.0,
        0.0,
        1.0 / ab.y.sqrt(),
        0.0,
        0.0,
        0.0,
        1.0,
    ))
}

/// Each view's `camera_from_centred` at the start: from its homography and the camera, then
/// refined by PnP's Levenberg-Marquardt.
pub(super) fn initial_poses(
    problem: &Problem,
    camera: &CameraModel,
) -> Result<Vec<Pose>, VisionError> {
    let k = Mat3::new(
        camera.fx_px,
        0.0,
        camera.cx_px,
        0.0,
        camera.fy_px,
        camera.cy_px,
        0.0,
        0.0,
        1.0,
    );
    let k_inv = k
        .try_inverse()
        .ok_or_else(|| refuse("the starting camera is singular"))?;
    let mut poses = Vec::with_capacity(problem.views.len());
    for (v, view) in problem.views.iter().enumerate() {
        let start_failed = || refuse(format!("view {v}: no pose of the plate explains it"));
        let h = homography(&problem.plate_xy(v), &view.points_px).ok_or_else(start_failed)?;
        let a = k_inv * h;
        let scale = 2.0 / (a.column(0).norm() + a.column(1).norm());
        let sign = if a[(2, 2)] * scale < 0.0 { -1.0 } else { 1.0 };
        let r1 = a.column(0) * scale * sign;
        let r2 = a.column(1) * scale * sign;
        let t = a.column(2) * scale * sign;
        let r3 = r1.cross(&r2);
        let rotation = sqpnp::nearest_rotation(&Mat3::from_columns(&[r1, r2, r3]));
        let camera_from_plate = Pose::from_parts(
            Translation3::from(Vec3::from(t)),
            Rotation::from_matrix_eps(&rotation, 1e-15, 100, Rotation::identity()),
        );
        let plate_mm: Vec<Vec3> = view
            .ids
            .iter()
            .map(|&i| problem.plate_points_mm[i])
            .collect();
        let refined = pnp::refine(
            camera,
            &plate_mm,
            &view.points_px,
            &problem.weights[v],
            &camera_from_plate,
            50,
        )
        .ok_or_else(start_failed)?;
        poses.push(refined.camera_from_marker * Translation3::from(problem.centroids_mm[v]));
    }
    Ok(poses)
}
