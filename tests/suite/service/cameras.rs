//! What the cameras see, through the router: the newest frame of each camera kept with the
//! answer `/frames` gave, served as lossless PNG and as detections, newest by measurement time.

use super::frames::{post_frame, rendered};
use super::helpers::TestApp;
use axum::http::StatusCode;
use brokenray::clock::format_ns;
use brokenray::imagefile::{FrameFormat, decode, encode};
use brokenray::vision::BitDepth;

#[tokio::test]
async fn before_any_frame_cameras_are_listed_and_their_frames_are_404() {
    let app = TestApp::start(None).await;
    let (status, body) = app.get("/api/v1/cameras").await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let cameras = body["cameras"].as_array().expect("cameras");
    let names: Vec<&str> = cameras.iter().filter_map(|c| c["name"].as_str()).collect();
    assert_eq!(names, ["C1", "C2", "C3"]);
    assert_eq!(cameras[0]["width_px"], 1280);
    assert_eq!(cameras[0]["markers"], serde_json::json!(["B"]));
    assert!(cameras.iter().all(|c| c.get("frame").is_none()), "{body}");

    for path in ["frame", "detections"] {
        let (status, body) = app.get(&format!("/api/v1/cameras/C1/{path}")).await;
        assert_eq!(status, StatusCode::NOT_FOUND);
        assert!(
            body["error"]["message"]
                .as_str()
                .is_some_and(|m| m.contains("no frame yet")),
            "{body}"
        );
        let (status, body) = app.get(&format!("/api/v1/cameras/C9/{path}")).await;
        assert_eq!(status, StatusCode::NOT_FOUND);
        assert!(
            body["error"]["message"]
                .as_str()
                .is_some_and(|m| m.contains("no camera `C9`")),
            "{body}"
        );
    }
}

#[tokio::test]
async fn the_newest_frame_is_served_losslessly_with_its_detections_and_a_late_one_does_not_hide_it()
{
    let app = TestApp::start(None).await;
    let (group, frames) = rendered(BitDepth::Eight);
    let (_, frames16) = rendered(BitDepth::Sixteen);
    let time = format_ns(group.time_ns);
    let (status, answer) = post_frame(
        &app,
        "C1",
        &time,
        "image/png",
        encode(&frames[0].1, FrameFormat::Png).expect("png"),
    )
    .await;
    assert_eq!(status, StatusCode::OK, "{answer}");
    // C2 as 16-bit PGM: served as 16-bit PNG.
    let (status, _) = post_frame(
        &app,
        "C2",
        &time,
        "image/x-portable-graymap",
        encode(&frames16[1].1, FrameFormat::Pgm).expect("pgm"),
    )
    .await;
    assert_eq!(status, StatusCode::OK);

    // The list: each camera's newest frame, its age on the server's clock, what was found.
    let (_, list) = app.get("/api/v1/cameras").await;
    let c1 = &list["cameras"][0];
    assert_eq!(c1["frame"]["time"], time.as_str(), "{list}");
    assert_eq!(c1["frame"]["markers"][0]["link"], "C1_from_B");
    assert_eq!(c1["frame"]["markers"][0]["found"], true);
    let age = c1["frame"]["age_s"].as_f64().expect("age");
    let expected = (app.service.now_ns() - group.time_ns) as f64 / 1e9;
    assert!((age - expected).abs() < 1e-6, "{age} against {expected}");
    assert!(list["cameras"][2].get("frame").is_none(), "C3 sent nothing");

    // The detections are the answer /frames gave, with the reprojected points beside the
    // measured ones (residuals of hundredths of a pixel).
    let (status, detections) = app.get("/api/v1/cameras/C1/detections").await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(detections, answer);
    let m = &detections["markers"][0];
    let points = m["points_px"].as_array().expect("points");
    let reprojected = m["reprojected_px"].as_array().expect("reprojected");
    assert_eq!(points.len(), reprojected.len());
    for (p, r) in points.iter().zip(reprojected) {
        let d = (p[0].as_f64().expect("u") - r[0].as_f64().expect("u"))
            .hypot(p[1].as_f64().expect("v") - r[1].as_f64().expect("v"));
        assert!(d < 0.05, "residual {d} px");
    }

    // The frame: lossless PNG of what was posted, 8 bit as 8, 16 as 16.
    for (camera, posted) in [("C1", &frames[0].1), ("C2", &frames16[1].1)] {
        let uri = format!("/api/v1/cameras/{camera}/frame");
        let (status, headers, bytes) = app.request_raw("GET", &uri, &[], "").await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(headers["content-type"], "image/png");
        assert_eq!(headers["x-frame-time"], time.as_str());
        let image = decode(&bytes, FrameFormat::Png, None).expect("a PNG");
        assert_eq!(&image, posted, "{camera}: the frame as posted");
        // Asked again with its tag: not modified, no body.
        let etag = headers["etag"].to_str().expect("etag").to_owned();
        let (status, _, bytes) = app
            .request_raw("GET", &uri, &[("if-none-match", &etag)], "")
            .await;
        assert_eq!(status, StatusCode::NOT_MODIFIED);
        assert!(bytes.is_empty());
    }

    // A frame 40 ms older arrives late: the newer one stays.
    let (status, _) = post_frame(
        &app,
        "C1",
        &format_ns(group.time_ns - 40_000_000),
        "image/png",
        encode(&frames[0].1, FrameFormat::Png).expect("png"),
    )
    .await;
    assert_eq!(status, StatusCode::OK);
    let (_, headers, _) = app
        .request_raw("GET", "/api/v1/cameras/C1/frame", &[], "")
        .await;
    assert_eq!(headers["x-frame-time"], time.as_str());
}

#[tokio::test]
async fn frames_with_a_marker_not_found_are_archived_as_evidence_and_listed() {
    let archive_dir = tempfile::tempdir().expect("temp dir");
    let text = format!(
        "{}\n[frames]\narchive_dir = \"{}\"\narchive_every_s = 60\n",
        brokenray::config::DEFAULT_INSTALLATION_TOML,
        archive_dir.path().display()
    );
    let app = TestApp::start(Some(&text)).await;
    let (group, frames) = rendered(BitDepth::Eight);
    let frame = &frames[0].1;
    let empty = brokenray::vision::GreyImage::from_u8(
        frame.width_px(),
        frame.height_px(),
        &vec![40; (frame.width_px() * frame.height_px()) as usize],
    )
    .expect("frame");
    let ms = 1_000_000;
    // The first frame is the period's; the second (within it) is not kept; the third shows no
    // marker: evidence.
    for (dt, image) in [(0, frame), (40 * ms, frame), (80 * ms, &empty)] {
        let (status, body) = post_frame(
            &app,
            "C1",
            &format_ns(group.time_ns + dt),
            "image/png",
            encode(image, FrameFormat::Png).expect("png"),
        )
        .await;
        assert_eq!(status, StatusCode::OK, "{body}");
    }
    // The writer runs beside the requests: wait for it.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
    let listed = loop {
        let (status, body) = app.get("/api/v1/cameras/C1/frames").await;
        assert_eq!(status, StatusCode::OK, "{body}");
        if body["frames"].as_array().is_some_and(|f| f.len() == 2) {
            break body;
        }
        assert!(std::time::Instant::now() < deadline, "{body}");
        tokio::time::sleep(std::time::Duration::from_millis(10)).await;
    };
    let frames_listed = listed["frames"].as_array().expect("frames");
    assert_eq!(frames_listed[0]["reason"], "periodic");
    assert_eq!(frames_listed[0]["time"], format_ns(group.time_ns).as_str());
    assert_eq!(frames_listed[1]["reason"], "not_found");
    assert_eq!(listed["truncated"], false);
    let file = frames_listed[1]["file"].as_str().expect("file");
    assert!(
        file.starts_with("C1/") && file.ends_with("_not_found.png"),
        "{file}"
    );
    assert!(archive_dir.path().join(file).exists());
    for (listed, posted) in frames_listed.iter().zip([frame, &empty]) {
        let url = listed["url"].as_str().expect("url");
        let (status, headers, bytes) = app.request_raw("GET", url, &[], "").await;
        assert_eq!(status, StatusCode::OK, "{url}");
        assert_eq!(headers["content-type"], "image/png");
        assert_eq!(
            &decode(&bytes, FrameFormat::Png, None).expect("png"),
            posted
        );
    }
    // A period, a limit, refusals.
    let from = format_ns(group.time_ns + 1);
    let (_, later) = app
        .get(&format!("/api/v1/cameras/C1/frames?from={from}"))
        .await;
    assert_eq!(later["frames"].as_array().map(Vec::len), Some(1), "{later}");
    let (_, one) = app.get("/api/v1/cameras/C1/frames?limit=1").await;
    assert_eq!(one["truncated"], true, "{one}");
    let (status, body) = app.get("/api/v1/cameras/C1/frames?from=yesterday").await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    assert_eq!(body["error"]["details"][0]["field"], "from", "{body}");
    let (status, _) = app.get("/api/v1/cameras/C9/frames").await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    let (status, _) = app
        .get(&format!(
            "/api/v1/cameras/C1/frames/{}",
            group.time_ns + 40 * ms
        ))
        .await;
    assert_eq!(status, StatusCode::NOT_FOUND, "the unkept frame");
    let (_, metrics_headers, metrics) = app.request_raw("GET", "/metrics", &[], "").await;
    assert!(
        metrics_headers["content-type"]
            .to_str()
            .is_ok_and(|t| t.starts_with("text/plain"))
    );
    let metrics = String::from_utf8_lossy(&metrics);
    assert!(
        metrics.contains("brokenray_frames_archived_total 2"),
        "{metrics}"
    );
    // A frame gone from the disk: 404, saying which, without the server's paths.
    std::fs::remove_file(archive_dir.path().join(file)).expect("removed");
    let url = frames_listed[1]["url"].as_str().expect("url");
    let (status, body) = app.get(url).await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{body}");
    let message = body["error"]["message"].as_str().expect("message");
    assert!(message.contains("_not_found.png"), "{message}");
    assert!(
        !message.contains(&archive_dir.path().display().to_string()),
        "{message}"
    );
}

#[tokio::test]
async fn without_an_archive_the_listing_says_so() {
    let app = TestApp::start(None).await;
    let (status, body) = app.get("/api/v1/cameras/C1/frames").await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    assert!(
        body["error"]["message"]
            .as_str()
            .is_some_and(|m| m.contains("archive_dir")),
        "{body}"
    );
}

/// A camera source's state as `GET /api/v1/cameras` and `/metrics` give it: what its thread
/// recorded (frames taken, the newest winning over a waiting one, a refusal, the last error) is
/// what a reader sees. No camera is opened: the test app sets the state.
#[tokio::test]
async fn a_camera_source_s_state_is_in_cameras_and_metrics() {
    use brokenray::acquire::{AcquiredFrame, SourceStatus};
    use brokenray::vision::GreyImage;
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML.replacen(
        "[[cameras]]\nframe = \"C3\"",
        "[[cameras]]\nframe = \"C3\"\nsource = { address = \"10.0.0.4\", trigger = \"software\", rate_hz = 5, timestamp = \"ptp\" }",
        1,
    );
    let app = TestApp::start(Some(&text)).await;
    let (_, body) = app.get("/api/v1/cameras").await;
    let source = &body["cameras"][2]["source"];
    assert_eq!(source["address"], "10.0.0.4", "{body}");
    assert_eq!(source["status"], "connecting");
    assert_eq!(source["connected"], false);
    assert_eq!(
        (source["trigger"].as_str(), source["timestamp"].as_str()),
        (Some("software"), Some("ptp"))
    );
    assert!(
        body["cameras"][0].get("source").is_none(),
        "C1 has no source: {body}"
    );

    let state = &app.sources[0];
    let frame = |t| AcquiredFrame {
        time_ns: t,
        image: GreyImage::from_u8(2, 1, &[0, 1]).expect("a frame"),
        arrival_ns: t,
    };
    state
        .counters
        .received
        .fetch_add(3, std::sync::atomic::Ordering::Relaxed);
    // Six frames into a queue of four: the two oldest dropped.
    for t in 1..=6 {
        state.offer(frame(t));
    }
    assert_eq!(state.take().map(|f| f.time_ns), Some(3));
    state.ingested(0.012);
    state.update(|d| {
        d.status = SourceStatus::Streaming;
        d.ptp_status = Some("Slave".into());
    });
    state.failed(
        "conflict: a sample differs".into(),
        1_800_000_000_000_000_000,
    );
    let (_, body) = app.get("/api/v1/cameras").await;
    let source = &body["cameras"][2]["source"];
    assert_eq!(source["status"], "streaming", "{body}");
    assert_eq!(source["connected"], true);
    assert_eq!(source["ptp_status"], "Slave");
    assert_eq!(
        [
            &source["frames_received"],
            &source["frames_ingested"],
            &source["frames_dropped"],
            &source["frames_failed"]
        ],
        [3, 1, 2, 1]
    );
    assert_eq!(source["delay_median_ms"], 12.0);
    assert_eq!(source["last_error"], "conflict: a sample differs");
    assert_eq!(
        source["last_error_at"],
        format_ns(1_800_000_000_000_000_000)
    );
    let (_, metrics) = app.get("/metrics").await;
    let metrics = metrics.as_str().expect("text").to_owned();
    for line in [
        "brokenray_camera_connected{camera=\"C3\"} 1",
        "brokenray_camera_frames_received_total{camera=\"C3\"} 3",
        "brokenray_camera_frames_dropped_total{camera=\"C3\"} 2",
        "brokenray_camera_frames_failed_total{camera=\"C3\"} 1",
        "brokenray_camera_delay_p99_seconds{camera=\"C3\"} 0.012",
    ] {
        assert!(metrics.contains(line), "{line} not in\n{metrics}");
    }
}

/// A calibration report as `calibrate-camera --report` writes it, of eight projected views of
/// the laboratory's camera, at `path`.
pub(crate) fn write_calibration_report(path: &std::path::Path) {
    use crate::camera_calibration::{lab_camera, plate, projected_views};
    use brokenray::report::calibration::{CalibrationReport, calibration_report};
    let camera = lab_camera();
    let plate = plate();
    let poses = brokenray::sim::plate::plate_poses(&camera, &plate, 8, 2);
    let views = projected_views(&camera, &plate, &poses, 0.02, 2);
    let calibration = brokenray::vision::calibrate_camera(
        &plate,
        camera.width_px,
        camera.height_px,
        &views,
        &brokenray::vision::CalibrationOptions::default(),
    )
    .expect("calibrated");
    let names: Vec<String> = (0..views.len()).map(|k| format!("view{k}.png")).collect();
    let page = calibration_report(&CalibrationReport {
        title: "C1",
        calibration: &calibration,
        plate: &plate,
        view_names: &names,
        notes: &[],
        made: "2026-11-27T12:00:00Z",
    });
    std::fs::write(path, page).expect("report written");
}

/// A camera's calibration report as the installation names it: linked from `GET /cameras`,
/// served as it was written under a policy that runs nothing; a page that is not there is a
/// warning when the installation is read and a 503 naming the camera (not the server's path)
/// when asked for; a camera with none, or no camera, is a 404 saying which.
#[tokio::test]
async fn a_camera_s_calibration_report_is_linked_and_served_and_a_missing_one_says_so() {
    let dir = tempfile::tempdir().expect("temp dir");
    let report = dir.path().join("c1.html");
    write_calibration_report(&report);
    let gone = dir.path().join("c2-gone.html");
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML
        .replacen(
            "[[cameras]]\nframe = \"C1\"",
            &format!(
                "[[cameras]]\nframe = \"C1\"\ncalibration_report = {:?}",
                report.display().to_string()
            ),
            1,
        )
        .replacen(
            "[[cameras]]\nframe = \"C2\"",
            &format!(
                "[[cameras]]\nframe = \"C2\"\ncalibration_report = {:?}",
                gone.display().to_string()
            ),
            1,
        );
    let app = TestApp::start(Some(&text)).await;
    let warnings: Vec<String> = app
        .service
        .installation()
        .warnings
        .iter()
        .map(|w| w.message.clone())
        .collect();
    assert!(
        warnings
            .iter()
            .any(|w| w.contains("camera `C2`: calibration_report") && w.contains("c2-gone.html")),
        "{warnings:?}"
    );
    assert!(
        !warnings
            .iter()
            .any(|w| w.contains("camera `C1`: calibration_report")),
        "{warnings:?}"
    );

    let (status, body) = app.get("/api/v1/cameras").await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let links: Vec<Option<&str>> = body["cameras"]
        .as_array()
        .expect("cameras")
        .iter()
        .map(|c| c["calibration_report"].as_str())
        .collect();
    assert_eq!(
        links,
        [
            Some("/api/v1/cameras/C1/calibration-report"),
            Some("/api/v1/cameras/C2/calibration-report"),
            None
        ]
    );

    let (status, headers, page) = app
        .request_raw("GET", "/api/v1/cameras/C1/calibration-report", &[], "")
        .await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(headers["content-type"], "text/html; charset=utf-8");
    let policy = headers["content-security-policy"].to_str().expect("ascii");
    assert!(
        policy.contains("default-src 'none'") && !policy.contains("script-src"),
        "{policy}"
    );
    assert_eq!(headers["x-content-type-options"], "nosniff");
    assert_eq!(page, std::fs::read(&report).expect("the report"));

    let (status, body) = app.get("/api/v1/cameras/C2/calibration-report").await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert_eq!(body["error"]["code"], "file_unavailable");
    let message = body["error"]["message"].as_str().expect("message");
    assert!(message.contains("camera `C2`"), "{message}");
    assert!(
        !message.contains(&dir.path().display().to_string()),
        "the server's path is not told: {message}"
    );

    let (status, body) = app.get("/api/v1/cameras/C3/calibration-report").await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{body}");
    assert!(
        body["error"]["message"]
            .as_str()
            .is_some_and(|m| m.contains("no calibration report for camera `C3`")),
        "{body}"
    );
    let (status, body) = app.get("/api/v1/cameras/C9/calibration-report").await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{body}");
    assert!(
        body["error"]["message"]
            .as_str()
            .is_some_and(|m| m.contains("no camera `C9`")),
        "{body}"
    );
}
