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
