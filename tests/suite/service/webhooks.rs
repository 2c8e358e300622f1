//! Alarm notifications received by a real HTTP server on a local port: the body is the alarm as
//! `GET /api/v1/alarms` shows it, the signature checks out with the secret, `min_level` filters,
//! a failing receiver is retried, a refusing one is given up, and all of it is counted.

use super::helpers::{T0_NS, TestApp, alarmed_installation, alarms_after_turns, turned_sample};
use axum::http::{HeaderMap, StatusCode};
use hmac::Mac as _;
use serde_json::{Value, json};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// One request received: path, signature header, alarm id header, body.
type Call = (String, String, String, Vec<u8>);

#[derive(Clone, Default)]
struct Received {
    calls: Arc<Mutex<Vec<Call>>>,
}

impl Received {
    fn of(&self, path: &str) -> Vec<(String, String, Vec<u8>)> {
        self.calls
            .lock()
            .unwrap()
            .iter()
            .filter(|c| c.0 == path)
            .map(|c| (c.1.clone(), c.2.clone(), c.3.clone()))
            .collect()
    }
}

/// A receiver: `/all` and `/alarms` answer 200, `/flaky` answers 503 to its first call and 200
/// after, `/refuse` answers 400, `/moved` redirects to `/redirected`.
async fn receiver() -> (String, Received) {
    let got = Received::default();
    let record = got.clone();
    let app = axum::Router::new().fallback(
        move |uri: axum::http::Uri, headers: HeaderMap, body: axum::body::Bytes| {
            let record = record.clone();
            async move {
                let path = uri.path().to_owned();
                let header = |name: &str| {
                    headers
                        .get(name)
                        .and_then(|v| v.to_str().ok())
                        .unwrap_or_default()
                        .to_owned()
                };
                let mut calls = record.calls.lock().unwrap();
                let earlier = calls.iter().filter(|c| c.0 == path).count();
                calls.push((
                    path.clone(),
                    header("x-brokenray-signature"),
                    header("x-brokenray-alarm-id"),
                    body.to_vec(),
                ));
                use axum::response::IntoResponse as _;
                match path.as_str() {
                    "/flaky" if earlier == 0 => StatusCode::SERVICE_UNAVAILABLE.into_response(),
                    "/refuse" => StatusCode::BAD_REQUEST.into_response(),
                    // Elsewhere on this receiver: a redirect followed would show as a call.
                    "/moved" => (
                        StatusCode::TEMPORARY_REDIRECT,
                        [("location", "/redirected")],
                    )
                        .into_response(),
                    _ => StatusCode::NO_CONTENT.into_response(),
                }
            }
        },
    );
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let base = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });
    (base, got)
}

fn installation(base: &str) -> String {
    alarmed_installation(&format!(
        r#"
[[notify.webhooks]]
url = "{base}/all"
secret = "all-secret"

[[notify.webhooks]]
url = "{base}/alarms"
secret = "alarm-secret"
min_level = "alarm"

[[notify.webhooks]]
url = "{base}/flaky"
secret = "s"

[[notify.webhooks]]
url = "{base}/refuse"
secret = "s"
"#
    ))
}

fn hmac_hex(secret: &str, body: &[u8]) -> String {
    let mut mac = hmac::Hmac::<sha2::Sha256>::new_from_slice(secret.as_bytes()).unwrap();
    mac.update(body);
    hex::encode(mac.finalize().into_bytes())
}

/// Waits (at most 20 s) until `done` holds.
async fn until(mut done: impl FnMut() -> bool) {
    for _ in 0..2000 {
        if done() {
            return;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    panic!("not reached in 20 s");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn alarm_transitions_reach_webhooks_signed_filtered_and_retried() {
    let (base, got) = receiver().await;
    let app = TestApp::start(Some(&installation(&base))).await;
    app.set_straight_reference().await;
    // 80 arcsec (warn), back to 0, 200 arcsec (alarm), back to 0: four transitions.
    let alarms = alarms_after_turns(&app, &[80.0, 0.0, 200.0, 0.0]).await;
    let levels: Vec<(&str, &str)> = alarms
        .iter()
        .map(|a| (a["from"].as_str().unwrap(), a["to"].as_str().unwrap()))
        .collect();
    assert_eq!(
        levels,
        [
            ("none", "warn"),
            ("warn", "none"),
            ("none", "alarm"),
            ("alarm", "none")
        ]
    );

    // `warn`: all four, in order, each body the stored alarm, signed with its secret.
    until(|| got.of("/all").len() == 4).await;
    for ((signature, id, body), alarm) in got.of("/all").iter().zip(&alarms) {
        let sent: Value = serde_json::from_slice(body).unwrap();
        assert_eq!(&sent, alarm);
        assert_eq!(id, &alarm["id"].to_string());
        assert_eq!(
            signature,
            &format!("sha256={}", hmac_hex("all-secret", body))
        );
        assert_ne!(signature, &format!("sha256={}", hmac_hex("other", body)));
    }
    // `alarm`: only the two transitions to and from `alarm`.
    until(|| got.of("/alarms").len() == 2).await;
    let ids: Vec<String> = got.of("/alarms").into_iter().map(|c| c.1).collect();
    assert_eq!(
        ids,
        [alarms[2]["id"].to_string(), alarms[3]["id"].to_string()]
    );
    // Flaky: the first attempt fails (503), retried after a second, then every one arrives.
    until(|| got.of("/flaky").len() == 5).await;
    let flaky: Vec<String> = got.of("/flaky").into_iter().map(|c| c.1).collect();
    assert_eq!(flaky[0], flaky[1], "the failed delivery is retried first");
    // Refused (400): one attempt each, not retried.
    until(|| got.of("/refuse").len() == 4).await;

    // Every queue done (the counters follow the answers).
    let mut hooks = Value::Null;
    for _ in 0..2000 {
        hooks = app.get("/api/v1/webhooks").await.1;
        if hooks.as_array().unwrap().iter().all(|h| h["queued"] == 0) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let summary: Vec<(u64, u64, u64, bool)> = hooks
        .as_array()
        .unwrap()
        .iter()
        .map(|h| {
            (
                h["delivered"].as_u64().unwrap(),
                h["failed"].as_u64().unwrap(),
                h["attempts_failed"].as_u64().unwrap(),
                h["failing"].as_bool().unwrap(),
            )
        })
        .collect();
    assert_eq!(
        summary,
        [
            (4, 0, 0, false),
            (2, 0, 0, false),
            (4, 0, 1, false),
            (0, 4, 4, true)
        ],
        "{hooks}"
    );
    assert!(
        hooks[3]["last_error"].as_str().unwrap().contains("400"),
        "{hooks}"
    );
    assert_eq!(hooks[0]["host"], base.trim_start_matches("http://"));
    let (_, metrics) = app.get("/metrics").await;
    let metrics = metrics.as_str().unwrap();
    assert!(
        metrics.contains(&format!(
            "brokenray_webhook_deliveries_total{{webhook=\"3\",host=\"{}\",outcome=\"failed\"}} 4",
            base.trim_start_matches("http://")
        )),
        "{metrics}"
    );
    assert!(metrics.contains("brokenray_alarm_notifications_dropped_total 0"));
}

#[tokio::test]
async fn a_webhook_that_cannot_be_reached_is_given_up_after_its_attempts_and_said() {
    // A port nobody listens on.
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let text = installation("http://127.0.0.1:1")
        .split("[[notify.webhooks]]")
        .next()
        .unwrap()
        .to_owned()
        + &format!(
            "[[notify.webhooks]]\nurl = \"http://user:pw@127.0.0.1:{port}/hook?token=t\"\nsecret = \"s\"\nmax_attempts = 2\ntimeout_s = 2\n"
        );
    let app = TestApp::start(Some(&text)).await;
    app.set_straight_reference().await;
    let (status, _) = app
        .post_live(
            "/api/v1/samples",
            &json!({"samples": [turned_sample(T0_NS, 200.0)]}),
        )
        .await;
    assert_eq!(
        status,
        StatusCode::OK,
        "ingest does not wait for the webhook"
    );
    let mut hooks = Value::Null;
    for _ in 0..2000 {
        hooks = app.get("/api/v1/webhooks").await.1;
        if hooks[0]["failed"] == 1 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert_eq!(hooks[0]["failed"], 1, "{hooks}");
    assert_eq!(hooks[0]["attempts_failed"], 2, "{hooks}");
    assert_eq!(hooks[0]["failing"], true);
    // Neither the credentials nor the token are shown.
    assert_eq!(hooks[0]["host"], format!("127.0.0.1:{port}"));
    assert!(!hooks.to_string().contains("pw") && !hooks.to_string().contains("token=t"));
}

/// A webhook that answers with a redirect: not followed (the alarm never reaches the other
/// address), a failed delivery with the reason, not retried.
#[tokio::test]
async fn a_redirecting_webhook_is_a_failed_delivery_never_followed() {
    let (base, got) = receiver().await;
    let text = installation(&base)
        .split("[[notify.webhooks]]")
        .next()
        .unwrap()
        .to_owned()
        + &format!("[[notify.webhooks]]\nurl = \"{base}/moved\"\nsecret = \"s\"\n");
    let app = TestApp::start(Some(&text)).await;
    app.set_straight_reference().await;
    let (status, _) = app
        .post_live(
            "/api/v1/samples",
            &json!({"samples": [turned_sample(T0_NS, 200.0)]}),
        )
        .await;
    assert_eq!(status, StatusCode::OK);
    let mut hooks = Value::Null;
    for _ in 0..2000 {
        hooks = app.get("/api/v1/webhooks").await.1;
        if hooks[0]["failed"].as_u64() >= Some(1) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert!(hooks[0]["failed"].as_u64() >= Some(1), "{hooks}");
    assert_eq!(hooks[0]["delivered"], 0, "{hooks}");
    assert_eq!(
        hooks[0]["attempts_failed"], hooks[0]["failed"],
        "a redirect is not retried: {hooks}"
    );
    assert!(hooks.to_string().contains("redirect"), "{hooks}");
    assert!(!got.of("/moved").is_empty());
    assert!(
        got.of("/redirected").is_empty(),
        "the redirect was followed"
    );
}
