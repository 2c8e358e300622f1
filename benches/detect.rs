//! Disc detection on a full 1280 x 1024 frame (the laboratory camera C1) holding a marker of
//! eight 20 mm discs at 3 m (about 32 px across), 0.6 px blur, read and shot noise: background
//! tiles, threshold, components, shape gates and the centroid with its covariance. Rendering is
//! outside the timed loop.
//!
//! Run: `cargo bench --bench detect`.

use brokenray::geometry::Vec3;
use brokenray::sim::render::{Disc, RenderSettings, render_discs};
use brokenray::vision::{CameraModel, DetectSettings, detect};
use criterion::{Criterion, criterion_group, criterion_main};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let camera = CameraModel {
        distortion: [-0.092, 0.151, 0.0004, -0.0003, 0.0],
        ..CameraModel::pinhole(4800.0, 4800.0, 652.0, 508.0, 1280, 1024)
    };
    // Eight discs on a 100 mm circle, the marker tilted by 20 degrees about x.
    let tilt = 20f64.to_radians();
    let normal = Vec3::new(0.0, tilt.sin(), -tilt.cos());
    let discs: Vec<Disc> = (0..8)
        .map(|k| {
            let a = f64::from(k) / 8.0 * std::f64::consts::TAU;
            let p = Vec3::new(
                50.0 * a.cos(),
                50.0 * a.sin() * tilt.cos(),
                50.0 * a.sin() * tilt.sin(),
            );
            Disc {
                centre_mm: Vec3::new(-20.0, 10.0, 2990.0) + p,
                normal,
                diameter_mm: 20.0,
            }
        })
        .collect();
    let frame = render_discs(&camera, &discs, &RenderSettings::default());
    let settings = DetectSettings::default();
    assert_eq!(
        detect(&frame, &settings).len(),
        8,
        "the bench frame shows eight discs"
    );
    c.bench_function("detect 1280x1024, 8 discs of 32 px", |b| {
        b.iter(|| detect(black_box(&frame), black_box(&settings)))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
