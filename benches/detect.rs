//! One camera frame through the pipeline the service runs on `POST /frames`, on the built-in
//! installation's camera C1 (1280 x 1024) seeing marker B (eight 20 mm discs at 3 m, about
//! 32 px across), 0.6 px blur, read and shot noise:
//!
//! * `detect`: background tiles, threshold, components, shape gates, centroids with their
//!   covariance;
//! * `observe_frame`: detection near the predicted points, identification, weighted PnP, the
//!   eccentricity correction and PnP again (the whole per-frame work), from a good prediction
//!   (the near search) and from one 32 px off (the near search fails, the wide one follows);
//! * `decode png` / `decode pgm`: the 8-bit frame file decoded into a grey frame.
//!
//! Rendering is outside the timed loops. Run: `cargo bench --bench detect`.

use brokenray::config::default_installation;
use brokenray::imagefile::{FrameFormat, decode, encode};
use brokenray::model::{LinkKind, Observer, observe_frame};
use brokenray::sim::render::{RenderSettings, marker_discs, render_discs};
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
