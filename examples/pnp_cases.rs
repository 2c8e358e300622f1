//! Writes PnP test cases with this crate's solutions, for `scripts/pnp_vs_opencv.py`.
//!
//! Run: `cargo run --release --example pnp_cases > target/pnp_cases.ndjson`.
//! Each line: the camera, the marker points, the noisy pixels, the true `camera_from_marker`
//! and this crate's estimate (all `t_mm` and row-major `r`).

use brokenray::geometry::{Pose, Rotation, Vec3};
use brokenray::vision::{CameraModel, PnpOptions, solve_pnp};
use nalgebra::{Point3, Translation3, Vector2};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use serde_json::json;

fn rows(p: &Pose) -> Vec<Vec<f64>> {
    let m = p.rotation.to_rotation_matrix().into_inner();
    (0..3)
        .map(|i| (0..3).map(|j| m[(i, j)]).collect())
        .collect()
}

fn main() {
    let mut rng = StdRng::seed_from_u64(2026);
    let noise = Normal::new(0.0, 0.1).expect("sigma");
    let camera = CameraModel::pinhole(4800.0, 4800.0, 652.0, 508.0, 1280, 1024)
        .with_distortion(&[-0.092, 0.151, 0.0004, -0.0003, 0.0]);
    for (label, planar, n) in [
        ("depth-8", false, 8),
        ("planar-8", true, 8),
        ("depth-16", false, 16),
        ("planar-4", true, 4),
    ] {
        for _ in 0..500 {
            let marker: Vec<Vec3> = (0..n)
                .map(|_| {
                    let z = if planar {
                        0.0
                    } else {
                        rng.random_range(-100.0..100.0)
                    };
                    Vec3::new(
                        rng.random_range(-250.0..250.0),
                        rng.random_range(-200.0..200.0),
                        z,
                    )
                })
                .collect();
            let tilt = Rotation::from_euler_angles(
                std::f64::consts::PI + rng.random_range(-0.5..0.5),
                rng.random_range(-0.5..0.5),
                rng.random_range(-3.1..3.1),
            );
            let truth = Pose::from_parts(
                Translation3::new(
                    rng.random_range(-50.0..50.0),
                    rng.random_range(-50.0..50.0),
                    rng.random_range(2500.0..3500.0),
                ),
                tilt,
            );
            let pixels: Vec<Vector2<f64>> = marker
                .iter()
                .map(|p| {
                    camera
                        .project(&(truth * Point3::from(*p)).coords)
                        .expect("in front")
                        + Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng))
                })
                .collect();
            let ours = solve_pnp(&camera, &marker, &pixels, &PnpOptions::default())
                .inspect_err(|e| eprintln!("{label}: {e}"))
                .ok();
            println!(
                "{}",
                json!({
                    "case": label,
                    "camera": {"fx": camera.fx_px, "fy": camera.fy_px, "cx": camera.cx_px, "cy": camera.cy_px, "distortion": camera.distortion},
                    "marker_mm": marker.iter().map(|p| [p.x, p.y, p.z]).collect::<Vec<_>>(),
                    "pixels": pixels.iter().map(|p| [p.x, p.y]).collect::<Vec<_>>(),
                    "truth": {"t_mm": truth.translation.vector.as_slice(), "r": rows(&truth)},
                    "ours": ours.map(|s| json!({"t_mm": s.camera_from_marker.translation.vector.as_slice(), "r": rows(&s.camera_from_marker)})),
                })
            );
        }
    }
}
