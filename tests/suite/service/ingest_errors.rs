//! Bad input: every kind gets a 4xx naming the item and field, and the store is unchanged.

use super::helpers::{TestApp, time_text};
use axum::http::StatusCode;
use serde_json::{Value, json};

const GOOD: &str = r#"{"link": "C1_from_B", "time": "2026-11-21T10:00:00.040Z", "pose": {"t_mm": [1.0, 2.0, 3000.0], "q_wxyz": [1, 0, 0, 0]}}"#;

/// A batch of one good sample and one bad one (index 1), built from text.
fn batch_with(bad: &str) -> String {
    format!(r#"{{"samples": [{GOOD}, {bad}]}}"#)
}

/// A sample whose `t_mm[1]` is written as `number` (verbatim JSON text).
fn with_t1(number: &str) -> String {
    format!(
        r#"{{"link": "C2_from_M", "time": "2026-11-21T10:00:00.040Z", "pose": {{"t_mm": [1.0, {number}, 3000.0], "q_wxyz": [1, 0, 0, 0]}}}}"#
    )
}

/// What the store holds, as the API reads it back: counts and the newest values.
async fn store_state(app: &TestApp) -> Value {
    let mut out = Vec::new();
    for link in ["C1_from_B", "C2_from_M", "C3_from_G"] {
        out.push(
            app.get(&format!("/api/v1/links/{link}/samples?limit=100000"))
                .await
                .1,
        );
    }
    out.push(app.get("/api/v1/targets/G/compensation").await.1);
    out.push(app.get("/api/v1/targets/G/stats?source=raw").await.1);
    let links = app.get("/api/v1/links").await.1;
    out.push(json!(
        links
            .as_array()
            .unwrap()
            .iter()
            .map(|l| (l["n_samples"].clone(), l["last_time"].clone()))
            .collect::<Vec<_>>()
    ));
    Value::Array(out)
}

async fn seeded() -> TestApp {
    let app = TestApp::start(Some(&brokenray::config::DEFAULT_INSTALLATION_TOML.replace(
        "database = \"brokenray.db\"",
        "database = \"brokenray.db\"\nmax_body_bytes = 65536\nmax_batch_samples = 50",
    )))
    .await;
    let mut samples = Vec::new();
    for k in 0..5 {
        for (link, t) in [
            ("C1_from_B", 2991.7),
            ("C2_from_M", 3156.6),
            ("C3_from_G", 2999.6),
        ] {
            samples.push(json!({"link": link, "time": time_text(k), "pose": {"t_mm": [0.0, 0.0, t], "q_wxyz": [0, 1, 0, 0]}}));
        }
    }
    let (status, body) = app
        .post_json("/api/v1/samples", &json!({"samples": samples}))
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    app
}

/// Posts `body`, expects `status`, and that some detail names `index` and a field containing
/// `field` (or the message containing it, where the problem has no field).
async fn expect_refused(
    app: &TestApp,
    content_type: &str,
    body: &str,
    status: StatusCode,
    index: Option<usize>,
    field: &str,
) -> Value {
    let (got, answer) = app.post_text("/api/v1/samples", content_type, body).await;
    assert_eq!(got, status, "for {body}: {answer}");
    let error = &answer["error"];
    assert!(
        error["code"].is_string() && error["message"].is_string(),
        "{answer}"
    );
    if index.is_some() || !field.is_empty() {
        let details = error["details"].as_array().expect("details");
        let found = details.iter().any(|d| {
            let index_ok = index.is_none_or(|i| d["index"] == json!(i));
            let field_ok = d["field"].as_str().is_some_and(|f| f.contains(field))
                || d["message"].as_str().is_some_and(|m| m.contains(field));
            index_ok && field_ok
        });
        assert!(
            found,
            "no detail names item {index:?} and `{field}` for {body}: {answer}"
        );
    }
    answer
}

#[tokio::test]
async fn every_kind_of_bad_input_is_refused_with_its_item_and_field_and_nothing_changes() {
    let app = seeded().await;
    let before = store_state(&app).await;
    let json_ct = "application/json";
    let unprocessable = StatusCode::UNPROCESSABLE_ENTITY;
    // Malformed JSON.
    expect_refused(
        &app,
        json_ct,
        r#"{"samples": [{"link": "C1_from_B", "#,
        StatusCode::BAD_REQUEST,
        Some(0),
        "",
    )
    .await;
    expect_refused(
        &app,
        json_ct,
        "not json at all",
        StatusCode::BAD_REQUEST,
        None,
        "",
    )
    .await;
    // Wrong types, missing and unknown fields.
    expect_refused(
        &app,
        json_ct,
        &batch_with(&with_t1("\"two\"")),
        unprocessable,
        Some(1),
        "pose.t_mm[1]",
    )
    .await;
    expect_refused(
        &app,
        json_ct,
        &batch_with(r#"{"link": 7, "time": 1, "pose": {"t_mm": [0,0,0], "q_wxyz": [1,0,0,0]}}"#),
        unprocessable,
        Some(1),
        "link",
    )
    .await;
    expect_refused(
        &app,
        json_ct,
        &batch_with(r#"{"link": "C1_from_B", "time": "2026-11-21T10:00:01Z"}"#),
        unprocessable,
        Some(1),
        "missing field `pose`",
    )
    .await;
    expect_refused(&app, json_ct, &batch_with(r#"{"link": "C1_from_B", "time": "2026-11-21T10:00:01Z", "pose": {"t_mm": [0,0,0], "q_wxyz": [1,0,0,0]}, "colour": "red"}"#), unprocessable, Some(1), "colour").await;
    expect_refused(&app, json_ct, &batch_with(r#"{"link": "C1_from_B", "time": "2026-11-21T10:00:01Z", "pose": {"t_mm": [0,0], "q_wxyz": [1,0,0,0]}}"#), unprocessable, Some(1), "pose.t_mm").await;
    expect_refused(&app, json_ct, r#"{"sample": []}"#, unprocessable, None, "").await;
    // Empty batch.
    expect_refused(
        &app,
        json_ct,
        r#"{"samples": []}"#,
        unprocessable,
        None,
        "samples",
    )
    .await;
    // NaN and infinity, written in many ways.
    for number in [
        "NaN",
        "nan",
        "Infinity",
        "-Infinity",
        "inf",
        "1e999",
        "-1e400",
    ] {
        let status = if number.starts_with(['1', '-']) && number.contains('e') {
            // A number out of range is well-formed JSON that does not fit an f64.
            unprocessable
        } else {
            StatusCode::BAD_REQUEST
        };
        expect_refused(
            &app,
            json_ct,
            &batch_with(&with_t1(number)),
            status,
            Some(1),
            "pose.t_mm[1]",
        )
        .await;
    }
    for text in ["\"NaN\"", "\"inf\"", "null"] {
        expect_refused(
            &app,
            json_ct,
            &batch_with(&with_t1(text)),
            unprocessable,
            Some(1),
            "pose.t_mm[1]",
        )
        .await;
    }
    // Every kind of invalid sample `docs/interface.md`, "HTTP API" lists.
    let cases: [(&str, &str); 11] = [
        (
            r#"{"link": "C1_from_B", "time": "2026-11-21T10:00:01Z", "pose": {"t_mm": [0,0,0], "q_wxyz": [1,0,0,0], "euler_deg": [0, 0, 1]}}"#,
            "pose.euler_deg",
        ),
        (
            r#"{"link": "C9_from_B", "time": "2026-11-21T10:00:01Z", "pose": {"t_mm": [0,0,0], "q_wxyz": [1,0,0,0]}}"#,
            "link",
        ),
        (
            r#"{"link": "C2_from_C1", "time": "2026-11-21T10:00:01Z", "pose": {"t_mm": [0,0,0], "q_wxyz": [1,0,0,0]}}"#,
            "link",
        ),
        (
            r#"{"link": "C1_from_B", "time": "2026-11-21T10:00:01Z", "pose": {"t_mm": [0,0,0], "q_wxyz": [1,0.1,0,0]}}"#,
            "pose.q_wxyz",
        ),
        (
            r#"{"link": "C1_from_B", "time": "2026-11-21T10:00:01Z", "pose": {"t_mm": [0,0,0], "r": [[1,0,0],[0,1,0],[0,0,-1]]}}"#,
            "pose.r",
        ),
        (
            r#"{"link": "C1_from_B", "time": "2026-11-21T10:00:01Z", "pose": {"t_mm": [0,0,0]}}"#,
            "pose",
        ),
        (
            r#"{"link": "C1_from_B", "time": "21/11/2026", "pose": {"t_mm": [0,0,0], "q_wxyz": [1,0,0,0]}}"#,
            "time",
        ),
        (
            r#"{"link": "C1_from_B", "time": "2500-01-01T00:00:00Z", "pose": {"t_mm": [0,0,0], "q_wxyz": [1,0,0,0]}}"#,
            "time",
        ),
        (
            r#"{"link": "C1_from_B", "time": 1e30, "pose": {"t_mm": [0,0,0], "q_wxyz": [1,0,0,0]}}"#,
            "time",
        ),
        (
            r#"{"link": "C1_from_B", "time": "2026-11-21T10:00:01Z", "pose": {"t_mm": [0,0,0], "q_wxyz": [1,0,0,0]}, "sigma": {"rotation_arcsec": -1, "translation_mm": 0.1}}"#,
            "sigma.rotation_arcsec",
        ),
        (
            r#"{"link": "C1_from_B", "time": "2026-11-21T10:00:01Z", "pose": {"t_mm": [0,0,0], "q_wxyz": [1,0,0,0]}, "covariance": [1, 2, 3]}"#,
            "covariance",
        ),
    ];
    for (bad, field) in cases {
        expect_refused(
            &app,
            json_ct,
            &batch_with(bad),
            unprocessable,
            Some(1),
            field,
        )
        .await;
    }
    // A duplicate inside the batch.
    expect_refused(
        &app,
        json_ct,
        &batch_with(GOOD),
        unprocessable,
        Some(1),
        "time",
    )
    .await;
    // Every problem of every item is listed.
    let answer = expect_refused(
        &app,
        json_ct,
        &format!(
            r#"{{"samples": [{}, {GOOD}, {}]}}"#,
            r#"{"link": "C9_from_B", "time": "x", "pose": {"t_mm": [0,0,0], "q_wxyz": [1,0,0,0]}}"#,
            r#"{"link": "C1_from_B", "time": "2026-11-21T10:00:02Z", "pose": {"t_mm": [0,0,0], "q_wxyz": [2,0,0,0]}}"#
        ),
        unprocessable,
        Some(2),
        "pose.q_wxyz",
    )
    .await;
    assert_eq!(
        answer["error"]["details"].as_array().unwrap().len(),
        3,
        "{answer}"
    );
    // NDJSON: the bad line is named by its index.
    let ndjson = format!("{GOOD}\n{}\n", with_t1("NaN"));
    expect_refused(
        &app,
        "application/x-ndjson",
        &ndjson,
        unprocessable,
        Some(1),
        "pose.t_mm[1]",
    )
    .await;
    // Too large: the body, and the batch.
    let big = format!(r#"{{"samples": [{}]}}"#, vec![GOOD; 400].join(","));
    expect_refused(&app, json_ct, &big, StatusCode::PAYLOAD_TOO_LARGE, None, "").await;
    let many: Vec<String> = (0..60)
        .map(|k| format!(r#"{{"link": "C1_from_B", "time": {}, "pose": {{"t_mm": [0,0,0], "q_wxyz": [1,0,0,0]}}}}"#, k))
        .collect();
    expect_refused(
        &app,
        json_ct,
        &format!(r#"{{"samples": [{}]}}"#, many.join(",")),
        StatusCode::PAYLOAD_TOO_LARGE,
        None,
        "",
    )
    .await;

    let after = store_state(&app).await;
    assert_eq!(before, after, "a refused request changed the store");
}

#[tokio::test]
async fn ndjson_batches_are_ingested_like_json_ones() {
    let app = seeded().await;
    let lines: Vec<String> = ["C1_from_B", "C2_from_M", "C3_from_G"]
        .iter()
        .map(|l| json!({"link": l, "time": time_text(5), "pose": {"t_mm": [0.0, 0.0, 3000.0], "q_wxyz": [0, 1, 0, 0]}}).to_string())
        .collect();
    let (status, body) = app
        .post_text("/api/v1/samples", "application/x-ndjson", &lines.join("\n"))
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["stored"], 3);
    assert_eq!(body["raw_results"], 1);
}
