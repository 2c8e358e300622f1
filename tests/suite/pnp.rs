//! PnP on synthetic cameras and markers: exact recovery without noise, a covariance that
//! describes the error with noise, and every refusal.

use crate::common;

use brokenray::geometry::{Pose, Rotation, Vec3};
use brokenray::vision::{CameraModel, PnpOptions, VisionError, solve_pnp, solve_pnp_weighted};
use common::{assert_summed_nees_within, nees};
use nalgebra::{Point3, Translation3, Vector2};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

fn lab_camera() -> CameraModel {
    CameraModel::pinhole(4800.0, 4800.0, 652.0, 508.0, 1280, 1024)
        .with_distortion(&[-0.092, 0.151, 0.0004, -0.0003, 0.0])
}

fn wide_camera() -> CameraModel {
    CameraModel::pinhole(820.0, 815.0, 640.0, 360.0, 1280, 720)
        .with_distortion(&[-0.28, 0.09, 0.001, -0.0007, -0.01])
}

/// `n` points of a marker of half-size `half_mm`: on a plane, or spread in depth too.
fn marker(rng: &mut StdRng, n: usize, half_mm: f64, planar: bool) -> Vec<Vec3> {
    (0..n)
        .map(|_| {
            Vec3::new(
                rng.random_range(-half_mm..half_mm),
                rng.random_range(-half_mm..half_mm),
                if planar {
                    0.0
                } else {
                    rng.random_range(-half_mm * 0.4..half_mm * 0.4)
                },
            )
        })
        .collect()
}

/// A pose looking at the marker from `distance_mm`, tilted up to `tilt_deg` off the view axis.
fn view(rng: &mut StdRng, distance_mm: f64, tilt_deg: f64) -> Pose {
    let tilt = tilt_deg.to_radians();
    let axis = nalgebra::Unit::new_normalize(Vec3::new(
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        0.0,
    ));
    let spin = Rotation::from_axis_angle(&Vec3::z_axis(), rng.random_range(-3.1..3.1));
    let lean = Rotation::from_axis_angle(&axis, rng.random_range(-tilt..tilt));
    // The marker faces the camera: its z axis points back toward it.
    let face = Rotation::from_axis_angle(&Vec3::x_axis(), std::f64::consts::PI);
    let offset = Vec3::new(
        rng.random_range(-0.05..0.05) * distance_mm,
        rng.random_range(-0.05..0.05) * distance_mm,
        distance_mm,
    );
    Pose::from_parts(Translation3::from(offset), lean * face * spin)
}

fn project_all(camera: &CameraModel, pose: &Pose, points: &[Vec3]) -> Vec<Vector2<f64>> {
    points
        .iter()
        .map(|p| {
            camera
                .project(&(pose * Point3::from(*p)).coords)
                .expect("the synthetic marker is in front of the camera")
        })
        .collect()
}

struct Case {
    name: &'static str,
    camera: CameraModel,
    n: usize,
    half_mm: f64,
    planar: bool,
    distance_mm: f64,
    tilt_deg: f64,
}

fn cases() -> Vec<Case> {
    let mut out = Vec::new();
    for &n in &[4usize, 6, 8, 16, 64] {
        for &planar in &[true, false] {
            out.push(Case {
                name: "lab, 3 m, tilted 40 deg",
                camera: lab_camera(),
                n,
                half_mm: 150.0,
                planar,
                distance_mm: 3000.0,
                tilt_deg: 40.0,
            });
            out.push(Case {
                name: "wide, near 0.4 m, oblique 60 deg",
                camera: wide_camera(),
                n,
                half_mm: 100.0,
                planar,
                distance_mm: 400.0,
                tilt_deg: 60.0,
            });
            out.push(Case {
                name: "lab, far 10 m",
                camera: lab_camera(),
                n,
                half_mm: 200.0,
                planar,
                distance_mm: 10_000.0,
                tilt_deg: 20.0,
            });
        }
    }
    out
}

#[test]
fn noise_free_observations_give_the_pose_to_1e9_relative() {
    let mut rng = StdRng::seed_from_u64(61);
    let options = PnpOptions::default();
    for case in cases() {
        for trial in 0..20 {
            let points = marker(&mut rng, case.n, case.half_mm, case.planar);
            let truth = view(&mut rng, case.distance_mm, case.tilt_deg);
            let pixels = project_all(&case.camera, &truth, &points);
            let solution = match solve_pnp(&case.camera, &points, &pixels, &options) {
                Ok(s) => s,
                // A random 4-point draw can be nearly collinear; that refusal is tested below.
                Err(VisionError::Degenerate { .. }) if case.n == 4 => continue,
                Err(e) => panic!(
                    "{} n={} planar={} trial {trial}: {e}",
                    case.name, case.n, case.planar
                ),
            };
            let est = solution.camera_from_marker;
            let rot_err = est.rotation.angle_to(&truth.rotation);
            let t_err = (est.translation.vector - truth.translation.vector).norm()
                / truth.translation.vector.norm();
            assert!(
                rot_err < 1e-9 && t_err < 1e-9,
                "{} n={} planar={} trial {trial}: rotation {rot_err:e} rad, translation {t_err:e} relative",
                case.name,
                case.n,
                case.planar
            );
            assert!(solution.rms_px < 1e-6, "rms {}", solution.rms_px);
        }
    }
}

#[test]
fn with_pixel_noise_the_error_lies_within_the_reported_covariance() {
    let mut rng = StdRng::seed_from_u64(62);
    let sigma_px = 0.1;
    let noise = Normal::new(0.0, sigma_px).expect("valid sigma");
    let options = PnpOptions {
        pixel_sigma_px: sigma_px,
        ..PnpOptions::default()
    };
    let configs = [
        (lab_camera(), 8, 150.0, false, 3000.0, 30.0),
        (lab_camera(), 8, 150.0, true, 3000.0, 30.0),
        (wide_camera(), 16, 100.0, true, 600.0, 50.0),
        (wide_camera(), 64, 100.0, false, 800.0, 45.0),
    ];
    let trials = 1000;
    let mut nees_sum = 0.0;
    for k in 0..trials {
        let (camera, n, half, planar, dist, tilt) = configs[k % configs.len()];
        let points = marker(&mut rng, n, half, planar);
        let truth = view(&mut rng, dist, tilt);
        let pixels: Vec<Vector2<f64>> = project_all(&camera, &truth, &points)
            .into_iter()
            .map(|p| p + Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng)))
            .collect();
        let s = solve_pnp(&camera, &points, &pixels, &options).expect("solvable");
        nees_sum += nees(&s.camera_from_marker, &truth, &s.covariance);
    }
    assert_summed_nees_within(nees_sum, trials, 0.005);
}

#[test]
fn planar_marker_reports_its_ambiguity() {
    // Small and far: the two IPPE solutions fit almost equally well.
    let mut rng = StdRng::seed_from_u64(63);
    let camera = lab_camera();
    let points = vec![
        Vec3::new(-20.0, -20.0, 0.0),
        Vec3::new(20.0, -20.0, 0.0),
        Vec3::new(20.0, 20.0, 0.0),
        Vec3::new(-20.0, 20.0, 0.0),
    ];
    let noise = Normal::new(0.0, 0.1).expect("valid");
    let truth = view(&mut rng, 8000.0, 5.0);
    let pixels: Vec<Vector2<f64>> = project_all(&camera, &truth, &points)
        .into_iter()
        .map(|p| p + Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng)))
        .collect();
    let small_far = solve_pnp(&camera, &points, &pixels, &PnpOptions::default()).expect("solves");
    // Large and near, strongly tilted: unambiguous.
    let big: Vec<Vec3> = points.iter().map(|p| p * 10.0).collect();
    let tilted = view(&mut rng, 2500.0, 1.0);
    let tilted = Pose::from_parts(
        tilted.translation,
        Rotation::from_axis_angle(&Vec3::x_axis(), 0.6) * tilted.rotation,
    );
    let pixels = project_all(&camera, &tilted, &big)
        .into_iter()
        .map(|p| p + Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng)))
        .collect::<Vec<_>>();
    let clear = solve_pnp(&camera, &big, &pixels, &PnpOptions::default()).expect("solves");
    assert!(
        small_far.ambiguity_ratio > 0.3 && clear.ambiguity_ratio < 0.05,
        "ambiguous {} vs clear {}",
        small_far.ambiguity_ratio,
        clear.ambiguity_ratio
    );
}

fn lab_case(seed: u64) -> (CameraModel, Vec<Vec3>, Pose, Vec<Vector2<f64>>) {
    let mut rng = StdRng::seed_from_u64(seed);
    let camera = lab_camera();
    let points = marker(&mut rng, 8, 150.0, false);
    let truth = view(&mut rng, 3000.0, 20.0);
    let pixels = project_all(&camera, &truth, &points);
    (camera, points, truth, pixels)
}

#[test]
fn too_few_points_are_refused() {
    let (camera, points, _, pixels) = lab_case(1);
    let err = solve_pnp(&camera, &points[..3], &pixels[..3], &PnpOptions::default())
        .expect_err("three points");
    assert_eq!(
        err,
        VisionError::NotEnoughPoints {
            given: 3,
            needed: 4
        }
    );
    let err =
        solve_pnp(&camera, &points, &pixels[..7], &PnpOptions::default()).expect_err("unpaired");
    assert!(matches!(
        err,
        VisionError::MismatchedPoints {
            marker_points: 8,
            image_points: 7
        }
    ));
}

#[test]
fn collinear_marker_points_are_refused() {
    let (camera, _, truth, _) = lab_case(2);
    let line: Vec<Vec3> = (0..6)
        .map(|i| Vec3::new(f64::from(i) * 40.0, f64::from(i) * 10.0, 0.0))
        .collect();
    let pixels = project_all(&camera, &truth, &line);
    let err = solve_pnp(&camera, &line, &pixels, &PnpOptions::default()).expect_err("collinear");
    assert!(
        matches!(&err, VisionError::Degenerate { reason } if reason.contains("collinear")),
        "{err}"
    );
}

#[test]
fn points_behind_the_camera_are_refused() {
    // Pixels of a marker behind the camera (the pinhole equations hold for negative depth):
    // the only exact fit puts the points behind, which must not be reported as a pose.
    let (camera, points, _, _) = lab_case(3);
    let behind = Pose::from_parts(
        Translation3::new(30.0, -20.0, -3000.0),
        Rotation::from_axis_angle(&Vec3::y_axis(), 0.3),
    );
    let pixels: Vec<Vector2<f64>> = points
        .iter()
        .map(|p| {
            let q = behind * Point3::from(*p);
            Vector2::new(
                camera.fx_px * q.x / q.z + camera.cx_px,
                camera.fy_px * q.y / q.z + camera.cy_px,
            )
        })
        .collect();
    let camera = CameraModel {
        distortion: [0.0; brokenray::vision::DISTORTION_TERMS],
        ..camera
    };
    let err = solve_pnp(&camera, &points, &pixels, &PnpOptions::default()).expect_err("behind");
    assert!(
        matches!(err, VisionError::BehindCamera { count: 8 }),
        "{err}"
    );
}

#[test]
fn a_fit_over_the_rms_limit_is_refused_and_robust_mode_drops_the_mislabelled_point() {
    let (camera, points, truth, mut pixels) = lab_case(4);
    pixels.swap(2, 5); // two labels exchanged: two wrong points out of eight
    let strict = PnpOptions {
        max_rms_px: 0.5,
        ..PnpOptions::default()
    };
    let err = solve_pnp(&camera, &points, &pixels, &strict).expect_err("mislabelled");
    assert!(
        matches!(err, VisionError::ReprojectionTooLarge { limit_px, .. } if limit_px == 0.5),
        "{err}"
    );

    let (_, _, _, mut one_wrong) = lab_case(4);
    one_wrong[6] += Vector2::new(35.0, -20.0);
    let robust = PnpOptions {
        robust: true,
        ..strict
    };
    let s = solve_pnp(&camera, &points, &one_wrong, &robust).expect("robust mode recovers");
    assert_eq!(s.rejected_points, vec![6]);
    assert_eq!(s.points, 7);
    assert!(s.camera_from_marker.rotation.angle_to(&truth.rotation) < 1e-9);
    assert!(matches!(
        solve_pnp(&camera, &points, &one_wrong, &strict),
        Err(VisionError::ReprojectionTooLarge { .. })
    ));
}

#[test]
fn non_finite_input_is_named() {
    let (camera, points, _, mut pixels) = lab_case(5);
    pixels[3].x = f64::NAN;
    let err = solve_pnp(&camera, &points, &pixels, &PnpOptions::default()).expect_err("NaN");
    assert_eq!(
        err,
        VisionError::NonFinite {
            what: "image point 3".into()
        }
    );
}

#[test]
fn duplicated_image_points_are_refused_as_a_degenerate_view() {
    // Every pixel at the same place: no pose reproduces it from a marker with extent.
    let (camera, points, _, _) = lab_case(6);
    let pixels = vec![Vector2::new(640.0, 500.0); points.len()];
    let err = solve_pnp(&camera, &points, &pixels, &PnpOptions::default()).expect_err("degenerate");
    assert!(
        matches!(
            err,
            VisionError::Degenerate { .. }
                | VisionError::ReprojectionTooLarge { .. }
                | VisionError::BehindCamera { .. }
        ),
        "{err}"
    );
}

#[test]
fn per_point_sigmas_weight_the_fit_and_the_covariance_stays_honest() {
    // Each point has its own noise, from 0.005 to 0.1 px (a detector's sigmas: large bright
    // discs near the centre, small faint ones at the edge). Weighted by those sigmas the error lies
    // within the reported covariance, and it is smaller than the error of the uniform fit.
    let mut rng = StdRng::seed_from_u64(64);
    let options = PnpOptions {
        pixel_sigma_px: 0.001,
        ..PnpOptions::default()
    };
    let trials = 800;
    let (mut nees_sum, mut weighted_sq, mut uniform_sq) = (0.0, 0.0, 0.0);
    for k in 0..trials {
        let camera = if k % 2 == 0 {
            lab_camera()
        } else {
            wide_camera()
        };
        let (n, half, dist) = if k % 2 == 0 {
            (12, 150.0, 3000.0)
        } else {
            (16, 100.0, 700.0)
        };
        let points = marker(&mut rng, n, half, k % 4 < 2);
        let truth = view(&mut rng, dist, 30.0);
        let sigmas: Vec<f64> = (0..n).map(|_| rng.random_range(0.005..0.1)).collect();
        let pixels: Vec<Vector2<f64>> = project_all(&camera, &truth, &points)
            .into_iter()
            .zip(&sigmas)
            .map(|(p, s)| {
                let noise = Normal::new(0.0, *s).expect("valid sigma");
                p + Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng))
            })
            .collect();
        let weighted =
            solve_pnp_weighted(&camera, &points, &pixels, &sigmas, &options).expect("solvable");
        nees_sum += nees(&weighted.camera_from_marker, &truth, &weighted.covariance);
        // The marker origin's position error in the camera frame.
        let error =
            |pose: &Pose| (pose.translation.vector - truth.translation.vector).norm_squared();
        weighted_sq += error(&weighted.camera_from_marker);
        let rms_sigma = (sigmas.iter().map(|s| s * s).sum::<f64>() / n as f64).sqrt();
        let uniform = solve_pnp(
            &camera,
            &points,
            &pixels,
            &PnpOptions {
                pixel_sigma_px: rms_sigma,
                ..options
            },
        )
        .expect("solvable");
        uniform_sq += error(&uniform.camera_from_marker);
    }
    assert_summed_nees_within(nees_sum, trials, 0.005);
    eprintln!(
        "weighted: mean NEES {:.3}; mean square translation error {:.3e} mm^2, uniform {:.3e}",
        nees_sum / trials as f64,
        weighted_sq / trials as f64,
        uniform_sq / trials as f64
    );
    assert!(
        weighted_sq < 0.8 * uniform_sq,
        "weighted mean square translation error {:.4} mm^2 vs uniform {:.4} mm^2",
        weighted_sq / trials as f64,
        uniform_sq / trials as f64
    );
}

#[test]
fn per_point_sigmas_are_checked() {
    let (camera, points, _, pixels) = lab_case(5);
    let options = PnpOptions::default();
    let err = solve_pnp_weighted(&camera, &points, &pixels, &[0.1; 7], &options)
        .expect_err("one sigma short");
    assert!(
        matches!(err, VisionError::MismatchedPoints { .. }),
        "{err:?}"
    );
    let mut sigmas = vec![0.1; 8];
    sigmas[3] = f64::NAN;
    let err =
        solve_pnp_weighted(&camera, &points, &pixels, &sigmas, &options).expect_err("a NaN sigma");
    assert!(err.to_string().contains("image point 3"), "{err}");
    sigmas[3] = -0.1;
    assert!(solve_pnp_weighted(&camera, &points, &pixels, &sigmas, &options).is_err());
    // Equal sigmas give the uniform fit: same pose, same covariance.
    let a = solve_pnp_weighted(&camera, &points, &pixels, &[0.0; 8], &options).expect("solves");
    let b = solve_pnp(&camera, &points, &pixels, &options).expect("solves");
    assert!(
        (a.camera_from_marker.translation.vector - b.camera_from_marker.translation.vector).norm()
            < 1e-9
    );
    assert!((a.covariance - b.covariance).norm() <= 1e-9 * b.covariance.norm());
}

#[test]
fn the_intrinsics_sensitivity_predicts_the_pose_a_perturbed_camera_solves_to() {
    // Independent computation: the same pixels solved again by a camera whose intrinsic k
    // is off by a small step; the pose moves (as a left perturbation) by the sensitivity's
    // column k times the step, to first order.
    use brokenray::geometry::se3_log;
    use brokenray::vision::intrinsics_sensitivity;
    let mut rng = StdRng::seed_from_u64(71);
    let options = PnpOptions::default();
    for case in cases().into_iter().filter(|c| c.n >= 8) {
        let points = marker(&mut rng, case.n, case.half_mm, case.planar);
        let truth = view(&mut rng, case.distance_mm, case.tilt_deg);
        let pixels = project_all(&case.camera, &truth, &points);
        let s =
            intrinsics_sensitivity(&case.camera, &points, &truth, None).expect("a determined pose");
        // Steps a hundredth of what a calibration is off by (5e-6 of a focal length, 0.003 px
        // of the principal point, small distortion terms): the derivative is what is tested,
        // and a weak geometry (a planar marker at 10 m) bends within a tenth of a calibration's
        // error already.
        let f = case.camera.fx_px;
        let steps = [5e-6 * f, 5e-6 * f, 3e-3, 3e-3, 1e-5, 1e-5, 1e-7, 1e-7, 1e-5];
        for (k, step) in steps.iter().enumerate() {
            let mut theta = brokenray::vision::intrinsics_of(&case.camera);
            theta[k] += step;
            let perturbed = CameraModel {
                fx_px: theta[0],
                fy_px: theta[1],
                cx_px: theta[2],
                cy_px: theta[3],
                distortion: std::array::from_fn(|k| theta[4 + k]),
                ..case.camera
            };
            let moved = solve_pnp(&perturbed, &points, &pixels, &options)
                .expect("solved")
                .camera_from_marker;
            let actual = se3_log(&(moved * truth.inverse()));
            let predicted = s.column(k) * *step;
            // Second-order terms: a few per cent of the move at most, plus the solver's rounding.
            let scale = actual.norm().max(predicted.norm());
            assert!(
                (actual - predicted).norm() <= 0.03 * scale + 1e-6,
                "{} n={} planar={}: intrinsic {k}: moved {actual:?}, predicted {predicted:?}",
                case.name,
                case.n,
                case.planar
            );
        }
    }
}
