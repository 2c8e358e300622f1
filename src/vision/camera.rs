//! The pinhole camera with Brown-Conrady distortion, in OpenCV's meaning of `k1 k2 p1 p2 k3`.
//!
//! A point `p` in the camera frame (mm, z forward) has normalized coordinates `x = X/Z, y = Y/Z`;
//! with `r2 = x^2 + y^2` and `radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3` they are distorted to
//!
//! ```text
//! xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
//! yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
//! ```
//!
//! and land on the pixel `u = fx xd + cx, v = fy yd + cy`. Undistortion inverts the distortion
//! by Newton's method and reports when it does not converge.

use super::VisionError;
use crate::geometry::Vec3;
use nalgebra::{Matrix2, Matrix2x3, SMatrix, Vector2};

/// Newton iterations allowed when undistorting one point.
const UNDISTORT_MAX_ITERATIONS: usize = 30;
/// Convergence of undistortion, in normalized image units (about 1e-9 px at fx = 5000).
const UNDISTORT_TOLERANCE: f64 = 1e-13;

/// A calibrated camera: intrinsics, distortion and image size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraModel {
    /// Focal length along x (px).
    pub fx_px: f64,
    /// Focal length along y (px).
    pub fy_px: f64,
    /// Principal point x (px).
    pub cx_px: f64,
    /// Principal point y (px).
    pub cy_px: f64,
    /// `[k1, k2, p1, p2, k3]`.
    pub distortion: [f64; 5],
    /// Image width (px).
    pub width_px: u32,
    /// Image height (px).
    pub height_px: u32,
}

impl CameraModel {
    /// A camera without distortion.
    pub fn pinhole(
        fx_px: f64,
        fy_px: f64,
        cx_px: f64,
        cy_px: f64,
        width_px: u32,
        height_px: u32,
    ) -> Self {
        Self {
            fx_px,
            fy_px,
            cx_px,
            cy_px,
            distortion: [0.0; 5],
            width_px,
            height_px,
        }
    }

    /// Distorts normalized coordinates, with the 2x2 Jacobian `d(xd, yd) / d(x, y)`.
    pub fn distort(&self, xy: Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>) {
        let [k1, k2, p1, p2, k3] = self.distortion;
        let (x, y) = (xy.x, xy.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        // d(radial)/d(r2)
        let g = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
        let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        let dxd_dx = radial + 2.0 * x * x * g + 2.0 * p1 * y + 6.0 * p2 * x;
        let cross = 2.0 * x * y * g + 2.0 * p1 * x + 2.0 * p2 * y;
        let dyd_dy = radial + 2.0 * y * y * g + 6.0 * p1 * y + 2.0 * p2 * x;
        (
            Vector2::new(xd, yd),
            Matrix2::new(dxd_dx, cross, cross, dyd_dy),
        )
    }

    /// Projects a point of the camera frame to pixels; `None` if it is not in front (`Z <= 0`).
    pub fn project(&self, p_camera_mm: &Vec3) -> Option<Vector2<f64>> {
        self.project_with_jacobian(p_camera_mm).map(|(uv, _)| uv)
    }

    /// Projects a point and gives `d(u, v) / d(p_camera)` (px per mm); `None` behind the camera.
    pub fn project_with_jacobian(&self, p: &Vec3) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
        if p.z.is_nan() || p.z <= 0.0 {
            return None;
        }
        let inv_z = 1.0 / p.z;
        let xy = Vector2::new(p.x * inv_z, p.y * inv_z);
        let (d, dd) = self.distort(xy);
        let uv = self.pixel_of_distorted(d);
        // d(x, y)/dp = [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]
        let dn = Matrix2x3::new(inv_z, 0.0, -xy.x * inv_z, 0.0, inv_z, -xy.y * inv_z);
        let scale = Matrix2::new(self.fx_px, 0.0, 0.0, self.fy_px);
        Some((uv, scale * dd * dn))
    }

    /// `d(u, v) / d(fx fy cx cy k1 k2 p1 p2 k3)` at a point of the camera frame (in front of
    /// it): how the pixel of a fixed point moves with each intrinsic, in the order of the
    /// calibration's covariance.
    pub fn intrinsics_jacobian(&self, p: &Vec3) -> SMatrix<f64, 2, 9> {
        let (x, y) = (p.x / p.z, p.y / p.z);
        let (xd, _) = self.distort(Vector2::new(x, y));
        let r2 = x * x + y * y;
        let (r4, r6) = (r2 * r2, r2 * r2 * r2);
        let (fx, fy) = (self.fx_px, self.fy_px);
        let mut j = SMatrix::<f64, 2, 9>::zeros();
        j[(0, 0)] = xd.x;
        j[(1, 1)] = xd.y;
        j[(0, 2)] = 1.0;
        j[(1, 3)] = 1.0;
        j[(0, 4)] = fx * x * r2;
        j[(1, 4)] = fy * y * r2;
        j[(0, 5)] = fx * x * r4;
        j[(1, 5)] = fy * y * r4;
        j[(0, 6)] = fx * 2.0 * x * y;
        j[(1, 6)] = fy * (r2 + 2.0 * y * y);
        j[(0, 7)] = fx * (r2 + 2.0 * x * x);
        j[(1, 7)] = fy * 2.0 * x * y;
        j[(0, 8)] = fx * x * r6;
        j[(1, 8)] = fy * y * r6;
        j
    }

    /// The pixel of normalized coordinates `(X/Z, Y/Z)`, whatever the sign of Z (the central
    /// projection's equations alone).
    pub fn pixel_of_normalized(&self, xy: Vector2<f64>) -> Vector2<f64> {
        self.pixel_of_distorted(self.distort(xy).0)
    }

    fn pixel_of_distorted(&self, d: Vector2<f64>) -> Vector2<f64> {
        Vector2::new(self.fx_px * d.x + self.cx_px, self.fy_px * d.y + self.cy_px)
    }

    /// The normalized, undistorted coordinates `(X/Z, Y/Z)` of a measured pixel.
    pub fn undistort(&self, uv_px: Vector2<f64>) -> Result<Vector2<f64>, VisionError> {
        let target = Vector2::new(
            (uv_px.x - self.cx_px) / self.fx_px,
            (uv_px.y - self.cy_px) / self.fy_px,
        );
        if self.distortion.iter().all(|k| *k == 0.0) {
            return Ok(target);
        }
        let diverged = || VisionError::UndistortDiverged {
            u_px: uv_px.x,
            v_px: uv_px.y,
        };
        // A root past the fold of the model (where it turns back on itself) is not the point
        // that was imaged: the Jacobian there is not positive and the ray points elsewhere.
        let valid =
            |xy: Vector2<f64>, dd: &Matrix2<f64>| dd.determinant() > 0.0 && xy.dot(&target) >= 0.0;
        let mut xy = target;
        for _ in 0..UNDISTORT_MAX_ITERATIONS {
            let (d, dd) = self.distort(xy);
            let residual = d - target;
            if residual.norm() < UNDISTORT_TOLERANCE {
                return if valid(xy, &dd) {
                    Ok(xy)
                } else {
                    Err(diverged())
                };
            }
            let step = dd.try_inverse().ok_or_else(diverged)? * residual;
            xy -= step;
            if !xy.iter().all(|v| v.is_finite()) {
                return Err(diverged());
            }
        }
        let (d, dd) = self.distort(xy);
        if (d - target).norm() < UNDISTORT_TOLERANCE && valid(xy, &dd) {
            Ok(xy)
        } else {
            Err(diverged())
        }
    }

    /// Whether a pixel lies inside the image.
    pub fn in_image(&self, uv_px: &Vector2<f64>) -> bool {
        uv_px.x >= 0.0
            && uv_px.y >= 0.0
            && uv_px.x <= f64::from(self.width_px)
            && uv_px.y <= f64::from(self.height_px)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lab_camera() -> CameraModel {
        CameraModel {
            distortion: [-0.092, 0.151, 0.0004, -0.0003, 0.012],
            ..CameraModel::pinhole(4800.0, 4790.0, 652.0, 508.0, 1280, 1024)
        }
    }

    #[test]
    fn distortion_jacobian_matches_central_differences() {
        let cam = lab_camera();
        let h = 1e-6;
        for &(x, y) in &[(0.0, 0.0), (0.12, -0.08), (-0.2, 0.15), (0.3, 0.3)] {
            let (_, jac) = cam.distort(Vector2::new(x, y));
            for (col, dv) in [Vector2::new(h, 0.0), Vector2::new(0.0, h)]
                .iter()
                .enumerate()
            {
                let plus = cam.distort(Vector2::new(x, y) + dv).0;
                let minus = cam.distort(Vector2::new(x, y) - dv).0;
                let numeric = (plus - minus) / (2.0 * h);
                for row in 0..2 {
                    assert!(
                        (jac[(row, col)] - numeric[row]).abs() < 1e-8,
                        "d{row}/d{col} at ({x}, {y}): {} vs {}",
                        jac[(row, col)],
                        numeric[row]
                    );
                }
            }
        }
    }

    #[test]
    fn projection_jacobian_matches_central_differences() {
        let cam = lab_camera();
        let p = Vec3::new(120.0, -80.0, 2900.0);
        let (_, jac) = cam.project_with_jacobian(&p).expect("in front");
        let h = 1e-4;
        for col in 0..3 {
            let mut dp = Vec3::zeros();
            dp[col] = h;
            let numeric = (cam.project(&(p + dp)).expect("front")
                - cam.project(&(p - dp)).expect("front"))
                / (2.0 * h);
            for row in 0..2 {
                assert!((jac[(row, col)] - numeric[row]).abs() < 1e-7);
            }
        }
    }

    #[test]
    fn undistort_inverts_projection_over_the_image() {
        let cam = lab_camera();
        for i in 0..=8 {
            for j in 0..=8 {
                let uv = Vector2::new(1280.0 * f64::from(i) / 8.0, 1024.0 * f64::from(j) / 8.0);
                let xy = cam.undistort(uv).expect("converges inside the image");
                let back = cam.project(&Vec3::new(xy.x, xy.y, 1.0)).expect("front");
                assert!((back - uv).norm() < 1e-8, "{uv:?} -> {back:?}");
            }
        }
    }

    #[test]
    fn undistort_reports_a_point_past_the_fold_of_the_model() {
        // With k1 = -0.5 the model folds at r = 0.82 (xd at most 0.54): nothing maps beyond.
        let cam = CameraModel {
            distortion: [-0.5, 0.0, 0.0, 0.0, 0.0],
            ..CameraModel::pinhole(1000.0, 1000.0, 500.0, 500.0, 1000, 1000)
        };
        let err = cam
            .undistort(Vector2::new(500.0 + 900.0, 500.0))
            .expect_err("no preimage");
        assert!(
            matches!(err, VisionError::UndistortDiverged { .. }),
            "{err}"
        );
    }

    #[test]
    fn points_behind_the_camera_do_not_project() {
        let cam = lab_camera();
        assert!(cam.project(&Vec3::new(0.0, 0.0, -100.0)).is_none());
        assert!(cam.project(&Vec3::new(0.0, 0.0, 0.0)).is_none());
    }
}
