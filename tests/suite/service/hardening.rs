//! Input that is wrong, absurd, hostile or late: refused with a JSON error naming the field,
//! never stored, never breaking what comes after.

use super::helpers::{T0_NS, TestApp, nominal_group, time_text};
use axum::http::StatusCode;
use serde_json::{Value, json};

fn sample(link: &str, time: Value, pose: Value) -> Value {
    json!({"samples": [{"link": link, "time": time, "pose": pose}]})
}

fn nominal_pose() -> Value {
    json!({"t_mm": [0.0, 0.0, 3000.0], "q_wxyz": [0, 1, 0, 0]})
}

/// The one detail of a refusal names `field`.
fn assert_field(body: &Value, field: &str) {
    let details = body["error"]["details"].as_array().expect("details");
    assert!(
        details.iter().any(|d| d["field"] == field),
        "no detail names `{field}`: {body}"
    );
}

#[tokio::test]
async fn a_time_ahead_of_the_server_clock_is_refused() {
    let app = TestApp::start(None).await;
    let ahead = app.service.now_ns() + 60_000_000_000;
    let (status, body) = app
        .post_json(
            "/api/v1/samples",
            &sample("C1_from_B", json!(ahead), nominal_pose()),
        )
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert_field(&body, "time");
    assert!(body.to_string().contains("in the future"), "{body}");
    // Observations too.
    let (status, body) = app
        .post_json(
            "/api/v1/observations",
            &json!({"observations": [{"camera": "C1", "marker": "B", "time": ahead,
                    "points_px": [[600.0, 500.0], [700.0, 500.0], [600.0, 600.0], [700.0, 600.0]]}]}),
        )
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert_field(&body, "time");
    // The far past too: a clock never set, or the earliest time there is (whose buckets would
    // wrap around to the year 2262).
    for past in [json!(i64::MIN), json!(0), json!("1999-12-31T23:59:59Z")] {
        let (status, body) = app
            .post_json(
                "/api/v1/samples",
                &sample("C1_from_B", past.clone(), nominal_pose()),
            )
            .await;
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{past}: {body}");
        assert_field(&body, "time");
        assert!(body.to_string().contains("before 2000"), "{body}");
    }
    // Within `max_future_s` (5 s by default) is accepted: clocks are never exactly equal.
    let (status, body) = app
        .post_json(
            "/api/v1/samples",
            &sample(
                "C1_from_B",
                json!(app.service.now_ns() + 2_000_000_000),
                nominal_pose(),
            ),
        )
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
}

#[tokio::test]
async fn absurd_finite_values_are_refused_by_name_and_nothing_breaks() {
    let app = TestApp::start(None).await;
    let cases = [
        (
            sample(
                "C1_from_B",
                json!(T0_NS),
                json!({"t_mm": [1e150, 0.0, 3000.0], "q_wxyz": [0, 1, 0, 0]}),
            ),
            "pose.t_mm",
        ),
        (
            sample(
                "C1_from_B",
                json!(T0_NS),
                json!({"t_mm": [0.0, 0.0, 3000.0], "euler_deg": [1e300, 0.0, 0.0]}),
            ),
            "pose.euler_deg",
        ),
        (
            json!({"samples": [{"link": "C1_from_B", "time": T0_NS, "pose": nominal_pose(),
                    "sigma": {"rotation_arcsec": 1e12, "translation_mm": 0.1}}]}),
            "sigma.rotation_arcsec[0]",
        ),
        (
            json!({"samples": [{"link": "C1_from_B", "time": T0_NS, "pose": nominal_pose(),
                    "covariance": (0..36).map(|i| if i % 7 == 0 { 1e30 } else { 0.0 }).collect::<Vec<f64>>()}]}),
            "covariance[0]",
        ),
    ];
    for (body, field) in cases {
        let (status, answer) = app.post_json("/api/v1/samples", &body).await;
        assert_eq!(
            status,
            StatusCode::UNPROCESSABLE_ENTITY,
            "{field}: {answer}"
        );
        let text = answer.to_string();
        assert!(text.contains(field), "{field} not named: {answer}");
    }
    let (status, answer) = app
        .request(
            "PUT",
            "/api/v1/links/C2_from_C1/calibration",
            Some((
                "application/json",
                json!({"pose": {"t_mm": [1e308, 0.0, 0.0], "euler_deg": [0.0, 180.0, 0.0]},
                       "sigma": {"rotation_arcsec": 5.0, "translation_mm": 0.05}})
                .to_string(),
            )),
            None,
        )
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{answer}");
    assert!(answer.to_string().contains("pose.t_mm"), "{answer}");
    let (status, answer) = app
        .post_json(
            "/api/v1/targets/G/reference",
            &json!({"pose": {"t_mm": [1e300, 0.0, 0.0], "q_wxyz": [1, 0, 0, 0]}}),
        )
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{answer}");
    assert!(answer.to_string().contains("pose.t_mm"), "{answer}");
    // Nothing was stored, and the service takes good data as before.
    let (_, links) = app.get("/api/v1/links/C1_from_B/samples").await;
    assert_eq!(
        links["samples"].as_array().map(Vec::len),
        Some(0),
        "{links}"
    );
    for k in 0..5 {
        let (status, body) = app.post_json("/api/v1/samples", &nominal_group(k)).await;
        assert_eq!(status, StatusCode::OK, "{body}");
    }
    let (_, calibrations) = app.get("/api/v1/links/C2_from_C1/calibrations").await;
    assert!(
        !calibrations.to_string().contains("1e308"),
        "{calibrations}"
    );
}

#[tokio::test]
async fn a_body_of_junk_gets_a_short_answer_listing_the_first_hundred_problems() {
    let app = TestApp::start(None).await;
    let n = 200_000;
    let items = vec!["{\"link\": 1}"; n].join(",");
    let body = format!("{{\"samples\": [{items}]}}");
    let (status, answer) = app
        .post_text("/api/v1/samples", "application/json", &body)
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    let details = answer["error"]["details"].as_array().expect("details");
    assert_eq!(details.len(), 100);
    assert_eq!(answer["error"]["details_omitted"], n - 100);
    assert!(
        answer["error"]["message"]
            .as_str()
            .unwrap()
            .contains(&n.to_string()),
        "{}",
        answer["error"]["message"]
    );
    assert!(answer.to_string().len() < 50_000, "the answer is small");
    // The same as NDJSON.
    let lines = vec!["{\"link\": 1}"; n].join("\n");
    let (status, answer) = app
        .post_text("/api/v1/samples", "application/x-ndjson", &lines)
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    assert_eq!(answer["error"]["details"].as_array().unwrap().len(), 100);
    assert_eq!(answer["error"]["details_omitted"], n - 100);
    // A message quoting a huge value is cut.
    let big = format!(
        "{{\"samples\": [{{\"link\": \"C1_from_B\", \"time\": {T0_NS}, \"pose\": {}, \
         \"sigma\": {{\"rotation_arcsec\": {{\"x\": \"{}\"}}, \"translation_mm\": 1}}}}]}}",
        nominal_pose(),
        "a".repeat(100_000)
    );
    let (status, answer) = app
        .post_text("/api/v1/samples", "application/json", &big)
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{answer}");
    assert!(
        answer.to_string().len() < 5_000,
        "{}",
        answer.to_string().len()
    );
}

#[tokio::test]
async fn retention_counts_back_from_the_server_clock_not_from_a_future_result() {
    let app = TestApp::start(Some(&format!(
        "[server]\ndatabase = \"brokenray.db\"\nmax_future_s = 1000000\n[retention]\nsamples_days = 1\nresults_days = 1\n{}",
        brokenray::config::DEFAULT_INSTALLATION_TOML
            .split_once("[rerun]")
            .map(|(_, rest)| format!("[rerun]{rest}"))
            .unwrap()
    )))
    .await;
    let real_start = app.service.now_ns() - 3_600_000_000_000;
    let group = |t: i64| {
        let samples: Vec<Value> = ["C1_from_B", "C2_from_M", "C3_from_G"]
            .iter()
            .map(|l| json!({"link": l, "time": t, "pose": nominal_pose()}))
            .collect();
        json!({ "samples": samples })
    };
    for k in 0..20 {
        let (status, body) = app
            .post_json("/api/v1/samples", &group(real_start + k * 40_000_000))
            .await;
        assert_eq!(status, StatusCode::OK, "{body}");
    }
    // One group ten days ahead (a wrong clock, inside this installation's generous limit).
    let (status, body) = app
        .post_json(
            "/api/v1/samples",
            &group(app.service.now_ns() + 10 * 86_400_000_000_000),
        )
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let (samples, _) = app.service.prune().await.expect("prune");
    assert_eq!(samples, 0, "real samples an hour old were pruned");
    let (_, stored) = app.get("/api/v1/links/C1_from_B/samples").await;
    assert_eq!(stored["samples"].as_array().unwrap().len(), 21);
}

#[tokio::test]
async fn a_backfilled_group_gets_its_raw_result() {
    let app = TestApp::start(None).await;
    // Live data first, far more groups than are assembled in memory.
    for k in 1000..1200 {
        let (status, body) = app.post_live("/api/v1/samples", &nominal_group(k)).await;
        assert_eq!(status, StatusCode::OK, "{body}");
    }
    // Then the buffer of an outage: each link's samples in its own request, oldest last.
    for k in (0..10).rev() {
        let group = nominal_group(k);
        for s in group["samples"].as_array().unwrap() {
            let (status, body) = app
                .post_json("/api/v1/samples", &json!({"samples": [s]}))
                .await;
            assert_eq!(status, StatusCode::OK, "{body}");
        }
    }
    let (status, stats) = app
        .get(&format!(
            "/api/v1/targets/G/stats?source=raw&from={}&to={}",
            time_text(0),
            time_text(9)
        ))
        .await;
    assert_eq!(status, StatusCode::OK, "{stats}");
    assert_eq!(stats["count"], 10, "{stats}");
    // Once each: a retry of the whole backfill adds nothing.
    for k in 0..10 {
        let (status, body) = app.post_json("/api/v1/samples", &nominal_group(k)).await;
        assert_eq!(status, StatusCode::OK, "{body}");
        assert_eq!(body["duplicates"], 3, "{body}");
    }
    let (_, history) = app
        .get(&format!(
            "/api/v1/targets/G/history?source=raw&from={}&to={}&max_points=10",
            time_text(0),
            time_text(9)
        ))
        .await;
    let total: i64 = history["count"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c.as_i64().unwrap())
        .sum();
    assert_eq!(total, 10, "{history}");
}

#[tokio::test]
async fn history_from_the_beginning_of_time_does_not_overflow() {
    let app = TestApp::start(None).await;
    for k in 0..50 {
        app.post_json("/api/v1/samples", &nominal_group(k)).await;
    }
    for max_points in [10, 100_000] {
        let (status, history) = app
            .get(&format!(
                "/api/v1/targets/G/history?from={}&to={}&max_points={max_points}",
                i64::MIN + 1,
                T0_NS + 10_000_000_000
            ))
            .await;
        assert_eq!(status, StatusCode::OK, "{history}");
        let total: i64 = history["count"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c.as_i64().unwrap())
            .sum();
        assert!(total >= 45, "max_points {max_points}: {history}");
    }
}

/// A request with the given headers through the router.
async fn send(
    app: &TestApp,
    method: &str,
    uri: &str,
    headers: &[(&str, &str)],
    body: &str,
) -> (StatusCode, Value) {
    app.request_with_headers(method, uri, headers, body.to_owned())
        .await
}

#[tokio::test]
async fn without_tokens_only_local_json_requests_are_served() {
    let app = TestApp::start(None).await;
    let group = nominal_group(0).to_string();
    // A form posted by a foreign page: text/plain needs no preflight.
    let (status, body) = send(
        &app,
        "POST",
        "/api/v1/samples",
        &[("content-type", "text/plain"), ("host", "127.0.0.1:7878")],
        &group,
    )
    .await;
    assert_eq!(status, StatusCode::UNSUPPORTED_MEDIA_TYPE, "{body}");
    assert_eq!(body["error"]["code"], "unsupported_media_type");
    let length = group.len().to_string();
    let (status, body) = send(
        &app,
        "POST",
        "/api/v1/samples",
        &[("host", "127.0.0.1:7878"), ("content-length", &length)],
        &group,
    )
    .await;
    assert_eq!(status, StatusCode::UNSUPPORTED_MEDIA_TYPE, "{body}");
    // A foreign origin.
    let (status, body) = send(
        &app,
        "POST",
        "/api/v1/samples",
        &[
            ("content-type", "application/json"),
            ("host", "127.0.0.1:7878"),
            ("origin", "https://evil.example"),
        ],
        &group,
    )
    .await;
    assert_eq!(status, StatusCode::FORBIDDEN, "{body}");
    assert_eq!(body["error"]["code"], "origin_not_allowed");
    // DNS rebinding: a foreign name resolving to loopback.
    let (status, body) = send(
        &app,
        "GET",
        "/api/v1/targets",
        &[("host", "evil.example:7878")],
        "",
    )
    .await;
    assert_eq!(status, StatusCode::FORBIDDEN, "{body}");
    assert_eq!(body["error"]["code"], "host_not_allowed");
    // The service's own page, and plain local clients, are served.
    let (status, body) = send(
        &app,
        "POST",
        "/api/v1/samples",
        &[
            ("content-type", "application/json; charset=utf-8"),
            ("host", "localhost:7878"),
            ("origin", "http://localhost:7878"),
        ],
        &group,
    )
    .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let (status, _) = send(
        &app,
        "GET",
        "/api/v1/targets",
        &[("host", "[::1]:7878")],
        "",
    )
    .await;
    assert_eq!(status, StatusCode::OK);
    let (status, _) = send(&app, "GET", "/healthz", &[("host", "127.0.0.1:7878")], "").await;
    assert_eq!(status, StatusCode::OK);
}

#[tokio::test]
async fn configured_names_are_served_without_tokens() {
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML.replace(
        "[server]",
        "[server]\nallowed_hosts = [\"bridge.ship.local\"]",
    );
    let app = TestApp::start(Some(&text)).await;
    for (host, expected) in [
        ("bridge.ship.local:7878", StatusCode::OK),
        ("other.ship.local:7878", StatusCode::FORBIDDEN),
    ] {
        let (status, body) = send(&app, "GET", "/api/v1/targets", &[("host", host)], "").await;
        assert_eq!(status, expected, "{host}: {body}");
    }
}

#[tokio::test]
async fn the_bearer_scheme_is_case_insensitive_and_tokens_need_a_scope() {
    let hash = brokenray::config::sha256_hex("s3cret");
    let text = format!(
        "{}\n[[auth.tokens]]\nname = \"ops\"\nsha256 = \"{hash}\"\nscopes = [\"read\"]\n",
        brokenray::config::DEFAULT_INSTALLATION_TOML
    );
    let app = TestApp::start(Some(&text)).await;
    for scheme in ["Bearer", "bearer", "BEARER"] {
        let (status, body) = send(
            &app,
            "GET",
            "/api/v1/targets",
            &[("authorization", &format!("{scheme} s3cret"))],
            "",
        )
        .await;
        assert_eq!(status, StatusCode::OK, "{scheme}: {body}");
    }
    let no_scopes = format!(
        "{}\n[[auth.tokens]]\nname = \"nothing\"\nsha256 = \"{hash}\"\nscopes = []\n",
        brokenray::config::DEFAULT_INSTALLATION_TOML
    );
    let err = brokenray::config::parse("scopes.toml", &no_scopes).expect_err("refused");
    assert!(err.to_string().contains("no scopes"), "{err}");
}

#[tokio::test]
async fn every_refusal_speaks_the_error_envelope() {
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML
        .replace("[server]", "[server]\nmax_body_bytes = 4096");
    let app = TestApp::start(Some(&text)).await;
    // A query string that does not parse names its field.
    let (status, body) = app.get("/api/v1/alarms?limit=abc").await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert_eq!(body["error"]["code"], "invalid_request", "{body}");
    assert_field(&body, "limit");
    // A method the path does not take.
    let (status, body) = app.request("DELETE", "/api/v1/targets", None, None).await;
    assert_eq!(status, StatusCode::METHOD_NOT_ALLOWED);
    assert_eq!(body["error"]["code"], "method_not_allowed", "{body}");
    // Every write honours max_body_bytes, with the envelope.
    let big = json!({"pose": {"t_mm": [0.0, 0.0, 0.0], "q_wxyz": [1, 0, 0, 0]},
                     "note": "x".repeat(10_000)})
    .to_string();
    for (method, uri) in [
        ("POST", "/api/v1/targets/G/reference"),
        ("PUT", "/api/v1/links/C2_from_C1/calibration"),
        ("POST", "/api/v1/samples"),
    ] {
        let (status, body) = app
            .request(method, uri, Some(("application/json", big.clone())), None)
            .await;
        assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE, "{uri}: {body}");
        assert!(body["error"]["code"].is_string(), "{uri}: {body}");
    }
}

#[tokio::test]
async fn a_target_without_results_has_no_age() {
    let app = TestApp::start(None).await;
    let (status, body) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["status"], "initializing", "{body}");
    assert!(body["age_s"].is_null(), "age before any result: {body}");
    assert!(body["time"].is_null(), "{body}");
}

/// One sample stamped an hour ahead (a wrong clock, inside a generous `max_future_s`) makes
/// every correct sample of its link out of order; a reset of that link's filter recovers it
/// from the next sample, is recorded and listed with the link, and survives a restart.
#[tokio::test]
async fn a_link_reset_recovers_from_a_sample_stamped_ahead() {
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML
        .replace("[server]", "[server]\nmax_future_s = 1000000");
    let app = TestApp::start(Some(&text)).await;
    let start = app.service.now_ns() - 60_000_000_000;
    let group = |k: i64| {
        let samples: Vec<Value> = ["C1_from_B", "C2_from_M", "C3_from_G"]
            .iter()
            .map(|l| json!({"link": l, "time": start + k * 40_000_000, "pose": nominal_pose()}))
            .collect();
        json!({ "samples": samples })
    };
    for k in 0..20 {
        let (status, body) = app.post_json("/api/v1/samples", &group(k)).await;
        assert_eq!(status, StatusCode::OK, "{body}");
    }
    let ahead = app.service.now_ns() + 3_600_000_000_000;
    let (status, body) = app
        .post_json(
            "/api/v1/samples",
            &sample("C1_from_B", json!(ahead), nominal_pose()),
        )
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let (_, body) = app.post_json("/api/v1/samples", &group(20)).await;
    assert_eq!(
        body["out_of_order"], 1,
        "the correct sample is refused by the filter: {body}"
    );
    let (_, stuck) = app.get("/api/v1/targets/G/compensation").await;

    // Only measured links have a filter; unknown links are not found.
    let (status, _) = app
        .request("POST", "/api/v1/links/C2_from_C1/reset", None, None)
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    let (status, _) = app
        .request("POST", "/api/v1/links/X_from_Y/reset", None, None)
        .await;
    assert_eq!(status, StatusCode::NOT_FOUND);

    let (status, reset) = app
        .post_json(
            "/api/v1/links/C1_from_B/reset",
            &json!({"by": "operator", "note": "camera clock was an hour ahead"}),
        )
        .await;
    assert_eq!(status, StatusCode::OK, "{reset}");
    assert_eq!(reset["link"], "C1_from_B");
    for k in 21..40 {
        let (status, body) = app.post_json("/api/v1/samples", &group(k)).await;
        assert_eq!(status, StatusCode::OK, "{body}");
        assert_eq!(body["out_of_order"], 0, "group {k} after the reset: {body}");
    }
    let (_, live) = app.get("/api/v1/targets/G/compensation").await;
    assert_ne!(live["time"], stuck["time"], "{live}");
    assert_eq!(
        brokenray::clock::parse_rfc3339_ns(live["time"].as_str().unwrap()).unwrap(),
        start + 39 * 40_000_000,
        "{live}"
    );
    let (_, links) = app.get("/api/v1/links").await;
    let c1 = links
        .as_array()
        .unwrap()
        .iter()
        .find(|l| l["name"] == "C1_from_B")
        .unwrap();
    assert_eq!(c1["last_reset"]["by"], "operator", "{c1}");
    assert_eq!(c1["last_reset"]["note"], "camera clock was an hour ahead");
    // The reset state was committed with the filters: a restart continues from it.
    let app = app.restart(Some(&text)).await;
    let (status, body) = app.post_json("/api/v1/samples", &group(40)).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["out_of_order"], 0, "{body}");
    let (_, links) = app.get("/api/v1/links").await;
    assert!(links.to_string().contains("camera clock was an hour ahead"));
}

/// A name of 60 KB in a request is not echoed back whole: an error's message is cut to a
/// thousand characters (and a detail's to three hundred).
#[tokio::test]
async fn a_long_name_is_not_echoed_whole() {
    let app = TestApp::start(None).await;
    let name = "G".repeat(60_000);
    let (status, body) = app
        .get(&format!("/api/v1/targets/{name}/compensation"))
        .await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{body}");
    let message = body["error"]["message"].as_str().unwrap();
    assert!(
        message.chars().count() <= 1003,
        "{} characters",
        message.len()
    );
    assert!(message.ends_with("..."), "said to be cut");
}
