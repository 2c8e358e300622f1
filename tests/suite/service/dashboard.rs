//! The web dashboard: its files served open, cacheable and under a strict content policy; and the
//! page itself driven in Chromium (`tests/browser/dashboard.mjs`, playwright-core) against a
//! service holding a simulated ship's history.

use super::access::with_tokens;
use super::helpers::TestApp;
use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use brokenray::clock::format_ns;
use brokenray::config::DEFAULT_INSTALLATION_TOML;
use brokenray::feed::observation_items;
use brokenray::sim::{Scenario, SimSettings, Simulator};
use http_body_util::BodyExt;
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use tower::ServiceExt;

/// Status, headers and body of a GET with the given request headers.
async fn fetch(
    app: &TestApp,
    uri: &str,
    headers: &[(header::HeaderName, &str)],
) -> (StatusCode, axum::http::HeaderMap, Vec<u8>) {
    let mut builder = Request::builder().uri(uri);
    for (name, value) in headers {
        builder = builder.header(name, *value);
    }
    let resp = app
        .router
        .clone()
        .oneshot(builder.body(Body::empty()).expect("request"))
        .await
        .expect("response");
    let status = resp.status();
    let headers = resp.headers().clone();
    let body = resp.into_body().collect().await.expect("body").to_bytes();
    (status, headers, body.to_vec())
}

#[tokio::test]
async fn the_page_and_its_files_are_served_open_with_a_content_policy_and_etags() {
    // Tokens configured: the API needs one, the dashboard's files do not.
    let app = TestApp::start(Some(&with_tokens())).await;
    follow_real_time(&app);
    let (status, headers, body) = fetch(&app, "/", &[]).await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(headers[header::CONTENT_TYPE], "text/html; charset=utf-8");
    let csp = headers[header::CONTENT_SECURITY_POLICY]
        .to_str()
        .expect("ascii");
    assert!(
        csp.contains("script-src 'self'") && csp.contains("connect-src 'self'"),
        "{csp}"
    );
    let page = String::from_utf8(body).expect("utf-8");
    assert_eq!(
        page.as_bytes(),
        std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("web/index.html"))
            .expect("web/index.html"),
        "the page served is web/index.html"
    );

    // Every file the page refers to is served, with its type, and revalidates to 304.
    let referred: Vec<&str> = page
        .split("\"/assets/")
        .skip(1)
        .map(|rest| &rest[..rest.find('"').expect("closing quote")])
        .collect();
    for want in [
        "app.js",
        "style.css",
        "uPlot.iife.min.js",
        "uPlot.min.css",
        "favicon.svg",
        "uPlot.LICENSE",
    ] {
        assert!(
            referred.contains(&want),
            "the page does not load `{want}`: {referred:?}"
        );
    }
    for file in &referred {
        let uri = format!("/assets/{file}");
        let (status, headers, body) = fetch(&app, &uri, &[]).await;
        assert_eq!(status, StatusCode::OK, "{uri}");
        assert!(!body.is_empty(), "{uri} is empty");
        let kind = headers[header::CONTENT_TYPE].to_str().expect("ascii");
        let expected = match file.rsplit('.').next() {
            Some("js") => "text/javascript",
            Some("css") => "text/css",
            Some("svg") => "image/svg+xml",
            _ => "text/plain",
        };
        assert!(kind.starts_with(expected), "{uri}: {kind}");
        let etag = headers[header::ETAG].to_str().expect("ascii").to_owned();
        let (again, _, body) = fetch(&app, &uri, &[(header::IF_NONE_MATCH, &etag)]).await;
        assert_eq!(again, StatusCode::NOT_MODIFIED, "{uri} with its ETag");
        assert!(body.is_empty());
        let (changed, _, _) =
            fetch(&app, &uri, &[(header::IF_NONE_MATCH, "\"something-else\"")]).await;
        assert_eq!(changed, StatusCode::OK, "{uri} with another ETag");
    }

    // The script is ES modules: every module imported by a served one is served too.
    let mut modules = vec!["app.js".to_owned()];
    let mut seen = std::collections::BTreeSet::new();
    while let Some(module) = modules.pop() {
        if !seen.insert(module.clone()) {
            continue;
        }
        let uri = format!("/assets/{module}");
        let (status, headers, body) = fetch(&app, &uri, &[]).await;
        assert_eq!(
            status,
            StatusCode::OK,
            "{uri}, imported by the dashboard's script"
        );
        let kind = headers[header::CONTENT_TYPE].to_str().expect("ascii");
        assert!(kind.starts_with("text/javascript"), "{uri}: {kind}");
        let text = String::from_utf8(body).expect("utf-8");
        for rest in text.split(" from './").skip(1) {
            modules.push(rest[..rest.find('\'').expect("closing quote")].to_owned());
        }
    }
    assert!(seen.len() > 5, "the script's modules: {seen:?}");

    // The charting library is the vendored, pinned one, and its licence ships with it.
    let (_, _, uplot) = fetch(&app, "/assets/uPlot.iife.min.js", &[]).await;
    assert!(uplot.starts_with(b"/*! https://github.com/leeoniya/uPlot (v1.6.32) */"));
    let (_, _, licence) = fetch(&app, "/assets/uPlot.LICENSE", &[]).await;
    assert!(String::from_utf8_lossy(&licence).contains("MIT License"));

    // An unknown file is named; the API still needs a token.
    let (status, _, body) = fetch(&app, "/assets/nothing.js", &[]).await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    let body: Value = serde_json::from_slice(&body).expect("error body");
    assert!(
        body["error"]["message"]
            .as_str()
            .is_some_and(|m| m.contains("`nothing.js`")),
        "{body}"
    );
    let (status, _, _) = fetch(&app, "/assets/index.html", &[]).await;
    assert_eq!(
        status,
        StatusCode::NOT_FOUND,
        "the page is served at / only"
    );
    let (status, _, _) = fetch(&app, "/api/v1/targets", &[]).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED);
}

#[tokio::test]
async fn answers_are_gzipped_when_asked_but_the_event_stream_is_not() {
    let app = TestApp::start(None).await;
    let gzip = [(header::ACCEPT_ENCODING, "gzip")];
    let (_, plain_headers, plain) = fetch(&app, "/assets/uPlot.iife.min.js", &[]).await;
    assert!(!plain_headers.contains_key(header::CONTENT_ENCODING));
    let (_, zipped_headers, zipped) = fetch(&app, "/assets/uPlot.iife.min.js", &gzip).await;
    assert_eq!(zipped_headers[header::CONTENT_ENCODING], "gzip");
    assert!(
        zipped.len() * 2 < plain.len(),
        "gzip: {} of {} bytes",
        zipped.len(),
        plain.len()
    );
    let (_, targets, _) = fetch(&app, "/api/v1/targets", &gzip).await;
    assert_eq!(targets[header::CONTENT_ENCODING], "gzip");
    // The event stream never ends: look at its headers only.
    let events = app
        .router
        .clone()
        .oneshot(
            Request::builder()
                .uri("/api/v1/events")
                .header(header::ACCEPT_ENCODING, "gzip")
                .body(Body::empty())
                .expect("request"),
        )
        .await
        .expect("answer");
    assert!(
        events.headers()[header::CONTENT_TYPE]
            .as_bytes()
            .starts_with(b"text/event-stream")
    );
    assert!(!events.headers().contains_key(header::CONTENT_ENCODING));
}

/// What the page draws the relay chain and the threshold lines from.
#[tokio::test]
async fn targets_answer_each_paths_frames_and_the_thresholds() {
    let app = TestApp::start(None).await;
    let (status, targets) = app.get("/api/v1/targets").await;
    assert_eq!(status, StatusCode::OK);
    let g = &targets[0];
    let path = &g["paths"][0];
    let frames: Vec<&str> = path["frames"]
        .as_array()
        .expect("frames")
        .iter()
        .map(|f| f.as_str().expect("name"))
        .collect();
    assert_eq!(frames, ["B", "C1", "C2", "M", "C3", "G"]);
    // Each step joins its two frames, in the direction it states.
    let steps = path["steps"].as_array().expect("steps");
    assert_eq!(steps.len() + 1, frames.len());
    for (i, step) in steps.iter().enumerate() {
        let link = step["link"].as_str().expect("link");
        let (parent, child) = link.split_once("_from_").expect("parent_from_child");
        let expected = match step["direction"].as_str() {
            Some("forward") => (child, parent),
            Some("inverted") => (parent, child),
            other => panic!("direction {other:?}"),
        };
        assert_eq!((frames[i], frames[i + 1]), expected, "step {i}: {link}");
    }
    let thresholds = &g["alarms"];
    let spec = &app.service.installation().model.targets[0].alarms;
    assert_eq!(
        thresholds["warn_rotation_arcsec"],
        json!(spec.warn_rotation_arcsec)
    );
    assert_eq!(
        thresholds["alarm_rotation_arcsec"],
        json!(spec.alarm_rotation_arcsec)
    );
    assert_eq!(
        thresholds["warn_translation_mm"],
        json!(spec.warn_translation_mm)
    );
    assert_eq!(
        thresholds["alarm_translation_mm"],
        json!(spec.alarm_translation_mm)
    );
    assert_eq!(thresholds["warn_rotation_arcsec"], json!(60.0));
}

/// What the browser test needs: Node.js, playwright-core under `tests/browser`, and Chromium.
pub(crate) struct Browser {
    node: PathBuf,
    chromium: PathBuf,
    dir: PathBuf,
}

/// Finds the browser tools, or says what is missing and how `scripts/test` installs it.
pub(crate) fn browser() -> Browser {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/browser");
    let node = crate::common::on_path("node").expect(
        "the dashboard test needs Node.js (`node`): `scripts/test` installs it (Debian: nodejs npm)",
    );
    assert!(
        dir.join("node_modules/playwright-core/package.json")
            .is_file(),
        "the dashboard test needs playwright-core: `scripts/test` installs it \
         (`npm ci --prefix tests/browser`)"
    );
    let chromium = std::env::var_os("BROKENRAY_CHROMIUM")
        .map(PathBuf::from)
        .or_else(|| crate::common::on_path("chromium"))
        .or_else(|| crate::common::on_path("chromium-browser"))
        .expect(
            "the dashboard test needs Chromium: `scripts/test` installs it (Debian: chromium), \
             or set BROKENRAY_CHROMIUM to a Chromium executable",
        );
    Browser {
        node,
        chromium,
        dir,
    }
}

/// The built-in installation with the oscillatory model a ship's flexure needs, camera C2 with
/// a source (never opened by the test app: its state is set by the test), and a Modbus output
/// on a free loopback port.
fn ship_installation() -> String {
    DEFAULT_INSTALLATION_TOML
        .replace("model = \"static\"", "model = \"oscillatory\"")
        .replacen(
            "[[cameras]]\nframe = \"C2\"",
            "[[cameras]]\nframe = \"C2\"\nsource = { address = \"10.0.0.2\" }",
            1,
        )
        + "\n[[outputs.modbus]]\nlisten = \"127.0.0.1:0\"\n"
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_dashboard_works_in_a_real_browser() {
    if crate::common::skip_without(
        crate::common::Needs::Browser,
        concat!(module_path!(), "::the_dashboard_works_in_a_real_browser"),
    ) {
        return;
    }
    let tools = browser();
    let app = TestApp::start(Some(&ship_installation())).await;
    follow_real_time(&app);
    let inst = app.service.installation().clone();
    // Camera C2's source has lost its camera.
    app.sources[0].error(
        brokenray::acquire::SourceStatus::Disconnected,
        "no frame for 2.1 s".into(),
        now_ns(),
    );

    // 150 s of a ship at 10 Hz, ending now; the reference set over the first 15 s.
    let now_ns = now_ns();
    let (rate_hz, span_s) = (10.0, 150.0);
    let start_ns = now_ns - (span_s * 1e9) as i64;
    let mut sim = Simulator::new(
        &inst.model,
        SimSettings {
            scenario: Scenario::Ship,
            rate_hz,
            start_ns,
            duration_s: None,
            pixel_sigma_px: None,
            outlier_rate: 0.0,
            seed: 8,
        },
    )
    .expect("simulator");
    let groups = (rate_hz * span_s) as usize;
    let mut posted = 0;
    while posted < groups {
        let mut items = Vec::new();
        for _ in 0..50 {
            items.extend(observation_items(&sim.next_group()));
        }
        posted += 50;
        let (status, body) = app
            .post_json("/api/v1/observations", &json!({ "observations": items }))
            .await;
        assert_eq!(status, StatusCode::OK, "{body}");
        if posted == 200 {
            let window =
                json!({"from": format_ns(start_ns), "to": format_ns(start_ns + 15_000_000_000)});
            let (status, body) = app.post_json("/api/v1/targets/G/reference", &window).await;
            assert_eq!(status, StatusCode::CREATED, "{body}");
        }
    }
    // What the cameras see: frames of C1 and C2, and C3's marker covered (an empty frame).
    let group = sim.next_group();
    let render = brokenray::sim::render::RenderSettings {
        samples_per_side: 8,
        ..brokenray::sim::render::RenderSettings::default()
    };
    for (camera, frame) in sim.render_frames(&group, &render) {
        let frame = if camera == "C3" {
            brokenray::vision::GreyImage::from_u8(
                frame.width_px(),
                frame.height_px(),
                &vec![40; (frame.width_px() * frame.height_px()) as usize],
            )
            .expect("frame")
        } else {
            frame
        };
        let (status, body) = app
            .request_with_headers(
                "POST",
                &format!(
                    "/api/v1/frames?camera={camera}&time={}",
                    format_ns(group.time_ns)
                ),
                &[("content-type", "image/png")],
                brokenray::imagefile::encode(&frame, brokenray::imagefile::FrameFormat::Png)
                    .expect("png"),
            )
            .await;
        assert_eq!(status, StatusCode::OK, "{camera}: {body}");
        assert_eq!(
            body["markers"][0]["found"],
            camera != "C3",
            "{camera}: {body}"
        );
    }
    // The live part, posted by the browser script with the current time.
    let live: Vec<Vec<Value>> = (0..25)
        .map(|_| {
            observation_items(&sim.next_group())
                .into_iter()
                .map(|mut o| {
                    o.as_object_mut().expect("object").remove("time");
                    o
                })
                .collect()
        })
        .collect();
    let live_file = app.dir.path().join("live.json");
    std::fs::write(&live_file, serde_json::to_vec(&live).expect("json")).expect("live file");

    let (base, server) = serve(&app).await;

    let artifacts = artifacts_dir();
    for shot in [
        "dashboard.png",
        "dashboard-laptop.png",
        "dashboard-control-room.png",
    ] {
        let _ = std::fs::remove_file(artifacts.join(shot));
    }
    run_script(
        tools,
        "dashboard.mjs",
        vec![
            base.into(),
            live_file.into_os_string(),
            artifacts.clone().into_os_string(),
        ],
    )
    .await;
    server.abort();
    for shot in [
        "dashboard.png",
        "dashboard-laptop.png",
        "dashboard-control-room.png",
    ] {
        let bytes = std::fs::metadata(artifacts_dir().join(shot)).map_or(0, |m| m.len());
        assert!(bytes > 20_000, "screenshot {shot}: {bytes} bytes");
    }
}

/// Runs a script of `tests/browser` with Node.js, prints what it said, and fails the test unless
/// every check of the script passed.
pub(crate) async fn run_script(tools: Browser, script: &str, args: Vec<std::ffi::OsString>) {
    let path = tools.dir.join(script);
    let output = tokio::task::spawn_blocking(move || {
        std::process::Command::new(&tools.node)
            .arg(&path)
            .args(&args)
            .env("BROKENRAY_CHROMIUM", &tools.chromium)
            .current_dir(&tools.dir)
            .output()
            .expect("node runs")
    })
    .await
    .expect("browser task");
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    println!("{stdout}");
    assert!(
        output.status.success() && stdout.contains("all checks passed"),
        "{script} failed in the browser:\n{stdout}\n{stderr}"
    );
}

/// The router of `app` on a free loopback port: its base URL and the server task.
async fn serve(app: &TestApp) -> (String, tokio::task::JoinHandle<std::io::Result<()>>) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let base = format!("http://{}", listener.local_addr().expect("address"));
    let router = app.router.clone();
    (
        base,
        tokio::spawn(async move { axum::serve(listener, router).await }),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_tokens_the_dashboard_asks_for_one_and_sends_it() {
    if crate::common::skip_without(
        crate::common::Needs::Browser,
        concat!(
            module_path!(),
            "::with_tokens_the_dashboard_asks_for_one_and_sends_it"
        ),
    ) {
        return;
    }
    let tools = browser();
    // Camera C1's calibration report is named by the installation.
    let reports = tempfile::tempdir().expect("temp dir");
    let report = reports.path().join("c1.html");
    super::cameras::write_calibration_report(&report);
    let text = with_tokens().replacen(
        "[[cameras]]\nframe = \"C1\"",
        &format!(
            "[[cameras]]\nframe = \"C1\"\ncalibration_report = {:?}",
            report.display().to_string()
        ),
        1,
    );
    let app = TestApp::start(Some(&text)).await;
    follow_real_time(&app);
    let inst = app.service.installation().clone();
    let mut sim = Simulator::new(
        &inst.model,
        SimSettings {
            scenario: Scenario::Static,
            rate_hz: 10.0,
            start_ns: now_ns() - 5_000_000_000,
            duration_s: None,
            pixel_sigma_px: None,
            outlier_rate: 0.0,
            seed: 3,
        },
    )
    .expect("simulator");
    let items: Vec<Value> = (0..40)
        .flat_map(|_| observation_items(&sim.next_group()))
        .collect();
    let (status, body) = app
        .request(
            "POST",
            "/api/v1/observations",
            Some((
                "application/json",
                json!({ "observations": items }).to_string(),
            )),
            Some("pipeline-secret"),
        )
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let (base, server) = serve(&app).await;
    run_script(
        tools,
        "token.mjs",
        vec![base.into(), "viewer-secret".into()],
    )
    .await;
    server.abort();
}

/// The browser reads the real clock, and posts at its times: the service's clock follows it
/// (until the test ends).
fn follow_real_time(app: &TestApp) {
    let clock = app.clock.clone();
    clock.set_ns(now_ns());
    tokio::spawn(async move {
        loop {
            clock.set_ns(now_ns());
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
    });
}

fn now_ns() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .expect("clock")
        .as_nanos() as i64
}

pub(crate) fn artifacts_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/artifacts")
}
