//! Perspective eccentricity of disc targets: the centroid of a disc's image is not the image of
//! the disc's centre.
//!
//! A detector measures the centroid of a disc's image (under a pinhole, the centre of the
//! ellipse it images to); PnP needs the image of the disc's centre. Once a first pose places
//! the disc (centre, normal, diameter in the camera frame), the offset between the two is
//! computed here and subtracted from the detection. The offset is the area centroid of the
//! projected disc minus the projection of its centre, integrated over the disc in polar
//! coordinates with `s = r^2` (so that `dA = ds dθ / 2`): Gauss-Legendre nodes in `s` and
//! equally spaced angles, each node projected with the full camera model (distortion included)
//! and weighted by the projection's local area magnification `|det d(u, v) / d(s, t)|`. The
//! integrand is smooth and, averaged over the angle, a smooth function of `r^2`; equally spaced
//! angles integrate a smooth periodic function to the rounding error and 8 Gauss nodes are
//! exact for polynomials of degree 15, so 8 x 32 nodes give the offset to about 1e-9 px (the
//! tests compare it with the centre of the ellipse a pinhole images the disc to, in closed
//! form).
//!
//! It grows with the disc's size and tilt: a 20 mm disc at 3 m tilted by 30 degrees is offset
//! by about 0.02 px, more than the detector's scatter. [`solve_pnp_discs`] is the whole step:
//! PnP on the centroids, the correction at that pose, PnP again.

use super::{CameraModel, PnpOptions, PnpSolution, VisionError, solve_pnp_weighted};
use crate::geometry::Vec3;
use nalgebra::{Matrix2, Matrix3x2, Vector2};

/// Gauss-Legendre nodes and weights on `[-1, 1]` (8 points, the positive half; the rule is
/// symmetric).
const GAUSS_8: [(f64, f64); 4] = [
    (0.183_434_642_495_649_8, 0.362_683_783_378_362),
    (0.525_532_409_916_329, 0.313_706_645_877_887_3),
    (0.796_666_477_413_626_7, 0.222_381_034_453_374_5),
    (0.960_289_856_497_536_3, 0.101_228_536_290_376_3),
];
/// Equally spaced angles of the integration.
const SECTORS: usize = 32;

/// The centroid of the image of a disc minus the image of its centre (px): subtract it from a
/// detected centroid to get the image of the centre. `centre_mm` and `normal` are in the camera
/// frame. `None` when part of the disc is not in front of the camera.
pub fn disc_image_offset(
    camera: &CameraModel,
    centre_mm: &Vec3,
    normal: &Vec3,
    diameter_mm: f64,
) -> Option<Vector2<f64>> {
    let (a, b) = plane_axes(normal)?;
    let axes = Matrix3x2::from_columns(&[a, b]);
    let radius = diameter_mm / 2.0;
    let image_of_centre = camera.project(centre_mm)?;
    let (mut sum, mut weight) = (Vector2::zeros(), 0.0);
    let angles: [(f64, f64); SECTORS] = std::array::from_fn(|j| {
        let t = (j as f64 + 0.5) / SECTORS as f64 * std::f64::consts::TAU;
        (t.cos(), t.sin())
    });
    for &(x, w_node) in &GAUSS_8 {
        for s in [0.5 * (1.0 - x), 0.5 * (1.0 + x)] {
            let r = radius * s.sqrt();
            for &(c, sn) in &angles {
                let p = centre_mm + axes * Vector2::new(r * c, r * sn);
                let (uv, jac) = camera.project_with_jacobian(&p)?;
                let area: Matrix2<f64> = jac * axes;
                let w = w_node * area.determinant().abs();
                sum += uv * w;
                weight += w;
            }
        }
    }
    (weight > 0.0).then(|| sum / weight - image_of_centre)
}

/// Two orthonormal axes of the plane whose normal is `normal` (`None` for a zero normal).
fn plane_axes(normal: &Vec3) -> Option<(Vec3, Vec3)> {
    let n = normal.try_normalize(1e-12)?;
    let helper = if n.x.abs() < 0.9 {
        Vec3::x()
    } else {
        Vec3::y()
    };
    let a = n.cross(&helper).normalize();
    Some((a, n.cross(&a)))
}

/// PnP on disc targets: solved on the detected centroids, each corrected by its disc's
/// perspective eccentricity at that first pose, and solved again. `normals_mm` are the discs'
/// normals in the marker frame, one per point; `diameter_mm(k)` is point `k`'s disc's diameter
/// (a plate's origin disc may be larger than the rest). Answers the pose and the corrected
/// points (the images of the disc centres).
pub fn solve_pnp_discs(
    camera: &CameraModel,
    points_mm: &[Vec3],
    normals: &[Vec3],
    diameter_mm: impl Fn(usize) -> f64,
    centroids_px: &[Vector2<f64>],
    sigmas_px: &[f64],
    options: &PnpOptions,
) -> Result<(PnpSolution, Vec<Vector2<f64>>), VisionError> {
    let first = solve_pnp_weighted(camera, points_mm, centroids_px, sigmas_px, options)?;
    let pose = &first.camera_from_marker;
    let corrected: Vec<Vector2<f64>> = points_mm
        .iter()
        .zip(normals)
        .zip(centroids_px)
        .enumerate()
        .map(|(k, ((p, n), c))| {
            let centre = (pose * nalgebra::Point3::from(*p)).coords;
            let normal = pose.rotation * n;
            disc_image_offset(camera, &centre, &normal, diameter_mm(k)).map_or(*c, |o| c - o)
        })
        .collect();
    let solution = solve_pnp_weighted(camera, points_mm, &corrected, sigmas_px, options)?;
    Ok((solution, corrected))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Matrix3;
    use proptest::prelude::*;

    /// The centre of the ellipse a pinhole images the disc to (px), in closed form: the disc's
    /// plane maps to the normalized image by the homography `[a b c]` (two in-plane axes and
    /// the centre), its circle `s^2 + t^2 = r^2` to the conic `H^-T diag(1, 1, -r^2) H^-1`, and
    /// an ellipse's area centroid is its centre.
    fn ellipse_centre(
        camera: &CameraModel,
        centre: &Vec3,
        normal: &Vec3,
        diameter: f64,
    ) -> Vector2<f64> {
        let (a, b) = plane_axes(normal).expect("a normal");
        let h = Matrix3::from_columns(&[a, b, *centre]);
        let h_inv = h
            .try_inverse()
            .expect("the plane does not pass through the camera");
        let r = 0.5 * diameter;
        let q = h_inv.transpose() * Matrix3::from_diagonal(&Vec3::new(1.0, 1.0, -r * r)) * h_inv;
        let m = Matrix2::new(q[(0, 0)], q[(0, 1)], q[(1, 0)], q[(1, 1)]);
        let xy = -m.try_inverse().expect("an ellipse") * Vector2::new(q[(0, 2)], q[(1, 2)]);
        Vector2::new(
            camera.fx_px * xy.x + camera.cx_px,
            camera.fy_px * xy.y + camera.cy_px,
        )
    }

    /// The area centroid of the projected disc by brute force: a fine grid of equal cells in
    /// the disc's plane, each projected with its own area (by its corners), no Jacobian.
    fn brute_force(
        camera: &CameraModel,
        centre: &Vec3,
        normal: &Vec3,
        diameter: f64,
    ) -> Vector2<f64> {
        let (a, b) = plane_axes(normal).expect("a normal");
        let r = 0.5 * diameter;
        let cells = 600;
        let step = 2.0 * r / cells as f64;
        let at = |s: f64, t: f64| camera.project(&(centre + a * s + b * t)).expect("in front");
        let (mut sum, mut weight) = (Vector2::zeros(), 0.0);
        for i in 0..cells {
            for j in 0..cells {
                let (s, t) = (-r + (i as f64 + 0.5) * step, -r + (j as f64 + 0.5) * step);
                if s * s + t * t > r * r {
                    continue;
                }
                let h = 0.5 * step;
                let (p00, p10, p01, p11) = (
                    at(s - h, t - h),
                    at(s + h, t - h),
                    at(s - h, t + h),
                    at(s + h, t + h),
                );
                let d1 = p11 - p00;
                let d2 = p01 - p10;
                let w = 0.5 * (d1.x * d2.y - d1.y * d2.x).abs();
                sum += at(s, t) * w;
                weight += w;
            }
        }
        sum / weight - camera.project(centre).expect("in front")
    }

    /// With strong distortion, near the corner of the view, the offset agrees with the brute
    /// force's (whose own error, from the circle's staircase edge, is about 1e-4 of the offset).
    #[test]
    fn the_offset_under_distortion_agrees_with_a_brute_force_centroid() {
        let camera = CameraModel::pinhole(1400.0, 1400.0, 640.0, 512.0, 1280, 1024)
            .with_distortion(&[-0.35, 0.2, 0.001, -0.0008, -0.05]);
        for (centre, normal) in [
            (Vec3::new(900.0, 700.0, 2000.0), Vec3::new(0.5, 0.2, -0.8)),
            (Vec3::new(-800.0, 300.0, 1500.0), Vec3::new(-0.3, 0.6, -0.7)),
            (Vec3::new(0.0, 0.0, 1000.0), Vec3::new(0.7, 0.0, -0.7)),
        ] {
            let offset = disc_image_offset(&camera, &centre, &normal, 60.0).expect("in front");
            let truth = brute_force(&camera, &centre, &normal, 60.0);
            assert!(
                (offset - truth).norm() < 2e-3 * truth.norm().max(0.01),
                "{offset:?} against {truth:?}"
            );
        }
    }

    /// A disc larger than the rest (a plate's origin disc) is corrected by its own diameter:
    /// from exact centroids, the corrected points are the images of the centres, which they
    /// are not when the common diameter is taken for it.
    #[test]
    fn each_disc_is_corrected_by_its_own_diameter() {
        let camera = CameraModel::pinhole(800.0, 800.0, 320.0, 240.0, 640, 480);
        let points: Vec<Vec3> = (0..16)
            .map(|i| Vec3::new(30.0 * (i % 4) as f64, 30.0 * (i / 4) as f64, 0.0))
            .collect();
        let normals = vec![Vec3::z(); points.len()];
        let diameter = |k: usize| if k == 0 { 30.0 } else { 15.0 };
        let camera_from_plate = crate::geometry::Pose::from_parts(
            nalgebra::Translation3::new(-60.0, -40.0, 400.0),
            nalgebra::UnitQuaternion::from_euler_angles(0.5, -0.4, 0.2),
        );
        let images: Vec<Vector2<f64>> = points
            .iter()
            .map(|p| {
                camera
                    .project(&(camera_from_plate * nalgebra::Point3::from(*p)).coords)
                    .expect("in front")
            })
            .collect();
        let centroids: Vec<Vector2<f64>> = points
            .iter()
            .enumerate()
            .map(|(k, p)| {
                let centre = (camera_from_plate * nalgebra::Point3::from(*p)).coords;
                images[k]
                    + disc_image_offset(
                        &camera,
                        &centre,
                        &(camera_from_plate.rotation * Vec3::z()),
                        diameter(k),
                    )
                    .expect("in front")
            })
            .collect();
        let sigmas = vec![0.01; points.len()];
        let options = crate::vision::PnpOptions::default();
        let (_, own) = solve_pnp_discs(
            &camera, &points, &normals, diameter, &centroids, &sigmas, &options,
        )
        .expect("solved");
        let (_, common) = solve_pnp_discs(
            &camera,
            &points,
            &normals,
            |_| 15.0,
            &centroids,
            &sigmas,
            &options,
        )
        .expect("solved");
        let worst = |corrected: &[Vector2<f64>]| {
            corrected
                .iter()
                .zip(&images)
                .map(|(c, i)| (c - i).norm())
                .fold(0.0, f64::max)
        };
        assert!(worst(&own) < 1e-3, "own diameters: {}", worst(&own));
        assert!(
            (common[0] - images[0]).norm() > 10.0 * worst(&own),
            "the common diameter leaves the origin's eccentricity: {}",
            (common[0] - images[0]).norm()
        );
    }

    proptest! {
        /// Under a pinhole the offset is the ellipse's centre minus the centre's image, for
        /// discs from 4 to 400 px across, tilted up to 70 degrees, anywhere in the view.
        #[test]
        fn the_offset_is_the_imaged_ellipses_centre(
            x in -900.0f64..900.0, y in -700.0f64..700.0, z in 400.0f64..6000.0,
            tilt in 0.0f64..1.22, turn in 0.0f64..std::f64::consts::TAU,
            diameter in 2.0f64..60.0,
        ) {
            let camera = CameraModel::pinhole(2400.0, 2400.0, 640.0, 512.0, 1280, 1024);
            let centre = Vec3::new(x, y, z);
            // Tilted from facing the camera (along the viewing ray) by `tilt`.
            let facing = -centre.normalize();
            let side = facing.cross(&Vec3::y()).normalize();
            let up = facing.cross(&side);
            let normal = facing * tilt.cos() + (side * turn.cos() + up * turn.sin()) * tilt.sin();
            let offset = disc_image_offset(&camera, &centre, &normal, diameter).expect("in front");
            let truth = ellipse_centre(&camera, &centre, &normal, diameter)
                - camera.project(&centre).expect("in front");
            prop_assert!((offset - truth).norm() < 1e-8 * (1.0 + truth.norm()),
                "{offset:?} against {truth:?}");
        }
    }
}
