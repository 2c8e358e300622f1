//! `POST /api/v1/frames` when no frame can be predicted from the one before: the release binary
//! in its own process, camera C1 of the built-in installation given a 1600 x 1200 sensor, and a
//! client posting its frames back to back (one in flight), each showing marker B at a new pose
//! (turned up to 20 degrees about each axis, moved up to 150 mm across and 400 mm in depth
//! from its nominal pose) among 30 pieces of clutter (stray discs, bars, rings, triangles).
//! Every frame is therefore searched with no prior: the prediction from the last pose misses,
//! the whole frame is detected and the marker found from its layout alone, then PnP and a
//! durable commit of the sample, as a camera whose marker was just moved, or a start-up, costs.
//! `[pnp] lost_search_interval_s = 0` lets a lost marker be searched in every frame.
//!
//! Prints the frames answered a second (wall time, one in flight), the server's CPU (user +
//! system time from `/proc`) and the frames a second of one core's CPU time (frames over CPU
//! seconds), and whether every marker was found and stored.
//!
//! Options (environment): `SECONDS` (default 10), `FRAMES` (default 100 rendered, cycled),
//! `FORMAT=png` (default `pgm`), `OUT=DIR` (the frames written there as `frame-NNNN.pgm` with
//! `truth.json`: the camera, the marker's points and each frame's true pose, for
//! `scripts/no_prior_vs_opencv.py`).
//!
//! Run: `cargo bench --bench frames_no_prior` (Linux).

#[path = "support/load.rs"]
mod load;
#[path = "../tests/suite/common/process.rs"]
#[allow(
    dead_code,
    reason = "the bench lets Drop stop the server; the tests kill it"
)]
mod process;

use brokenray::clock::format_ns;
use brokenray::geometry::{Twist, se3_exp};
use brokenray::imagefile::{FrameFormat, encode};
use brokenray::model::{LinkKind, Observer, find_without_prior};
use brokenray::sim::render::{Clutter, RenderSettings, marker_discs, render_scene};
use brokenray::vision::{CameraModel, DetectSettings, SearchArea, detect_in};
use load::{cpu_s, post_frame, wall_ns};
use rand::{Rng, SeedableRng};
use std::time::{Duration, Instant};

/// The sensor the frames are rendered for, and the installation's C1 is given.
const WIDTH: u32 = 1600;
const HEIGHT: u32 = 1200;
const CX: f64 = 803.0;
const CY: f64 = 597.0;

/// One rendered frame: its file and the pose it shows.
struct Rendered {
    bytes: Vec<u8>,
    camera_from_marker: brokenray::geometry::Pose,
}

fn main() {
    if std::env::args().any(|a| a == "--test")
        || !std::env::args().any(|a| a == "--bench")
        || !cfg!(target_os = "linux")
    {
        println!("no-prior frames bench: run with `cargo bench --bench frames_no_prior`");
        return;
    }
    let seconds: f64 = std::env::var("SECONDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(10.0);
    let count: usize = std::env::var("FRAMES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(100)
        .max(2);
    let format = match std::env::var("FORMAT").as_deref() {
        Ok("png") => FrameFormat::Png,
        Ok("pgm") | Err(_) => FrameFormat::Pgm,
        Ok(other) => panic!("FORMAT is png or pgm, not {other}"),
    };
    let out = std::env::var("OUT").ok().map(std::path::PathBuf::from);

    let dir = tempfile::tempdir().expect("a temporary directory");
    let default = brokenray::config::DEFAULT_INSTALLATION_TOML;
    let c1 = "frame = \"C1\"\nwidth = 1280\nheight = 1024\nfx = 4800.0\nfy = 4800.0\ncx = 652.0\ncy = 508.0\n";
    assert!(
        default.contains(c1),
        "C1's block of the built-in installation changed"
    );
    let text = format!(
        "[pnp]\nlost_search_interval_s = 0\n\n{}",
        default
            .replace(
                c1,
                &format!(
                    "frame = \"C1\"\nwidth = {WIDTH}\nheight = {HEIGHT}\nfx = 4800.0\nfy = 4800.0\ncx = {CX:.1}\ncy = {CY:.1}\n"
                ),
            )
            .replace("listen = \"127.0.0.1:7878\"", "listen = \"127.0.0.1:0\"")
            .replace(
                "database = \"brokenray.db\"",
                &format!("database = \"{}\"", dir.path().join("load.db").display()),
            )
    );
    let config = dir.path().join("load.toml");
    std::fs::write(&config, &text).expect("the config file");
    let installation = brokenray::config::parse("load.toml", &text).expect("a valid installation");

    // The frames: the marker at a new pose in each, clutter around it (none over its discs).
    let observer = Observer::new(&installation.model);
    let link = observer.link("C1", "B").expect("C1 sees B").clone();
    assert_eq!(link.camera.width_px, WIDTH, "C1 has the bench's sensor");
    let nominal = match &installation.model.link(link.link).kind {
        LinkKind::Measured(m) => m.nominal.expect("a nominal pose"),
        LinkKind::Calibrated { .. } => unreachable!("C1_from_B is measured"),
    };
    // 16 x 16 samples a pixel (the frames load bench's): the discs' edges as smooth as a
    // detector sees, and the 100 frames rendered in about half a minute.
    let mut settings = RenderSettings {
        samples_per_side: 16,
        ..RenderSettings::default()
    };
    let detect_settings = DetectSettings {
        gain_e_per_dn: link.gain_e_per_dn,
        ..DetectSettings::default()
    };
    let mut rng = rand::rngs::StdRng::seed_from_u64(11);
    let render_start = Instant::now();
    let mut frames: Vec<Rendered> = Vec::with_capacity(count);
    let mut refused = 0usize;
    while frames.len() < count {
        let turn = 20f64.to_radians();
        let twist = Twist::new(
            rng.random_range(-150.0..150.0),
            rng.random_range(-150.0..150.0),
            rng.random_range(0.0..400.0),
            rng.random_range(-turn..turn),
            rng.random_range(-turn..turn),
            rng.random_range(-turn..turn),
        );
        let pose = nominal * se3_exp(&twist);
        let mut discs = marker_discs(&link, &pose);
        let marker_px: Vec<_> = discs
            .iter()
            .filter_map(|d| link.camera.project(&d.centre_mm))
            .collect();
        let inside = marker_px.len() == discs.len()
            && marker_px.iter().all(|p| {
                (40.0..f64::from(WIDTH) - 40.0).contains(&p.x)
                    && (40.0..f64::from(HEIGHT) - 40.0).contains(&p.y)
            });
        if !inside {
            continue;
        }
        let clutter = Clutter::scattered(&link.camera, 30, 3000.0, rng.random()).clear_of(
            &link.camera,
            &marker_px,
            12.0,
        );
        discs.extend(clutter.discs.iter().copied());
        settings.seed = rng.random();
        let frame = render_scene(&link.camera, &discs, &clutter.shapes, &settings);
        // Only frames the search can solve alone are posted: the bench measures speed, and
        // says how many it rendered and left out.
        let blobs = detect_in(&frame, &detect_settings, &SearchArea::whole(WIDTH, HEIGHT));
        if find_without_prior(&link, &blobs, None).is_err() {
            refused += 1;
            continue;
        }
        frames.push(Rendered {
            bytes: encode(&frame, format).expect("encodes"),
            camera_from_marker: pose,
        });
    }
    println!(
        "rendered {count} frames of {WIDTH} x {HEIGHT} in {:.1} s ({format:?}, about {:.0} KiB a frame); {refused} more rendered and left out, not found with no prior in process",
        render_start.elapsed().as_secs_f64(),
        frames[0].bytes.len() as f64 / 1024.0,
    );
    in_process(&observer, &frames, &detect_settings, format);
    if let Some(out) = &out {
        write_frames(out, &link.camera, &link.points_mm, &frames, format);
    }

    let server = process::start(
        &config,
        "warn,brokenray=info",
        false,
        Duration::from_secs(120),
    );
    let pid = server.child.id();
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let client = reqwest::Client::new();
    let (answered, found, whole, searched, stored, errors, cpu, wall) = runtime.block_on(async {
        let cpu0 = cpu_s(pid);
        let t0 = Instant::now();
        let end = t0 + Duration::from_secs_f64(seconds);
        let (mut answered, mut found, mut whole, mut stored, mut errors) =
            (0u64, 0u64, 0u64, 0u64, 0u64);
        let mut searched = 0.0;
        let mut k = 0usize;
        while Instant::now() < end {
            let time = format_ns(wall_ns());
            let body = frames[k % frames.len()].bytes.clone();
            k += 1;
            match post_frame(&client, &server.base, "C1", &time, format, body).await {
                Ok(body) => {
                    answered += 1;
                    if body["markers"][0]["found"] == true {
                        found += 1;
                    }
                    let fraction = body["searched_fraction"].as_f64().unwrap_or(0.0);
                    searched += fraction;
                    if fraction >= 1.0 {
                        whole += 1;
                    }
                    stored += body["ingest"]["stored"].as_u64().unwrap_or(0);
                }
                Err(e) => {
                    errors += 1;
                    eprintln!("C1: {e}");
                }
            }
        }
        let wall = t0.elapsed().as_secs_f64();
        let searched = searched / answered.max(1) as f64;
        (
            answered,
            found,
            whole,
            searched,
            stored,
            errors,
            cpu_s(pid) - cpu0,
            wall,
        )
    });
    println!(
        "{answered} frames answered in {wall:.1} s: {:.1} frames/s, one in flight; {found} markers found, {whole} frames searched whole ({searched:.2} of a frame searched on average), {stored} samples stored, {errors} errors",
        answered as f64 / wall,
    );
    println!(
        "server CPU: {cpu:.2} s = {:.2} cores; {:.1} frames per CPU second of the server",
        cpu / wall,
        answered as f64 / cpu,
    );
}

/// The same frames in this process, on one core, each from the previous frame's pose (what
/// the service predicts from): decoding, then `observe_frame` (the near and wide searches that
/// miss, the whole frame detected and searched, PnP), and the parts.
fn in_process(
    observer: &Observer,
    frames: &[Rendered],
    settings: &DetectSettings,
    format: FrameFormat,
) {
    let images: Vec<_> = frames
        .iter()
        .map(|f| brokenray::imagefile::decode(&f.bytes, format, None).expect("decodes"))
        .collect();
    let timed = |what: &str, f: &mut dyn FnMut(usize)| {
        let t0 = Instant::now();
        for round in 0..3 {
            for k in 0..frames.len() {
                f(round * frames.len() + k);
            }
        }
        let ms = t0.elapsed().as_secs_f64() * 1e3 / (3 * frames.len()) as f64;
        println!("in process, a frame: {what} {ms:.2} ms");
    };
    timed("decoding", &mut |k| {
        std::hint::black_box(
            brokenray::imagefile::decode(&frames[k % frames.len()].bytes, format, None)
                .expect("decodes"),
        );
    });
    let whole = SearchArea::whole(WIDTH, HEIGHT);
    timed("detecting the whole frame", &mut |k| {
        std::hint::black_box(detect_in(&images[k % frames.len()], settings, &whole));
    });
    let link = observer.link("C1", "B").expect("C1 sees B");
    timed("detecting the whole frame and searching it", &mut |k| {
        let blobs = detect_in(&images[k % frames.len()], settings, &whole);
        std::hint::black_box(find_without_prior(link, &blobs, None).is_ok());
    });
    timed("observe_frame from the previous frame's pose", &mut |k| {
        let n = frames.len();
        let prior = frames[(k + n - 1) % n].camera_from_marker;
        let seen = brokenray::model::observe_frame(observer, "C1", &images[k % n], |_| vec![prior])
            .expect("C1's frame");
        std::hint::black_box(seen.markers[0].result.is_ok());
    });
}

/// Writes the frames and what the comparison needs to know of them.
fn write_frames(
    out: &std::path::Path,
    camera: &CameraModel,
    points_mm: &[brokenray::geometry::Vec3],
    frames: &[Rendered],
    format: FrameFormat,
) {
    std::fs::create_dir_all(out).expect("the output directory");
    let extension = if format == FrameFormat::Pgm {
        "pgm"
    } else {
        "png"
    };
    let mut truth = Vec::with_capacity(frames.len());
    for (k, f) in frames.iter().enumerate() {
        let file = format!("frame-{k:04}.{extension}");
        std::fs::write(out.join(&file), &f.bytes).expect("a frame file");
        let r = f.camera_from_marker.rotation.to_rotation_matrix();
        let rows: Vec<[f64; 3]> = (0..3).map(|i| [r[(i, 0)], r[(i, 1)], r[(i, 2)]]).collect();
        let t = f.camera_from_marker.translation.vector;
        truth.push(serde_json::json!({"file": file, "r": rows, "t_mm": [t.x, t.y, t.z]}));
    }
    let doc = serde_json::json!({
        "camera": {
            "fx": camera.fx_px, "fy": camera.fy_px, "cx": camera.cx_px, "cy": camera.cy_px,
            "distortion": camera.distortion,
        },
        "points_mm": points_mm.iter().map(|p| [p.x, p.y, p.z]).collect::<Vec<_>>(),
        "frames": truth,
    });
    std::fs::write(
        out.join("truth.json"),
        serde_json::to_string_pretty(&doc).expect("JSON"),
    )
    .expect("truth.json");
    println!(
        "wrote {} frames and truth.json to {}",
        frames.len(),
        out.display()
    );
}
