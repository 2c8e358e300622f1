//! `POST /api/v1/frames` under a live load: the release binary in its own process on the
//! built-in installation, three cameras each posting an 8-bit frame every 40 ms (25 Hz) for
//! `SECONDS` (default 20) of wall time, stamped with the wall clock, as PNG (or as binary PGM with
//! `FORMAT=pgm`). Prints the server's CPU
//! (user + system time from `/proc`, in cores: 1.0 is one core busy), the answer latency, and
//! whether every marker was found and stored.
//!
//! The frames are rendered once before the run (25 groups of the ship scenario, cycled).
//!
//! Options (environment): `FORMAT=pgm`; `RERUN=save` (frames and everything else recorded to
//! a file, `[rerun] image_hz` 1); `PANEL=1` (a client doing what the dashboard's Cameras panel
//! does while open: every second `GET /cameras`, and for each camera with a new frame its PNG
//! and detections); `CAMERAS=16` (cameras beyond the built-in three are copies of C1, each
//! seeing its own copy of marker B through a measured link; the server's peak RSS is printed).
//!
//! Run: `cargo bench --bench frames_load` (Linux); e.g.
//! `FORMAT=pgm RERUN=save PANEL=1 cargo bench --bench frames_load`.

#[path = "support/load.rs"]
mod load;
#[path = "../tests/suite/common/process.rs"]
#[allow(
    dead_code,
    reason = "the bench lets Drop stop the server; the tests kill it"
)]
mod process;

use brokenray::clock::format_ns;
use brokenray::imagefile::{FrameFormat, encode};
use brokenray::sim::render::RenderSettings;
use brokenray::sim::{Scenario, SimSettings, Simulator};
use load::{cpu_s, post_frame, wall_ns};
use std::time::{Duration, Instant};

/// Camera `C<k>`: a copy of C1, seeing its own copy of marker B (`B<k>`) through a measured
/// link with C1_from_B's nominal pose.
fn extra_camera(k: usize) -> String {
    let default = brokenray::config::DEFAULT_INSTALLATION_TOML;
    let block = |start: &str| -> String {
        let from = default
            .find(start)
            .expect("a block of the built-in installation");
        let rest = &default[from..];
        let end = rest[2..].find("\n[").map_or(rest.len(), |e| e + 3);
        rest[..end].to_owned()
    };
    format!(
        "\n{}\n{}\n{}",
        block("[[cameras]]\nframe = \"C1\"").replace("\"C1\"", &format!("\"C{k}\"")),
        block("[[markers]]\nframe = \"B\"").replace("\"B\"", &format!("\"B{k}\"")),
        block("[[links]]\nname = \"C1_from_B\"")
            .replace("\"C1_from_B\"", &format!("\"C{k}_from_B{k}\"")),
    )
}

/// Peak resident set of a process so far (MB), from `/proc`.
fn peak_rss_mb(pid: u32) -> f64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap_or_default()
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(0.0, |kb| kb / 1024.0)
}

fn main() {
    if std::env::args().any(|a| a == "--test") || !std::env::args().any(|a| a == "--bench") {
        println!("frames load bench: run with `cargo bench --bench frames_load`");
        return;
    }
    let seconds: f64 = std::env::var("SECONDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(20.0);
    let format = match std::env::var("FORMAT").as_deref() {
        Ok("pgm") => FrameFormat::Pgm,
        Ok("png") | Err(_) => FrameFormat::Png,
        Ok(other) => panic!("FORMAT is png or pgm, not {other}"),
    };
    let cameras: usize = std::env::var("CAMERAS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3)
        .max(3);
    let rerun_save = std::env::var("RERUN").as_deref() == Ok("save");
    let panel = std::env::var("PANEL").as_deref() == Ok("1");
    let dir = tempfile::tempdir().expect("a temporary directory");
    let mut text = brokenray::config::DEFAULT_INSTALLATION_TOML
        .replace("listen = \"127.0.0.1:7878\"", "listen = \"127.0.0.1:0\"")
        .replace(
            "database = \"brokenray.db\"",
            &format!("database = \"{}\"", dir.path().join("load.db").display()),
        );
    if rerun_save {
        text = text.replace(
            "[rerun]\nmode = \"off\"\nrecordings_dir = \"recordings\"",
            &format!(
                "[rerun]\nmode = \"save\"\nrecordings_dir = \"{}\"",
                dir.path().join("recordings").display()
            ),
        );
        assert!(
            text.contains("mode = \"save\""),
            "the [rerun] section changed"
        );
    }
    for k in 4..=cameras {
        text.push_str(&extra_camera(k));
    }
    let config = dir.path().join("load.toml");
    std::fs::write(&config, &text).expect("the config file");
    brokenray::config::parse("load.toml", &text).expect("a valid installation");
    // Frames of the built-in three cameras; the extra cameras post C1's.
    let inst = brokenray::config::default_installation();

    let render_start = Instant::now();
    let mut sim = Simulator::new(
        &inst.model,
        SimSettings {
            scenario: Scenario::Ship,
            rate_hz: 25.0,
            start_ns: wall_ns(),
            duration_s: None,
            pixel_sigma_px: None,
            outlier_rate: 0.0,
            seed: 3,
        },
    )
    .expect("simulator");
    let settings = RenderSettings {
        samples_per_side: 16,
        ..RenderSettings::default()
    };
    let groups: Vec<Vec<(String, Vec<u8>)>> = (0..25)
        .map(|_| {
            let g = sim.next_group();
            sim.render_frames(&g, &settings)
                .into_iter()
                .map(|(camera, frame)| (camera, encode(&frame, format).expect("encodes")))
                .collect()
        })
        .collect();
    let kb = groups[0].iter().map(|(_, b)| b.len()).sum::<usize>() as f64 / 3.0 / 1024.0;
    println!(
        "rendered 25 groups of 3 frames in {:.1} s ({format:?} about {kb:.0} KiB a frame)",
        render_start.elapsed().as_secs_f64()
    );

    let server = process::start(
        &config,
        "warn,brokenray=info",
        false,
        Duration::from_secs(120),
    );
    let pid = server.child.id();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    let client = reqwest::Client::new();
    let (latencies, found, stored, errors, cpu, wall) = runtime.block_on(async {
        let mut tasks = Vec::new();
        let cpu0 = cpu_s(pid);
        let t0 = Instant::now();
        let end = t0 + Duration::from_secs_f64(seconds);
        let names: Vec<String> = (1..=cameras).map(|k| format!("C{k}")).collect();
        if panel {
            let client = client.clone();
            let base = server.base.clone();
            tasks.push(tokio::spawn(async move {
                // What the Cameras panel asks while open: the list every second, and each new
                // frame's PNG and detections.
                let mut shown: std::collections::HashMap<String, String> = Default::default();
                let mut tick = tokio::time::interval(Duration::from_secs(1));
                while Instant::now() < end {
                    tick.tick().await;
                    let Ok(list) = client.get(format!("{base}/api/v1/cameras")).send().await else {
                        continue;
                    };
                    let list: serde_json::Value = list.json().await.unwrap_or_default();
                    for c in list["cameras"].as_array().into_iter().flatten() {
                        let (Some(name), Some(time)) =
                            (c["name"].as_str(), c["frame"]["time"].as_str())
                        else {
                            continue;
                        };
                        if shown.get(name).map(String::as_str) == Some(time) {
                            continue;
                        }
                        shown.insert(name.to_owned(), time.to_owned());
                        for part in ["frame", "detections"] {
                            if let Ok(r) = client
                                .get(format!("{base}/api/v1/cameras/{name}/{part}"))
                                .send()
                                .await
                            {
                                let _ = r.bytes().await;
                            }
                        }
                    }
                }
                (Vec::new(), 0, 0, 0)
            }));
        }
        for (c, camera) in names.iter().enumerate() {
            let frames: Vec<Vec<u8>> = groups
                .iter()
                .map(|g| g[if c < 3 { c } else { 0 }].1.clone())
                .collect();
            let client = client.clone();
            let base = server.base.clone();
            let camera = camera.to_string();
            tasks.push(tokio::spawn(async move {
                let mut latencies = Vec::new();
                let (mut found, mut stored, mut errors) = (0u64, 0u64, 0u64);
                let mut k = 0usize;
                let mut tick = tokio::time::interval(Duration::from_millis(40));
                tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Burst);
                while Instant::now() < end {
                    tick.tick().await;
                    let time = format_ns(wall_ns());
                    let sent = Instant::now();
                    let body = frames[k % frames.len()].clone();
                    k += 1;
                    match post_frame(&client, &base, &camera, &time, format, body).await {
                        Ok(body) => {
                            latencies.push(sent.elapsed().as_secs_f64() * 1e3);
                            if body["markers"][0]["found"] == true {
                                found += 1;
                            }
                            stored += body["ingest"]["stored"].as_u64().unwrap_or(0);
                        }
                        Err(e) => {
                            errors += 1;
                            eprintln!("{camera}: {e}");
                        }
                    }
                }
                (latencies, found, stored, errors)
            }));
        }
        let mut all = Vec::new();
        let (mut found, mut stored, mut errors) = (0, 0, 0);
        for t in tasks {
            let (l, f, s, e) = t.await.expect("a camera task");
            all.extend(l);
            found += f;
            stored += s;
            errors += e;
        }
        let wall = t0.elapsed().as_secs_f64();
        (all, found, stored, errors, cpu_s(pid) - cpu0, wall)
    });
    let mut sorted = latencies.clone();
    sorted.sort_by(f64::total_cmp);
    let pct = |p: f64| sorted[((sorted.len() as f64 - 1.0) * p).round() as usize];
    println!(
        "{} frames in {wall:.1} s ({:.1} frames/s from {cameras} cameras{}{}): {found} markers found, {stored} samples stored, {errors} errors",
        latencies.len(),
        latencies.len() as f64 / wall,
        if rerun_save { ", Rerun save on" } else { "" },
        if panel {
            ", the Cameras panel open"
        } else {
            ""
        },
    );
    println!("server peak RSS: {:.0} MB", peak_rss_mb(pid));
    println!(
        "server CPU: {cpu:.2} s over {wall:.1} s = {:.2} cores; answer latency p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms",
        cpu / wall,
        pct(0.5),
        pct(0.99),
        pct(1.0)
    );
}
