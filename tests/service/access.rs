//! Authentication, unknown endpoints, health.

use super::helpers::TestApp;
use axum::http::StatusCode;
use brokenray::api::auth::sha256_hex;
use serde_json::json;

fn with_tokens() -> String {
    format!(
        "{}\n[[auth.tokens]]\nname = \"viewer\"\nsha256 = \"{}\"\nscopes = [\"read\"]\n\n[[auth.tokens]]\nname = \"pipeline\"\nsha256 = \"{}\"\nscopes = [\"ingest\"]\n\n[[auth.tokens]]\nname = \"operator\"\nsha256 = \"{}\"\nscopes = [\"read\", \"admin\"]\n",
        brokenray::config::DEFAULT_INSTALLATION_TOML,
        sha256_hex("viewer-secret"),
        sha256_hex("pipeline-secret"),
        sha256_hex("operator-secret"),
    )
}

#[tokio::test]
async fn tokens_and_scopes_guard_every_endpoint() {
    let app = TestApp::start(Some(&with_tokens())).await;
    let sample = json!({"samples": [{"link": "C1_from_B", "time": 1, "pose": {"t_mm": [0, 0, 3000], "q_wxyz": [1, 0, 0, 0]}}]}).to_string();
    let reference = json!({"pose": {"t_mm": [0, 0, 0], "q_wxyz": [1, 0, 0, 0]}}).to_string();
    let calibration = json!({"pose": {"t_mm": [0, 0, 0], "q_wxyz": [1, 0, 0, 0]}, "sigma": {"rotation_arcsec": 5, "translation_mm": 0.05}}).to_string();
    // (method, uri, body, token that may, token that may not)
    let cases: Vec<(&str, &str, Option<String>, &str, &str)> = vec![
        (
            "GET",
            "/api/v1/targets",
            None,
            "viewer-secret",
            "pipeline-secret",
        ),
        (
            "GET",
            "/api/v1/links",
            None,
            "viewer-secret",
            "pipeline-secret",
        ),
        (
            "GET",
            "/api/v1/targets/G/stats",
            None,
            "viewer-secret",
            "pipeline-secret",
        ),
        (
            "GET",
            "/api/v1/targets/G/references",
            None,
            "viewer-secret",
            "pipeline-secret",
        ),
        (
            "GET",
            "/api/v1/links/C1_from_B/samples",
            None,
            "viewer-secret",
            "pipeline-secret",
        ),
        (
            "GET",
            "/api/v1/links/C2_from_C1/calibrations",
            None,
            "viewer-secret",
            "pipeline-secret",
        ),
        (
            "GET",
            "/api/v1/targets/G/compensation",
            None,
            "viewer-secret",
            "pipeline-secret",
        ),
        (
            "POST",
            "/api/v1/samples",
            Some(sample),
            "pipeline-secret",
            "viewer-secret",
        ),
        (
            "POST",
            "/api/v1/targets/G/reference",
            Some(reference),
            "operator-secret",
            "pipeline-secret",
        ),
        (
            "PUT",
            "/api/v1/links/C2_from_C1/calibration",
            Some(calibration),
            "operator-secret",
            "viewer-secret",
        ),
    ];
    for (method, uri, body, allowed, denied) in cases {
        let b = || body.clone().map(|t| ("application/json", t));
        let (s, _) = app.request(method, uri, b(), None).await;
        assert_eq!(
            s,
            StatusCode::UNAUTHORIZED,
            "{method} {uri} without a token"
        );
        let (s, _) = app.request(method, uri, b(), Some("wrong")).await;
        assert_eq!(
            s,
            StatusCode::UNAUTHORIZED,
            "{method} {uri} with an unknown token"
        );
        let (s, body403) = app.request(method, uri, b(), Some(denied)).await;
        assert_eq!(
            s,
            StatusCode::FORBIDDEN,
            "{method} {uri} with a token lacking the scope: {body403}"
        );
        let (s, ok) = app.request(method, uri, b(), Some(allowed)).await;
        assert!(
            s.is_success(),
            "{method} {uri} with the right scope: {s} {ok}"
        );
    }
}

#[tokio::test]
async fn unknown_endpoints_and_names_answer_json_404() {
    let app = TestApp::start(None).await;
    for uri in [
        "/api/v1/nothing",
        "/api/v1/targets/Q/compensation",
        "/api/v1/links/X_from_Y/samples",
        "/elsewhere",
    ] {
        let (status, body) = app.get(uri).await;
        assert_eq!(status, StatusCode::NOT_FOUND, "{uri}");
        assert_eq!(body["error"]["code"], "not_found", "{uri}: {body}");
    }
    let (status, body) = app.get("/healthz").await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(body["database"], true);
    assert_eq!(body["writer"], true);
}

#[tokio::test]
async fn listening_beyond_loopback_without_tokens_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML.replace("127.0.0.1:7878", "0.0.0.0:0");
    let inst = super::helpers::installation(&dir, Some(&text));
    let err = brokenray::api::App::build(inst)
        .await
        .err()
        .expect("refused");
    assert!(
        err.to_string()
            .contains("refusing to listen on 0.0.0.0:0 without authentication"),
        "{err}"
    );
}

fn metric(text: &str, name: &str) -> f64 {
    text.lines()
        .find(|l| l.starts_with(name) && l[name.len()..].starts_with(' '))
        .and_then(|l| l.rsplit(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no metric `{name}` in:\n{text}"))
}

#[tokio::test]
async fn metrics_count_ingest_rejections_and_links_in_prometheus_text() {
    let app = TestApp::start(None).await;
    let group = |k: i64| {
        let samples: Vec<serde_json::Value> = ["C1_from_B", "C2_from_M", "C3_from_G"]
            .iter()
            .map(|l| {
                json!({"link": l, "time": 1_795_255_200_000_000_000i64 + k * 40_000_000,
                       "pose": {"t_mm": [0.0, 0.0, 3000.0], "q_wxyz": [0, 1, 0, 0]}})
            })
            .collect();
        json!({ "samples": samples })
    };
    let (_, before) = app.get("/metrics").await;
    let rejected_before = metric(
        before.as_str().unwrap(),
        "brokenray_requests_rejected_total{status=\"422\"}",
    );
    for k in 0..3 {
        app.post_json("/api/v1/samples", &group(k)).await;
    }
    app.post_json("/api/v1/samples", &group(2)).await;
    let (status, _) = app
        .post_json("/api/v1/samples", &json!({"samples": []}))
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    let (status, text) = app.get("/metrics").await;
    assert_eq!(status, StatusCode::OK);
    let text = text.as_str().unwrap();
    assert!(text.contains("# TYPE brokenray_samples_stored_total counter"));
    assert_eq!(metric(text, "brokenray_samples_stored_total"), 9.0);
    assert_eq!(metric(text, "brokenray_samples_duplicate_total"), 3.0);
    assert_eq!(metric(text, "brokenray_ingest_requests_total"), 4.0);
    assert!(metric(text, "brokenray_commit_seconds_count") >= 1.0);
    assert!(
        metric(text, "brokenray_requests_rejected_total{status=\"422\"}") >= rejected_before + 1.0
    );
    assert_eq!(
        metric(text, "brokenray_link_samples_total{link=\"C1_from_B\"}"),
        3.0
    );
    assert_eq!(
        metric(text, "brokenray_link_rate_hz{link=\"C2_from_M\"}"),
        25.0
    );
    assert_eq!(
        metric(text, "brokenray_link_stale{link=\"C3_from_G\"}"),
        0.0
    );
    assert_eq!(metric(text, "brokenray_writer_queue_depth"), 0.0);
}
