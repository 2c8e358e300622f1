//! The pinhole camera with OpenCV's distortion: Brown-Conrady's `k1 k2 p1 p2 k3`, and beside
//! them the rational terms `k4 k5 k6` and the thin prism `s1 s2 s3 s4`, in OpenCV's meaning
//! and order.
//!
//! A point `p` in the camera frame (mm, z forward) has normalized coordinates `x = X/Z, y = Y/Z`;
//! with `r2 = x^2 + y^2` and the radial factor
//! `radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)` they are
//! distorted to
//!
//! ```text
//! xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2) + s1 r2 + s2 r2^2
//! yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y + s3 r2 + s4 r2^2
//! ```
//!
//! and land on the pixel `u = fx xd + cx, v = fy yd + cy`. Undistortion inverts the distortion
//! by Newton's method and reports when it does not converge. Which terms a camera uses is its
//! [`LensModel`]: the terms beyond it are zero.

use super::VisionError;
use crate::geometry::Vec3;
use nalgebra::{Matrix2, Matrix2x3, SMatrix, Vector2};

/// Newton iterations allowed when undistorting one point.
const UNDISTORT_MAX_ITERATIONS: usize = 30;
/// Convergence of undistortion, in normalized image units (about 1e-9 px at fx = 5000).
const UNDISTORT_TOLERANCE: f64 = 1e-13;

/// Distortion terms of the widest model, in OpenCV's order `k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4`.
pub const DISTORTION_TERMS: usize = 12;
/// Intrinsics of the widest model: `fx fy cx cy` and the distortion terms.
pub const INTRINSICS: usize = 4 + DISTORTION_TERMS;
// A camera's intrinsics error is one contributor of a pose's error: its factor has a column
// per intrinsic.
const _: () = assert!(INTRINSICS == crate::chain::FACTOR_COLUMNS);

crate::words! {
    /// Which distortion terms a camera model has (OpenCV's 5, 8 and 12 coefficients).
    #[derive(PartialOrd, Ord, Default)]
    pub enum LensModel("lens model") {
        /// Brown-Conrady: `k1 k2 p1 p2 k3`.
        #[default]
        Brown = "brown",
        /// Rational: `k1 k2 p1 p2 k3 k4 k5 k6`, the radial factor a ratio of polynomials (wide
        /// lenses).
        Rational = "rational",
        /// Rational with thin prism: `k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4` (a tilted or
        /// decentred element, a sensor not square to the axis).
        RationalPrism = "rational_prism",
    }
}

impl LensModel {
    /// How many distortion coefficients it has, in OpenCV's order.
    pub fn distortion_terms(self) -> usize {
        match self {
            LensModel::Brown => 5,
            LensModel::Rational => 8,
            LensModel::RationalPrism => 12,
        }
    }

    /// How many intrinsics it has: `fx fy cx cy` and its distortion terms.
    pub fn intrinsics(self) -> usize {
        4 + self.distortion_terms()
    }

    /// The model with `n` distortion coefficients, if there is one.
    pub fn with_terms(n: usize) -> Option<LensModel> {
        LensModel::ALL
            .iter()
            .copied()
            .find(|m| m.distortion_terms() == n)
    }
}

/// The radial distortion's factor at one radius, with what its users need of it.
#[derive(Debug, Clone, Copy)]
struct RadialFactor {
    /// The factor the normalized point is scaled by.
    radial: f64,
    /// The rational model's denominator (1 for Brown-Conrady).
    denominator: f64,
    /// `d(radial) / d(r^2)`.
    d_radial_d_r2: f64,
}

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
    /// `[k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4]`, zero beyond the camera's model.
    pub distortion: [f64; DISTORTION_TERMS],
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
            distortion: [0.0; DISTORTION_TERMS],
            width_px,
            height_px,
        }
    }

    /// The camera with these distortion coefficients in OpenCV's order (5, 8 or 12 of them;
    /// the terms not given are zero, more than twelve are ignored).
    pub fn with_distortion(mut self, coefficients: &[f64]) -> Self {
        self.distortion = [0.0; DISTORTION_TERMS];
        let n = coefficients.len().min(DISTORTION_TERMS);
        self.distortion[..n].copy_from_slice(&coefficients[..n]);
        self
    }

    /// The smallest model whose terms hold every non-zero coefficient.
    pub fn lens_model(&self) -> LensModel {
        let used = self
            .distortion
            .iter()
            .rposition(|k| *k != 0.0)
            .map_or(0, |i| i + 1);
        LensModel::ALL
            .iter()
            .copied()
            .find(|m| m.distortion_terms() >= used)
            .unwrap_or(LensModel::RationalPrism)
    }

    /// The distortion coefficients of its [`CameraModel::lens_model`] (5, 8 or 12).
    pub fn distortion_coefficients(&self) -> &[f64] {
        &self.distortion[..self.lens_model().distortion_terms()]
    }

    /// Whether the radial distortion is a one-to-one map out to `r2_max` (the square of the
    /// largest normalized radius seen): the rational factor's denominator stays positive and
    /// the distorted radius `r * radial` grows with `r`. A model that folds or has a pole
    /// inside the field sends two rays to one pixel, or a ray to infinity; a fit that wanders
    /// there along a direction the data do not determine is not a lens.
    pub fn radially_monotonic_to(&self, r2_max: f64) -> bool {
        const STEPS: usize = 64;
        (0..=STEPS).all(|i| {
            let r2 = r2_max * i as f64 / STEPS as f64;
            let f = self.radial_factor(r2);
            // d(r radial)/dr = radial + 2 r^2 d(radial)/d(r^2)
            f.denominator > 0.0 && f.radial + 2.0 * r2 * f.d_radial_d_r2 > 0.0
        })
    }

    /// The radial factor at `r2`, the square of the normalized radius: the rational
    /// `(1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)` (Brown-Conrady's
    /// polynomial when `k4 k5 k6` are zero), its denominator and its derivative in `r^2`.
    fn radial_factor(&self, r2: f64) -> RadialFactor {
        let [k1, k2, _, _, k3, k4, k5, k6, ..] = self.distortion;
        let numerator = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let denominator = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6));
        let radial = numerator / denominator;
        // The quotient rule.
        let d_numerator = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2);
        let d_denominator = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2);
        RadialFactor {
            radial,
            denominator,
            d_radial_d_r2: (d_numerator - radial * d_denominator) / denominator,
        }
    }

    /// Distorts normalized coordinates, with the 2x2 Jacobian `d(xd, yd) / d(x, y)`.
    pub fn distort(&self, xy: Vector2<f64>) -> (Vector2<f64>, Matrix2<f64>) {
        let [_, _, p1, p2, _, _, _, _, s1, s2, s3, s4] = self.distortion;
        let (x, y) = (xy.x, xy.y);
        let r2 = x * x + y * y;
        let RadialFactor {
            radial,
            d_radial_d_r2: g,
            ..
        } = self.radial_factor(r2);
        // d(prism)/d(r2) of each axis.
        let (px, py) = (s1 + 2.0 * s2 * r2, s3 + 2.0 * s4 * r2);
        let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + r2 * (s1 + s2 * r2);
        let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + r2 * (s3 + s4 * r2);
        let dxd_dx = radial + 2.0 * x * x * g + 2.0 * p1 * y + 6.0 * p2 * x + 2.0 * x * px;
        let dxd_dy = 2.0 * x * y * g + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * y * px;
        let dyd_dx = 2.0 * x * y * g + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * x * py;
        let dyd_dy = radial + 2.0 * y * y * g + 6.0 * p1 * y + 2.0 * p2 * x + 2.0 * y * py;
        (
            Vector2::new(xd, yd),
            Matrix2::new(dxd_dx, dxd_dy, dyd_dx, dyd_dy),
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

    /// `d(u, v) / d(fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4)` at a point of the camera
    /// frame (in front of it): how the pixel of a fixed point moves with each intrinsic, in the
    /// order of the calibration's covariance (every term, whatever the camera's model).
    pub fn intrinsics_jacobian(&self, p: &Vec3) -> SMatrix<f64, 2, INTRINSICS> {
        let (x, y) = (p.x / p.z, p.y / p.z);
        let (xd, _) = self.distort(Vector2::new(x, y));
        let r2 = x * x + y * y;
        let (r4, r6) = (r2 * r2, r2 * r2 * r2);
        let RadialFactor {
            radial,
            denominator,
            ..
        } = self.radial_factor(r2);
        let (fx, fy) = (self.fx_px, self.fy_px);
        let mut j = SMatrix::<f64, 2, INTRINSICS>::zeros();
        j[(0, 0)] = xd.x;
        j[(1, 1)] = xd.y;
        j[(0, 2)] = 1.0;
        j[(1, 3)] = 1.0;
        // The numerator's terms (k1 k2 k3) and the denominator's (k4 k5 k6), at columns 4 5 8
        // and 9 10 11.
        for (col, power) in [(4, r2), (5, r4), (8, r6)] {
            j[(0, col)] = fx * x * power / denominator;
            j[(1, col)] = fy * y * power / denominator;
        }
        for (col, power) in [(9, r2), (10, r4), (11, r6)] {
            j[(0, col)] = -fx * x * radial * power / denominator;
            j[(1, col)] = -fy * y * radial * power / denominator;
        }
        j[(0, 6)] = fx * 2.0 * x * y;
        j[(1, 6)] = fy * (r2 + 2.0 * y * y);
        j[(0, 7)] = fx * (r2 + 2.0 * x * x);
        j[(1, 7)] = fy * 2.0 * x * y;
        j[(0, 12)] = fx * r2;
        j[(0, 13)] = fx * r4;
        j[(1, 14)] = fy * r2;
        j[(1, 15)] = fy * r4;
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
        CameraModel::pinhole(4800.0, 4790.0, 652.0, 508.0, 1280, 1024)
            .with_distortion(&[-0.092, 0.151, 0.0004, -0.0003, 0.012])
    }

    /// A wide lens with every term: rational radial factor and thin prism.
    fn wide_camera() -> CameraModel {
        CameraModel::pinhole(610.0, 608.0, 322.0, 236.0, 640, 480).with_distortion(&[
            0.41, -0.12, 0.0011, -0.0007, 0.03, 0.72, -0.05, 0.08, 0.0021, -0.0009, -0.0015, 0.0004,
        ])
    }

    #[test]
    fn distortion_jacobian_matches_central_differences() {
        for (cam, points) in [
            (
                lab_camera(),
                [(0.0, 0.0), (0.12, -0.08), (-0.2, 0.15), (0.3, 0.3)],
            ),
            (
                wide_camera(),
                [(0.0, 0.0), (0.4, -0.3), (-0.6, 0.45), (0.5, 0.5)],
            ),
        ] {
            distortion_jacobian_holds(&cam, &points);
        }
    }

    fn distortion_jacobian_holds(cam: &CameraModel, points: &[(f64, f64)]) {
        let h = 1e-6;
        for &(x, y) in points {
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
    fn intrinsics_jacobian_matches_central_differences_for_every_term() {
        let cam = wide_camera();
        let p = Vec3::new(310.0, -220.0, 900.0);
        let jac = cam.intrinsics_jacobian(&p);
        let h = 1e-7;
        let with = |col: usize, d: f64| {
            let mut c = cam;
            match col {
                0 => c.fx_px += d,
                1 => c.fy_px += d,
                2 => c.cx_px += d,
                3 => c.cy_px += d,
                k => c.distortion[k - 4] += d,
            }
            c.project(&p).expect("in front")
        };
        for col in 0..INTRINSICS {
            let numeric = (with(col, h) - with(col, -h)) / (2.0 * h);
            for row in 0..2 {
                assert!(
                    (jac[(row, col)] - numeric[row]).abs() < 1e-5 * (1.0 + numeric[row].abs()),
                    "d{row}/d{col}: {} vs {}",
                    jac[(row, col)],
                    numeric[row]
                );
            }
        }
    }

    #[test]
    fn a_model_that_folds_or_has_a_pole_in_the_field_is_not_monotonic() {
        assert!(lab_camera().radially_monotonic_to(0.1));
        assert!(wide_camera().radially_monotonic_to(1.0));
        // k1 = -0.5 folds at r^2 = 2/3 (d(r - 0.5 r^3)/dr = 1 - 1.5 r^2).
        let fold = CameraModel::pinhole(1.0, 1.0, 0.0, 0.0, 10, 10).with_distortion(&[-0.5]);
        assert!(fold.radially_monotonic_to(0.6));
        assert!(!fold.radially_monotonic_to(0.7));
        // A denominator 1 - 1.7 r^2 has a pole at r^2 = 0.59.
        let pole = CameraModel::pinhole(1.0, 1.0, 0.0, 0.0, 10, 10)
            .with_distortion(&[-1.75, 0.1, 0.0, 0.0, 0.0, -1.7, 0.1]);
        assert!(!pole.radially_monotonic_to(0.8));
    }

    #[test]
    fn the_lens_model_is_the_smallest_that_holds_every_term() {
        let pin = CameraModel::pinhole(1.0, 1.0, 0.0, 0.0, 10, 10);
        assert_eq!(pin.lens_model(), LensModel::Brown);
        assert_eq!(lab_camera().lens_model(), LensModel::Brown);
        assert_eq!(lab_camera().distortion_coefficients().len(), 5);
        let rational = pin.with_distortion(&[0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.2]);
        assert_eq!(rational.lens_model(), LensModel::Rational);
        assert_eq!(wide_camera().lens_model(), LensModel::RationalPrism);
        assert_eq!(wide_camera().distortion_coefficients().len(), 12);
        for m in LensModel::ALL {
            assert_eq!(LensModel::with_terms(m.distortion_terms()), Some(*m));
        }
        assert_eq!(LensModel::with_terms(4), None);
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
        for cam in [lab_camera(), wide_camera()] {
            undistort_inverts(&cam);
        }
    }

    fn undistort_inverts(cam: &CameraModel) {
        let (w, h) = (f64::from(cam.width_px), f64::from(cam.height_px));
        for i in 0..=8 {
            for j in 0..=8 {
                let uv = Vector2::new(w * f64::from(i) / 8.0, h * f64::from(j) / 8.0);
                let xy = cam.undistort(uv).expect("converges inside the image");
                let back = cam.project(&Vec3::new(xy.x, xy.y, 1.0)).expect("front");
                assert!((back - uv).norm() < 1e-8, "{uv:?} -> {back:?}");
            }
        }
    }

    #[test]
    fn undistort_reports_a_point_past_the_fold_of_the_model() {
        // With k1 = -0.5 the model folds at r = 0.82 (xd at most 0.54): nothing maps beyond.
        let cam =
            CameraModel::pinhole(1000.0, 1000.0, 500.0, 500.0, 1000, 1000).with_distortion(&[-0.5]);
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
