//! One camera frame through the pipeline the service runs on `POST /frames`, on the built-in
//! installation's camera C1 (1280 x 1024) seeing marker B (eight 20 mm discs at 3 m, about
//! 32 px across), 0.6 px blur, read and shot noise:
//!
//! * `detect`: background tiles, threshold, components, shape gates, centroids with their
//!   covariance;
//! * `observe_frame`: detection near the predicted points, identification, weighted PnP, the
//!   eccentricity correction and PnP again (the whole per-frame work), from a good prediction
//!   (the near search) and from one 32 px off (the near search fails, the wide one follows);
//! * `decode png` / `decode pgm`: the 8-bit frame file decoded into a grey frame;
//! * at 1600 x 1200 (the same marker and lens, turned about 27 degrees, 30 pieces of clutter
//!   around it and none over its discs): `observe_frame` tracked (a good prediction), and with
//!   no prior (the whole frame detected, then the search from the layout alone and PnP), and
//!   that frame's detection alone.
//!
//! Rendering is outside the timed loops. Run: `cargo bench --bench detect`.

use brokenray::config::default_installation;
use brokenray::geometry::{Twist, se3_exp};
use brokenray::imagefile::{FrameFormat, decode, encode};
use brokenray::model::{LinkKind, Observer, find_without_prior, observe_frame};
use brokenray::sim::render::{Clutter, RenderSettings, marker_discs, render_discs, render_scene};
use brokenray::vision::{CameraModel, SearchArea, detect_in};
use brokenray::vision::{DetectSettings, detect};
use criterion::{Criterion, criterion_group, criterion_main};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let installation = default_installation();
    let observer = Observer::new(&installation.model);
    let link = observer.link("C1", "B").expect("C1 sees B");
    let nominal = match &installation.model.link(link.link).kind {
        LinkKind::Measured(m) => m.nominal.expect("a nominal pose"),
        LinkKind::Calibrated { .. } => unreachable!("C1_from_B is measured"),
    };
    let frame = render_discs(
        &link.camera,
        &marker_discs(link, &nominal),
        &RenderSettings::default(),
    );
    let settings = DetectSettings {
        gain_e_per_dn: link.gain_e_per_dn,
        ..DetectSettings::default()
    };
    assert_eq!(
        detect(&frame, &settings).len(),
        8,
        "the bench frame shows eight discs"
    );
    c.bench_function("detect 1280x1024, 8 discs of 32 px", |b| {
        b.iter(|| detect(black_box(&frame), black_box(&settings)))
    });
    // Predicted from the true pose (the marker is where the filter expects it: the near search),
    // or from one 20 mm off (32 px: the near search fails and the wide one follows).
    let off = nalgebra::Isometry3::translation(20.0, 0.0, 0.0) * nominal;
    for (name, prior) in [
        ("a good prediction", nominal),
        ("a prediction 32 px off", off),
    ] {
        let seen = observe_frame(&observer, "C1", &frame, |_| vec![prior]).expect("C1's frame");
        assert!(
            seen.markers[0].result.is_ok(),
            "the bench frame's marker is found"
        );
        println!(
            "{name}: {:.3} of the frame searched",
            seen.searched_fraction
        );
        c.bench_function(
            &format!("observe_frame 1280x1024 from {name} (detect, identify, PnP twice)"),
            |b| {
                b.iter(|| {
                    observe_frame(&observer, "C1", black_box(&frame), |_| vec![prior])
                        .expect("C1's frame")
                        .markers
                        .len()
                })
            },
        );
    }
    // 1600 x 1200: tracked, and found with no prior among clutter.
    let mut link_1600 = link.clone();
    link_1600.camera = CameraModel {
        width_px: 1600,
        height_px: 1200,
        cx_px: 803.0,
        cy_px: 597.0,
        ..link.camera
    };
    let observer_1600 = Observer::from_links(vec![link_1600.clone()]);
    let tilted = nominal * se3_exp(&Twist::new(0.0, 0.0, 300.0, 0.35, 0.35, 0.3));
    let mut discs = marker_discs(&link_1600, &tilted);
    let marker_px: Vec<_> = discs
        .iter()
        .filter_map(|d| link_1600.camera.project(&d.centre_mm))
        .collect();
    let clutter = Clutter::scattered(&link_1600.camera, 30, 3000.0, 5).clear_of(
        &link_1600.camera,
        &marker_px,
        12.0,
    );
    discs.extend(clutter.discs.iter().copied());
    let frame_1600 = render_scene(
        &link_1600.camera,
        &discs,
        &clutter.shapes,
        &RenderSettings::default(),
    );
    let whole = SearchArea::whole(1600, 1200);
    let found = find_without_prior(&link_1600, &detect_in(&frame_1600, &settings, &whole), None)
        .expect("found with no prior");
    println!(
        "1600x1200 with no prior: {} points, {} blobs in the frame",
        found.ids.len(),
        detect_in(&frame_1600, &settings, &whole).len()
    );
    c.bench_function("no prior 1600x1200: detect the whole frame alone", |b| {
        b.iter(|| detect_in(black_box(&frame_1600), &settings, &whole).len())
    });
    c.bench_function(
        "no prior 1600x1200: detect the whole frame, search, PnP",
        |b| {
            b.iter(|| {
                let blobs = detect_in(black_box(&frame_1600), &settings, &whole);
                find_without_prior(&link_1600, &blobs, None).map(|f| f.ids.len())
            })
        },
    );
    let blobs_1600 = detect_in(&frame_1600, &settings, &whole);
    c.bench_function("no prior 1600x1200: the search and PnP alone", |b| {
        b.iter(|| find_without_prior(&link_1600, black_box(&blobs_1600), None).map(|f| f.ids.len()))
    });
    c.bench_function(
        "tracked 1600x1200: observe_frame from a good prediction",
        |b| {
            b.iter(|| {
                observe_frame(&observer_1600, "C1", black_box(&frame_1600), |_| {
                    vec![tilted]
                })
                .expect("C1's frame")
                .markers
                .len()
            })
        },
    );
    let size = Some((frame.width_px(), frame.height_px()));
    for format in [FrameFormat::Png, FrameFormat::Pgm] {
        let bytes = encode(&frame, format).expect("encodes");
        c.bench_function(&format!("decode {format:?} 1280x1024 8-bit"), |b| {
            b.iter(|| decode(black_box(&bytes), format, size).expect("decodes"))
        });
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(30).measurement_time(std::time::Duration::from_secs(3)).warm_up_time(std::time::Duration::from_millis(500));
    targets = bench
}
criterion_main!(benches);
