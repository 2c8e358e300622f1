//! Rerun: what a recording of a run holds (read back with the SDK's own decoder), that an absent
//! viewer never holds up ingest, and that `replay` rebuilds a stored period.

use super::helpers::{T0_NS, TestApp, installation, pose_json};
use axum::http::StatusCode;
use brokenray::bank::ResultSource;
use brokenray::geometry::{Pose, Vec3, se3_exp};
use brokenray::model::TargetId;
use rerun::external::re_log_encoding::DecoderApp;
use rerun::log::{Chunk, LogMsg};
use serde_json::{Value, json};
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// The built-in installation with its `[rerun]` section replaced.
pub(super) fn with_rerun(section: &str) -> String {
    brokenray::config::DEFAULT_INSTALLATION_TOML.replace(
        "[rerun]\nmode = \"off\"\nrecordings_dir = \"recordings\"\nurl = \"rerun+http://127.0.0.1:9876/proxy\"\n",
        &format!("[rerun]\n{section}\n"),
    )
}

/// A group of the three measured links at `k * 40 ms`; G turns slowly about its x axis
/// (0.5 arc-seconds a step), so the deformation changes from result to result.
fn turning_group(k: i64) -> Value {
    let nominal = |t: [f64; 3]| Pose::from_parts(Vec3::from(t).into(), Default::default());
    let turn = se3_exp(&brokenray::geometry::Twist::new(
        0.0,
        0.0,
        0.0,
        (0.5 * k as f64).to_radians() / 3600.0,
        0.0,
        0.0,
    ));
    let poses = [
        ("C1_from_B", nominal([0.0, 0.0, 3000.0])),
        ("C2_from_M", nominal([0.0, 0.0, 3000.0])),
        ("C3_from_G", nominal([0.0, 0.0, 3000.0]) * turn),
    ];
    let samples: Vec<Value> = poses
        .iter()
        .map(|(l, p)| json!({"link": l, "time": T0_NS + k * 40_000_000, "pose": pose_json(p)}))
        .collect();
    json!({ "samples": samples })
}

/// What a recording holds: every entity path, and per entity the rows of f64 scalars and the
/// number of transform rows, each with its measurement time.
#[derive(Debug, Default)]
struct Recording {
    entities: BTreeSet<String>,
    /// Per entity, its rows on the measurement timeline.
    rows: BTreeMap<String, usize>,
    /// Per entity, the 2-D positions logged (all rows).
    points2d: BTreeMap<String, Vec<[f32; 2]>>,
    scalars: BTreeMap<String, Vec<(i64, Vec<f64>)>>,
    transforms: BTreeMap<String, usize>,
}

fn read_recording(path: &Path) -> Recording {
    let file = std::fs::File::open(path).expect("the recording exists");
    let decoder =
        DecoderApp::decode_eager(std::io::BufReader::new(file)).expect("an .rrd recording");
    let timeline: rerun::TimelineName = brokenray::viz::TIMELINE.into();
    let mut out = Recording::default();
    for msg in decoder {
        let LogMsg::ArrowMsg(store_id, arrow) = msg.expect("a readable message") else {
            continue;
        };
        if store_id.kind() != rerun::StoreKind::Recording {
            continue;
        }
        let chunk = Chunk::from_arrow_msg(&arrow).expect("a chunk");
        let entity = chunk.entity_path().to_string();
        out.entities.insert(entity.clone());
        if chunk.is_static() {
            continue;
        }
        let times: Vec<i64> = chunk
            .timelines()
            .get(&timeline)
            .map(|c| c.times_raw().to_vec())
            .unwrap_or_default();
        *out.rows.entry(entity.clone()).or_default() += times.len();
        out.points2d.entry(entity.clone()).or_default().extend(
            chunk
                .iter_slices::<[f32; 2]>(rerun::Points2D::descriptor_positions().component)
                .flat_map(|s| s.to_vec()),
        );
        let scalars: Vec<Vec<f64>> = chunk
            .iter_slices::<f64>(rerun::Scalars::descriptor_scalars().component)
            .map(|s| s.to_vec())
            .collect();
        if !scalars.is_empty() {
            assert_eq!(
                times.len(),
                scalars.len(),
                "{entity}: every row has its time"
            );
            out.scalars
                .entry(entity.clone())
                .or_default()
                .extend(times.iter().copied().zip(scalars));
        }
        let translations = chunk
            .iter_slices::<[f32; 3]>(rerun::Transform3D::descriptor_translation().component)
            .count();
        *out.transforms.entry(entity).or_default() += translations;
    }
    for rows in out.scalars.values_mut() {
        rows.sort_by_key(|(t, _)| *t);
    }
    out
}

/// The built-in installation on `app`'s database, plus `extra`, as `site.toml` in its
/// directory: what `replay` runs on.
fn site_config(app: &TestApp, extra: &str) -> std::path::PathBuf {
    let config = app.dir.path().join("site.toml");
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML.replace(
        "database = \"brokenray.db\"",
        &format!(
            "database = \"{}\"",
            app.dir.path().join("brokenray.db").display()
        ),
    );
    std::fs::write(&config, format!("{text}\n{extra}")).unwrap();
    config
}

/// The only `.rrd` file of a directory.
fn only_recording(dir: &Path) -> std::path::PathBuf {
    let files: Vec<_> = std::fs::read_dir(dir)
        .expect("the recordings directory")
        .map(|e| e.expect("entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "rrd"))
        .collect();
    assert_eq!(files.len(), 1, "{files:?}");
    files[0].clone()
}

/// Stops the service (the logger closes its file) and starts it again without Rerun on the
/// same database.
async fn stop_and_restart(app: TestApp) -> TestApp {
    app.restart(None).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_recorded_run_holds_the_frames_and_the_values_the_api_serves() {
    let dir = tempfile::tempdir().unwrap();
    let recordings = dir.path().join("recordings");
    let text = with_rerun(&format!(
        "mode = \"save\"\nrecordings_dir = \"{}\"\nseries_hz = 1000.0\nscene_hz = 5.0",
        recordings.display()
    ));
    let inst = installation(&dir, Some(&text));
    let app = TestApp::start_with(dir, inst).await;
    for k in 0..10 {
        let (s, body) = app.post_json("/api/v1/samples", &turning_group(k)).await;
        assert_eq!(s, StatusCode::OK, "{body}");
    }
    let window = json!({"from": T0_NS, "to": T0_NS + 9 * 40_000_000});
    let (s, body) = app.post_json("/api/v1/targets/G/reference", &window).await;
    assert_eq!(s, StatusCode::CREATED, "{body}");
    for k in 10..120 {
        let (s, body) = app.post_json("/api/v1/samples", &turning_group(k)).await;
        assert_eq!(s, StatusCode::OK, "{body}");
    }
    let app = stop_and_restart(app).await;
    let rec = read_recording(&only_recording(&recordings));

    for entity in [
        "/world/B",
        "/world/B/C1",
        "/world/B/C1/camera",
        "/world/B/C1/C2/M/points",
        "/world/B/C1/C2/M/C3/G",
        "/world/B/G_filtered",
        "/world/B/G_raw",
        "/world/B/G_reference",
        "/plots/G/rotation_arcsec/filtered",
        "/plots/G/rotation_arcsec/raw",
        "/plots/G/rotation_arcsec/plus_3sigma",
        "/plots/G/translation_mm/filtered",
        "/plots/links/C3_from_G/nis",
        "/plots/links/C3_from_G/gate",
        "/alarms/G",
    ] {
        assert!(
            rec.entities.contains(entity),
            "no {entity} in {:?}",
            rec.entities
        );
    }
    // The measured links place their frames over time.
    assert!(rec.transforms["/world/B/C1/C2/M/C3/G"] >= 2);

    let rotation = &rec.scalars["/plots/G/rotation_arcsec/filtered"];
    let translation = &rec.scalars["/plots/G/translation_mm/filtered"];
    assert!(rotation.len() >= 100, "{} filtered points", rotation.len());
    assert_eq!(rotation.len(), translation.len());
    let mut largest = 0.0f64;
    for ((t, rot), (t2, trans)) in rotation.iter().zip(translation) {
        assert_eq!(t, t2);
        let (s, c) = app
            .get(&format!("/api/v1/targets/G/compensation?at={t}"))
            .await;
        assert_eq!(s, StatusCode::OK, "{c}");
        for i in 0..3 {
            let api_rot = c["deformation"]["rotation_arcsec"][i].as_f64().unwrap();
            let api_trans = c["deformation"]["translation_mm"][i].as_f64().unwrap();
            assert!(
                (rot[i] - api_rot).abs() < 1e-9,
                "t={t} rotation[{i}]: {} vs {api_rot}",
                rot[i]
            );
            assert!(
                (trans[i] - api_trans).abs() < 1e-9,
                "t={t} translation[{i}]: {} vs {api_trans}",
                trans[i]
            );
        }
        largest = largest.max(rot[0].abs());
    }
    // The turn shows: tens of arc-seconds by the end, not a constant.
    assert!(largest > 20.0, "largest x rotation {largest} arcsec");
    // The 3-sigma band surrounds the filtered value.
    let plus = &rec.scalars["/plots/G/rotation_arcsec/plus_3sigma"];
    assert_eq!(plus.len(), rotation.len());
    for ((_, p), (_, v)) in plus.iter().zip(rotation) {
        assert!((0..3).all(|i| p[i] > v[i]));
    }
    // The filtered G_from_B's sigma and its two parts, as the API answers them.
    for (quantity, key) in [
        ("sigma_rotation_arcsec", "rotation_arcsec"),
        ("sigma_translation_mm", "translation_mm"),
    ] {
        for (part, field) in [
            ("whole", "sigma"),
            ("random", "sigma_random"),
            ("systematic", "sigma_systematic"),
        ] {
            let series = &rec.scalars[&format!("/plots/G/{quantity}/{part}")];
            // Every filtered result, those before the reference too.
            assert!(series.len() >= rotation.len(), "{quantity}/{part}");
            for (t, v) in series.iter().step_by(25) {
                let (_, c) = app
                    .get(&format!("/api/v1/targets/G/compensation?at={t}"))
                    .await;
                for i in 0..3 {
                    let api = c[field][key][i].as_f64().unwrap();
                    assert!(
                        (v[i] - api).abs() <= 1e-9 * api.abs().max(1.0),
                        "t={t} {quantity}/{part}[{i}]: {} vs {api}",
                        v[i]
                    );
                }
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_absent_viewer_never_holds_up_ingest() {
    let dir = tempfile::tempdir().unwrap();
    // Nothing listens on port 1; a one-record queue fills at once.
    let text = with_rerun(
        "mode = \"connect\"\nurl = \"rerun+http://127.0.0.1:1/proxy\"\nqueue_capacity = 1\nseries_hz = 1000000.0\nscene_hz = 1000000.0",
    );
    let inst = installation(&dir, Some(&text));
    let app = TestApp::start_with(dir, inst).await;
    for batch in 0..20 {
        let samples: Vec<Value> = (0..50)
            .flat_map(|j| {
                turning_group(batch * 50 + j)["samples"]
                    .as_array()
                    .unwrap()
                    .clone()
            })
            .collect();
        let (s, body) = app
            .post_live("/api/v1/samples", &json!({ "samples": samples }))
            .await;
        assert_eq!(s, StatusCode::OK, "batch {batch}: {body}");
        assert_eq!(body["stored"], 150);
    }
    let (_, metrics) = app.get("/metrics").await;
    let text = metrics.as_str().expect("Prometheus text");
    let value = |name: &str| -> f64 {
        text.lines()
            .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
            .unwrap_or_else(|| panic!("no {name}"))
    };
    assert!(value("brokenray_rerun_dropped_total") > 0.0);
    assert!(value("brokenray_rerun_queued_total") > 0.0);
    assert_eq!(value("brokenray_samples_stored_total"), 3000.0);
    // The service still stops (the viewer gets a bounded time).
    let _ = stop_and_restart(app).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_writes_one_filtered_point_per_stored_result() {
    let app = TestApp::start(None).await;
    for k in 0..5 {
        let (s, _) = app.post_json("/api/v1/samples", &turning_group(k)).await;
        assert_eq!(s, StatusCode::OK);
    }
    let window = json!({"from": T0_NS, "to": T0_NS + 4 * 40_000_000});
    let (s, _) = app.post_json("/api/v1/targets/G/reference", &window).await;
    assert_eq!(s, StatusCode::CREATED);
    for k in 5..80 {
        let (s, _) = app.post_json("/api/v1/samples", &turning_group(k)).await;
        assert_eq!(s, StatusCode::OK);
    }
    // The period: from step 20 to step 60, both included.
    let (from_ns, to_ns) = (T0_NS + 20 * 40_000_000, T0_NS + 60 * 40_000_000);
    let stored = app
        .service
        .store()
        .results(
            TargetId(0),
            ResultSource::Filtered,
            from_ns,
            to_ns,
            i64::MAX,
        )
        .await
        .unwrap();
    assert!(stored.len() >= 40, "{} stored results", stored.len());
    let config = site_config(&app, "");
    let out = app.dir.path().join("review.rrd");
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_brokenray"))
        .args(["replay", "--config", config.to_str().unwrap()])
        .args(["--from", &from_ns.to_string(), "--to", &to_ns.to_string()])
        .args(["--target", "G", "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let report = String::from_utf8_lossy(&run.stdout);
    assert!(
        report.contains(&format!("{} filtered", stored.len())),
        "{report}"
    );
    let rec = read_recording(&out);
    let points = &rec.scalars["/plots/G/rotation_arcsec/filtered"];
    assert_eq!(points.len(), stored.len());
    for (p, r) in points.iter().zip(&stored) {
        assert_eq!(p.0, r.time_ns);
        let (_, rotation, _) = r.deformation.expect("a reference was in force");
        for (got, stored) in p.1.iter().zip(rotation) {
            assert!((got - stored).abs() < 1e-9, "{got} vs {stored}");
        }
    }
    assert_eq!(rec.transforms["/world/B/G_filtered"], stored.len());
    // A second replay to the same file is refused.
    let again = std::process::Command::new(env!("CARGO_BIN_EXE_brokenray"))
        .args(["replay", "--config", config.to_str().unwrap()])
        .args(["--from", &from_ns.to_string(), "--to", &to_ns.to_string()])
        .args(["--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("already exists"));
}

/// Camera frames go to Rerun at `image_hz` per camera (measurement time), under the camera's
/// pinhole, with the detected points at pixel centres and a log line for a marker not found.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frames_are_recorded_under_their_cameras_at_image_hz() {
    use brokenray::imagefile::{FrameFormat, encode};
    let dir = tempfile::tempdir().unwrap();
    let recordings = dir.path().join("recordings");
    let text = with_rerun(&format!(
        "mode = \"save\"\nrecordings_dir = \"{}\"\nimage_hz = 2.0",
        recordings.display()
    ));
    let inst = installation(&dir, Some(&text));
    let app = TestApp::start_with(dir, inst).await;
    let (group, frames) = super::frames::rendered(brokenray::vision::BitDepth::Eight);
    let png = encode(&frames[0].1, FrameFormat::Png).unwrap();
    // One second of C1 at 25 Hz, starting on a whole second: two frames are due at 2 Hz.
    let start = group.time_ns - group.time_ns.rem_euclid(1_000_000_000) + 1_000_000_000;
    app.clock.set_ns(start + 2_000_000_000);
    let mut answer = Value::Null;
    for k in 0..25 {
        let (status, body) = super::frames::post_frame(
            &app,
            "C1",
            &brokenray::clock::format_ns(start + k * 40_000_000),
            "image/png",
            png.clone(),
        )
        .await;
        assert_eq!(status, StatusCode::OK, "{body}");
        if k == 0 {
            answer = body;
        }
    }
    // C3 sees nothing: its marker is not found, and the reason is logged.
    let empty = brokenray::vision::GreyImage::from_u8(
        frames[2].1.width_px(),
        frames[2].1.height_px(),
        &vec![40; (frames[2].1.width_px() * frames[2].1.height_px()) as usize],
    )
    .unwrap();
    let (status, _) = super::frames::post_frame(
        &app,
        "C3",
        &brokenray::clock::format_ns(start),
        "image/png",
        encode(&empty, FrameFormat::Png).unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::OK);
    let _app = stop_and_restart(app).await;
    let rec = read_recording(&only_recording(&recordings));
    let image = "/world/B/C1/camera/image";
    assert_eq!(rec.rows.get(image), Some(&2), "{:?}", rec.rows);
    // The first frame's points, at their pixel centres (+0.5 in Rerun's image coordinates).
    let detected = &rec.points2d["/world/B/C1/camera/image/detected"];
    let points = answer["markers"][0]["points_px"].as_array().unwrap();
    assert_eq!(detected.len(), 2 * points.len());
    for (d, p) in detected.iter().zip(points) {
        let (u, v) = (p[0].as_f64().unwrap(), p[1].as_f64().unwrap());
        assert!(
            (f64::from(d[0]) - (u + 0.5)).abs() < 1e-3
                && (f64::from(d[1]) - (v + 0.5)).abs() < 1e-3
        );
    }
    assert!(
        rec.entities
            .contains("/world/B/C1/camera/image/reprojected")
    );
    assert_eq!(rec.rows.get("/cameras/C3"), Some(&1), "{:?}", rec.rows);
    assert!(rec.entities.contains("/world/B/C1/C2/M/C3/camera/image"));
}

/// `replay` puts the archived frames of the period under their cameras, and says why the
/// evidence frames were kept.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_includes_the_archived_frames_of_the_period() {
    use brokenray::archive::{ArchiveReason, FrameArchive};
    use brokenray::config::FrameSettings;
    let app = TestApp::start(None).await;
    let archive_dir = app.dir.path().join("frames");
    let settings = FrameSettings {
        archive_dir: Some(archive_dir.clone()),
        archive_every_s: 1.0,
        archive_max_mb: 100.0,
    };
    let archive = FrameArchive::open(&settings).unwrap().unwrap();
    let (group, frames) = super::frames::rendered(brokenray::vision::BitDepth::Eight);
    let image = std::sync::Arc::new(frames[0].1.clone());
    let second = 1_000_000_000;
    for (k, evidence) in [
        (0, None),
        (1, Some(ArchiveReason::NotFound)),
        (2, None),
        (5, None),
    ] {
        archive
            .offer("C1", group.time_ns + k * second, &image, evidence)
            .unwrap();
    }
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
    while archive
        .counters()
        .written
        .load(std::sync::atomic::Ordering::Relaxed)
        < 4
    {
        assert!(std::time::Instant::now() < deadline, "the archive's writer");
        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
    }
    drop(archive);
    let config = site_config(
        &app,
        &format!("[frames]\narchive_dir = \"{}\"\n", archive_dir.display()),
    );
    // The period holds the first three frames, not the one at 5 s.
    let out = app.dir.path().join("frames.rrd");
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_brokenray"))
        .args(["replay", "--config", config.to_str().unwrap()])
        .args(["--from", &group.time_ns.to_string()])
        .args(["--to", &(group.time_ns + 3 * second).to_string()])
        .args(["--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let report = String::from_utf8_lossy(&run.stdout);
    assert!(report.contains("3 archived frames"), "{report}");
    let rec = read_recording(&out);
    assert_eq!(
        rec.rows.get("/world/B/C1/camera/image"),
        Some(&3),
        "{:?}",
        rec.rows
    );
    assert_eq!(
        rec.rows.get("/cameras/C1"),
        Some(&1),
        "the evidence frame's line"
    );
}
