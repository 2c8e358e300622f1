//! Authentication, unknown endpoints, health.

use super::helpers::{TestApp, nominal_group};
use axum::http::StatusCode;
use brokenray::config::sha256_hex;
use serde_json::json;

pub fn with_tokens() -> String {
    format!(
        "{}\n[[auth.tokens]]\nname = \"viewer\"\nsha256 = \"{}\"\nscopes = [\"read\"]\n\n[[auth.tokens]]\nname = \"pipeline\"\nsha256 = \"{}\"\nscopes = [\"ingest\"]\n\n[[auth.tokens]]\nname = \"operator\"\nsha256 = \"{}\"\nscopes = [\"read\", \"admin\"]\n\n[[auth.tokens]]\nname = \"ship-1\"\nsha256 = \"{}\"\nscopes = [\"sync\"]\nsite = \"ship-1\"\n",
        brokenray::config::DEFAULT_INSTALLATION_TOML,
        sha256_hex("viewer-secret"),
        sha256_hex("pipeline-secret"),
        sha256_hex("operator-secret"),
        sha256_hex("site-secret"),
    )
}

#[tokio::test]
async fn tokens_and_scopes_guard_every_endpoint() {
    let app = TestApp::start(Some(&with_tokens())).await;
    let sample = json!({"samples": [{"link": "C1_from_B", "time": "2026-11-21T10:00:00Z", "pose": {"t_mm": [0, 0, 3000], "q_wxyz": [1, 0, 0, 0]}}]}).to_string();
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
        (
            "POST",
            "/api/v1/calibration/camera",
            Some(super::calibration::request(6, &["k3"]).to_string()),
            "operator-secret",
            "pipeline-secret",
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
    let err = brokenray::app::App::build(inst)
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
    let group = nominal_group;
    let (_, before) = app.get("/metrics").await;
    assert_eq!(
        metric(
            before.as_str().unwrap(),
            "brokenray_requests_rejected_total{status=\"422\"}"
        ),
        0.0,
        "the counters are the service's own: none refused yet"
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
    assert_eq!(
        metric(text, "brokenray_requests_rejected_total{status=\"422\"}"),
        1.0,
        "exactly the one refused request"
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

#[tokio::test]
async fn events_stream_new_results_and_drop_a_client_that_lags() {
    use axum::body::Body;
    use axum::http::Request;
    use http_body_util::BodyExt;
    use tower::ServiceExt;
    let app = TestApp::start(None).await;
    // A subscriber that never reads: ingest must not wait for it.
    let mut idle = app.service.subscribe();
    let resp = app
        .router
        .clone()
        .oneshot(Request::get("/api/v1/events").body(Body::empty()).unwrap())
        .await
        .unwrap();
    assert_eq!(resp.status(), StatusCode::OK);
    assert_eq!(resp.headers()["content-type"], "text/event-stream");
    let mut body = resp.into_body();
    let group = nominal_group;
    let (status, _) = app.post_json("/api/v1/samples", &group(0)).await;
    assert_eq!(status, StatusCode::OK);
    let mut text = String::new();
    while !text.contains("event: result") || !text.contains("\n\n") {
        let frame = tokio::time::timeout(std::time::Duration::from_secs(5), body.frame())
            .await
            .expect("an event within 5 s")
            .expect("stream open")
            .unwrap();
        if let Ok(data) = frame.into_data() {
            text.push_str(&String::from_utf8_lossy(&data));
        }
    }
    let data = text
        .lines()
        .find_map(|l| l.strip_prefix("data: "))
        .expect("data line");
    let event: serde_json::Value = serde_json::from_str(data).unwrap();
    assert_eq!(event["target"], "G");
    assert_eq!(event["status"], "ok");
    assert!(event["pose"]["t_mm"].is_array());
    // Flood past the buffer: 300 commits, each a result 0.4 s (measurement time) after the
    // last, so none is held back by the 10-a-second limit. The idle subscriber lags and is told
    // so; every request was answered meanwhile.
    for i in 1..=300 {
        let (status, _) = app.post_live("/api/v1/samples", &group(10 * i)).await;
        assert_eq!(status, StatusCode::OK);
    }
    let mut lagged = false;
    while let Ok(r) = idle.try_recv().map_err(|e| {
        lagged |= matches!(e, tokio::sync::broadcast::error::TryRecvError::Lagged(_));
    }) {
        let _ = r;
    }
    assert!(
        lagged,
        "a subscriber that does not read falls behind and is cut off"
    );
}

#[tokio::test]
async fn live_results_are_limited_per_target_in_measurement_time() {
    let app = TestApp::start(None).await;
    let mut rx = app.service.subscribe();
    for k in 0..10i64 {
        let (status, _) = app.post_json("/api/v1/samples", &nominal_group(k)).await;
        assert_eq!(status, StatusCode::OK);
    }
    // Ten results 40 ms apart (0.36 s) at the default 10 events a second: times 0, 120, 240,
    // 360 ms pass (each at least 100 ms after the last sent).
    let mut times = Vec::new();
    while let Ok(brokenray::service::LiveEvent::Result { estimate, .. }) = rx.try_recv() {
        times.push((estimate.time_ns - 1_795_255_200_000_000_000i64) / 1_000_000);
    }
    assert_eq!(times, [0, 120, 240, 360]);
}

/// The Prometheus text exposition format (0.0.4), read strictly: every line a comment, a HELP
/// or TYPE line, or a sample `name{label="value",...} value`; a family's TYPE and HELP at most
/// once and before its samples; every family's samples in one group (a scraper refuses a
/// family that comes back after another began); no series twice. Answers the families in order
/// with their sample counts, or what is wrong and on which line.
fn strict_exposition(text: &str) -> Result<Vec<(String, usize)>, String> {
    use std::collections::{HashMap, HashSet};
    fn metric_name(s: &str) -> bool {
        let mut chars = s.chars();
        chars
            .next()
            .is_some_and(|c| c.is_ascii_alphabetic() || c == '_' || c == ':')
            && chars.all(|c| c.is_ascii_alphanumeric() || c == '_' || c == ':')
    }
    // `{a="x",b="y"}` with escapes; answers the labels and the rest of the line.
    type Labels = Vec<(String, String)>;
    fn labels(s: &str) -> Result<(Labels, &str), String> {
        let mut out = Vec::new();
        let mut rest = s.strip_prefix('{').ok_or("no `{`")?;
        loop {
            if let Some(r) = rest.strip_prefix('}') {
                return Ok((out, r));
            }
            let eq = rest.find('=').ok_or("a label without `=`")?;
            let key = &rest[..eq];
            if !metric_name(key) || key.contains(':') {
                return Err(format!("bad label name `{key}`"));
            }
            let mut chars = rest[eq + 1..].char_indices();
            if chars.next().map(|(_, c)| c) != Some('"') {
                return Err(format!("label `{key}`'s value is not quoted"));
            }
            let mut value = String::new();
            let end = loop {
                match chars.next() {
                    Some((_, '\\')) => match chars.next() {
                        Some((_, 'n')) => value.push('\n'),
                        Some((_, c @ ('\\' | '"'))) => value.push(c),
                        _ => return Err(format!("bad escape in label `{key}`")),
                    },
                    Some((i, '"')) => break eq + 1 + i + 1,
                    Some((_, '\n')) | None => return Err(format!("label `{key}` unterminated")),
                    Some((_, c)) => value.push(c),
                }
            };
            out.push((key.to_owned(), value));
            rest = &rest[end..];
            rest = rest.strip_prefix(',').unwrap_or(rest);
        }
    }
    /// The families in order with their sample counts, those already over, the one open.
    #[derive(Default)]
    struct Groups {
        order: Vec<(String, usize)>,
        closed: HashSet<String>,
        current: Option<String>,
    }
    impl Groups {
        fn enter(&mut self, family: &str, line: usize) -> Result<(), String> {
            if self.current.as_deref() == Some(family) {
                return Ok(());
            }
            if let Some(previous) = self.current.take() {
                self.closed.insert(previous);
            }
            if self.closed.contains(family) {
                return Err(format!(
                    "line {line}: family `{family}` comes back after another began"
                ));
            }
            self.current = Some(family.to_owned());
            self.order.push((family.to_owned(), 0));
            Ok(())
        }
    }
    let mut groups = Groups::default();
    let mut kinds: HashMap<String, String> = HashMap::new();
    let mut helps: HashSet<String> = HashSet::new();
    let mut series: HashSet<String> = HashSet::new();
    for (k, line) in text.lines().enumerate() {
        let n = k + 1;
        if line.trim().is_empty() {
            continue;
        }
        if let Some(comment) = line.strip_prefix('#') {
            let words: Vec<&str> = comment.trim_start().splitn(3, ' ').collect();
            match words.as_slice() {
                ["TYPE", name, kind] => {
                    if !metric_name(name) {
                        return Err(format!("line {n}: bad name `{name}`"));
                    }
                    if !["counter", "gauge", "histogram", "summary", "untyped"].contains(kind) {
                        return Err(format!("line {n}: unknown type `{kind}`"));
                    }
                    if groups.order.iter().any(|(f, c)| f == name && *c > 0) {
                        return Err(format!("line {n}: TYPE of `{name}` after its samples"));
                    }
                    if kinds
                        .insert((*name).to_owned(), (*kind).to_owned())
                        .is_some()
                    {
                        return Err(format!("line {n}: TYPE of `{name}` twice"));
                    }
                    groups.enter(name, n)?;
                }
                ["HELP", name, ..] => {
                    if !helps.insert((*name).to_owned()) {
                        return Err(format!("line {n}: HELP of `{name}` twice"));
                    }
                    groups.enter(name, n)?;
                }
                _ => {}
            }
            continue;
        }
        let name_end = line.find(['{', ' ']).ok_or(format!("line {n}: no value"))?;
        let name = &line[..name_end];
        if !metric_name(name) {
            return Err(format!("line {n}: bad name `{name}`"));
        }
        let (labels, rest) = if line[name_end..].starts_with('{') {
            labels(&line[name_end..]).map_err(|e| format!("line {n}: {e}"))?
        } else {
            (Vec::new(), &line[name_end..])
        };
        let value = rest
            .strip_prefix(' ')
            .ok_or(format!("line {n}: no space before the value"))?;
        let value = value.split(' ').next().unwrap_or_default();
        if !matches!(value, "NaN" | "+Inf" | "-Inf") && value.parse::<f64>().is_err() {
            return Err(format!("line {n}: bad value `{value}`"));
        }
        // The family: the name, or for a histogram or summary the name less its suffix.
        let family = ["_bucket", "_sum", "_count"]
            .iter()
            .filter_map(|s| name.strip_suffix(s))
            .find(|base| {
                matches!(
                    kinds.get(*base).map(String::as_str),
                    Some("histogram" | "summary")
                )
            })
            .unwrap_or(name);
        if kinds.get(family).map(String::as_str) == Some("histogram")
            && name.ends_with("_bucket")
            && !labels.iter().any(|(k, _)| k == "le")
        {
            return Err(format!("line {n}: a bucket without `le`"));
        }
        groups.enter(family, n)?;
        if let Some(last) = groups.order.last_mut() {
            last.1 += 1;
        }
        let mut sorted = labels.clone();
        sorted.sort();
        if !series.insert(format!("{name}{sorted:?}")) {
            return Err(format!("line {n}: series `{name}{sorted:?}` twice"));
        }
    }
    Ok(groups.order)
}

#[test]
fn the_strict_reader_refuses_what_a_scraper_refuses() {
    let good =
        "# HELP a_total A.\n# TYPE a_total counter\na_total{x=\"1\"} 2\na_total{x=\"2\"} 3\n";
    assert_eq!(
        strict_exposition(good).unwrap(),
        vec![("a_total".to_owned(), 2)]
    );
    for bad in [
        // Two families interleaved.
        "# TYPE a_total counter\n# TYPE b_total counter\na_total 1\nb_total 1\na_total{x=\"2\"} 1\n",
        "# TYPE a counter\na 1\n# TYPE a counter\n",
        "a{x=\"1} 2\n",
        "a{x=\"1\"} two\n",
        "a 1\na 2\n",
        "# TYPE h histogram\nh_bucket 1\n",
    ] {
        assert!(strict_exposition(bad).is_err(), "accepted:\n{bad}");
    }
}

/// `/metrics` with samples of several links, rejections and a writer at work reads as strict
/// exposition text: every family one group, each link family holding every measured link.
#[tokio::test]
async fn metrics_are_strict_exposition_text_with_every_family_in_one_group() {
    let app = TestApp::start(None).await;
    for k in 0..3 {
        app.post_json("/api/v1/samples", &nominal_group(k)).await;
    }
    app.post_json("/api/v1/samples", &json!({"samples": []}))
        .await;
    let (status, text) = app.get("/metrics").await;
    assert_eq!(status, StatusCode::OK);
    let text = text.as_str().unwrap();
    let families = strict_exposition(text).unwrap_or_else(|e| panic!("{e}\n{text}"));
    let measured = app
        .service
        .installation()
        .model
        .links
        .iter()
        .filter(|l| matches!(l.kind, brokenray::model::LinkKind::Measured(_)))
        .count();
    assert!(measured >= 2, "the test needs two measured links");
    for name in [
        "brokenray_link_samples_total",
        "brokenray_link_outliers_total",
        "brokenray_link_rate_hz",
        "brokenray_link_age_seconds",
        "brokenray_link_stale",
    ] {
        let count = families
            .iter()
            .find(|(f, _)| f == name)
            .map_or(0, |(_, c)| *c);
        assert_eq!(count, measured, "{name}: one sample per measured link");
    }
}
