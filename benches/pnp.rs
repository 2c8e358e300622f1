//! PnP per solve for 4, 8, 16 and 64 points: the initialiser (undistortion plus SQPnP for a
//! marker with depth, IPPE for a planar one), the Levenberg-Marquardt refinement, and the whole
//! `solve_pnp` (initialiser, refinement of up to two candidates, checks, covariance).
//!
//! Run: `cargo bench --bench pnp`.

use brokenray::geometry::{Pose, Rotation, Vec3};
use brokenray::vision::{CameraModel, PnpOptions, initial_poses, refine, solve_pnp};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use nalgebra::{Point3, Translation3, Vector2};
use std::hint::black_box;

fn lcg(state: &mut u64) -> f64 {
    *state = state
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*state >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
}

struct Case {
    camera: CameraModel,
    marker: Vec<Vec3>,
    pixels: Vec<Vector2<f64>>,
}

/// The laboratory camera C1 at 3 m from a marker of `n` points, 0.1 px of noise.
fn case(n: usize, planar: bool) -> Case {
    let camera = CameraModel::pinhole(4800.0, 4800.0, 652.0, 508.0, 1280, 1024)
        .with_distortion(&[-0.092, 0.151, 0.0004, -0.0003, 0.0]);
    let mut s = 7 + n as u64;
    let marker: Vec<Vec3> = (0..n)
        .map(|_| {
            let z = if planar { 0.0 } else { lcg(&mut s) * 50.0 };
            Vec3::new(lcg(&mut s) * 150.0, lcg(&mut s) * 150.0, z)
        })
        .collect();
    let pose = Pose::from_parts(
        Translation3::new(-20.0, 10.0, 2990.0),
        Rotation::from_euler_angles(3.0f64.to_radians() + std::f64::consts::PI, 0.2, 0.4),
    );
    let pixels = marker
        .iter()
        .map(|p| {
            let uv = camera
                .project(&(pose * Point3::from(*p)).coords)
                .expect("in front");
            // Approximately Gaussian noise of 0.1 px (sum of uniforms).
            let noise = |s: &mut u64| (lcg(s) + lcg(s) + lcg(s)) * 0.1;
            uv + Vector2::new(noise(&mut s), noise(&mut s))
        })
        .collect();
    Case {
        camera,
        marker,
        pixels,
    }
}

fn bench(c: &mut Criterion) {
    let options = PnpOptions::default();
    for (label, planar) in [("depth", false), ("planar", true)] {
        let mut group = c.benchmark_group(format!("pnp_{label}"));
        for n in [4usize, 8, 16, 64] {
            let k = case(n, planar);
            let start = initial_poses(&k.camera, &k.marker, &k.pixels).expect("solvable")[0];
            let weights = vec![1.0 / options.pixel_sigma_px.powi(2); n];
            group.bench_with_input(BenchmarkId::new("initialise", n), &k, |b, k| {
                b.iter(|| {
                    initial_poses(
                        black_box(&k.camera),
                        black_box(&k.marker),
                        black_box(&k.pixels),
                    )
                })
            });
            group.bench_with_input(BenchmarkId::new("refine", n), &k, |b, k| {
                b.iter(|| {
                    refine(
                        black_box(&k.camera),
                        &k.marker,
                        &k.pixels,
                        &weights,
                        black_box(&start),
                        50,
                    )
                })
            });
            group.bench_with_input(BenchmarkId::new("solve", n), &k, |b, k| {
                b.iter(|| solve_pnp(black_box(&k.camera), &k.marker, &k.pixels, &options))
            });
        }
        group.finish();
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(50).measurement_time(std::time::Duration::from_secs(2)).warm_up_time(std::time::Duration::from_millis(500));
    targets = bench
}
criterion_main!(benches);
