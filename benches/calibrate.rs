//! Camera calibration: 20 views of a 7 x 9 plate (1260 points), the whole `calibrate_camera`
//! (closed form, the bundle adjustment over 9 intrinsics and 20 poses, the eccentricity rounds,
//! covariance, checks) on one core; and finding the plate among a frame's 63 detected discs.
//!
//! Run: `cargo bench --bench calibrate`.

use brokenray::sim::plate::{plate_discs, plate_poses};
use brokenray::vision::{
    Blob, CalibrationOptions, CalibrationView, CameraModel, Plate, Polarity, calibrate_camera,
    disc_image_offset,
};
use criterion::{Criterion, criterion_group, criterion_main};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use std::hint::black_box;

/// A 1280 x 1024 camera with a common lens and marked barrel distortion.
fn camera() -> CameraModel {
    CameraModel::pinhole(1650.0, 1648.0, 645.3, 508.9, 1280, 1024)
        .with_distortion(&[-0.19, 0.11, 0.0006, -0.0004, -0.02])
}

/// The plate's disc centroids in each view with 0.01 px of noise.
fn views(camera: &CameraModel, plate: &Plate, n: usize) -> Vec<CalibrationView> {
    let mut rng = rand::rngs::StdRng::seed_from_u64(3);
    let noise = Normal::new(0.0, 0.01).expect("a valid sigma");
    plate_poses(camera, plate, n, 9)
        .iter()
        .map(|pose| CalibrationView {
            points_px: plate_discs(plate, pose)
                .iter()
                .map(|d| {
                    camera.project(&d.centre_mm).expect("in front")
                        + disc_image_offset(camera, &d.centre_mm, &d.normal, d.diameter_mm)
                            .expect("in front")
                        + nalgebra::Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng))
                })
                .collect(),
            ids: (0..plate.len()).collect(),
            sigmas_px: Some(vec![0.01; plate.len()]),
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let camera = camera();
    let plate = Plate::new(7, 9, 15.0, 7.5, true, Polarity::Dark).expect("a valid plate");
    let views = views(&camera, &plate, 20);
    let options = CalibrationOptions::default();
    let mut group = c.benchmark_group("calibrate");
    group.sample_size(10);
    group.bench_function("20 views of 7x9", |b| {
        b.iter(|| {
            calibrate_camera(black_box(&plate), 1280, 1024, black_box(&views), &options)
                .expect("calibrated")
        })
    });
    group.finish();
    let blobs: Vec<Blob> = views[3]
        .points_px
        .iter()
        .rev()
        .map(|p| Blob {
            centre_px: [p.x, p.y],
            covariance_px2: [[1e-4, 0.0], [0.0, 1e-4]],
            area_px: 300.0,
            ellipse: [10.0, 9.0, 0.0],
            contrast_dn: 150.0,
            background_dn: 200.0,
        })
        .collect();
    c.bench_function("find a 7x9 plate among 63 discs", |b| {
        b.iter(|| plate.find(black_box(&blobs)).expect("found"))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
