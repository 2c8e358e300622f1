//! Liveness on the server's clock: a feed that stops makes its target and links stale, the
//! stale alarm follows with its dwell and hysteresis (stored, sent live), and every surface
//! (compensation, links, metrics, health) says how old the data is. The clock is set by the
//! test, never slept on.

use super::helpers::{START_NS, T0_NS, TestApp, nominal_group};
use axum::http::StatusCode;
use brokenray::clock::Clock as _;
use brokenray::service::LiveEvent;
use serde_json::Value;

/// The built-in installation's links run at 25 Hz with `stale_after_periods = 5` (0.2 s), and
/// `[server] clock_tolerance_s` is 2 s: stale after 2.2 s without a sample.
const LIMIT_S: f64 = 2.2;

fn metric(text: &str, name_and_labels: &str) -> Option<f64> {
    text.lines()
        .find_map(|l| l.strip_prefix(name_and_labels)?.trim().parse().ok())
}

async fn metrics(app: &TestApp) -> String {
    let (status, body) = app.get("/metrics").await;
    assert_eq!(status, StatusCode::OK);
    body.as_str().expect("text").to_owned()
}

fn link<'a>(links: &'a Value, name: &str) -> &'a Value {
    links
        .as_array()
        .expect("links")
        .iter()
        .find(|l| l["name"] == name)
        .expect("link listed")
}

/// Posts groups `from..to` (40 ms apart) as a live feed.
async fn feed(app: &TestApp, from: i64, to: i64) {
    for k in from..to {
        let (status, body) = app.post_live("/api/v1/samples", &nominal_group(k)).await;
        assert_eq!(status, StatusCode::OK, "{body}");
    }
}

async fn alarms_of_kind(app: &TestApp, kind: &str) -> Vec<Value> {
    let (status, list) = app.get("/api/v1/alarms?target=G").await;
    assert_eq!(status, StatusCode::OK, "{list}");
    list["alarms"]
        .as_array()
        .expect("alarms")
        .iter()
        .filter(|a| a["kind"] == kind)
        .cloned()
        .collect()
}

#[tokio::test]
async fn a_feed_that_stops_goes_stale_everywhere_and_raises_then_clears_the_alarm() {
    let app = TestApp::start(None).await;
    let mut events = app.service.subscribe();
    // 6 s of a live feed: current.
    feed(&app, 0, 150).await;
    let last_ns = T0_NS + 149 * 40_000_000;
    assert_eq!(app.clock.now_ns(), last_ns);
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(c["status"], "ok", "{c}");
    assert_eq!(c["age_s"], 0.0, "{c}");
    assert_eq!(app.service.check_liveness().await.unwrap(), 0);

    // The feed stops. 2 s later (inside the limit) it is still current, its age counting.
    app.clock.advance_s(2.0);
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(c["status"], "ok", "{c}");
    assert!((c["age_s"].as_f64().unwrap() - 2.0).abs() < 1e-9, "{c}");
    assert_eq!(app.service.check_liveness().await.unwrap(), 0);

    // 20 s later: stale by the server's clock, everywhere.
    app.clock.set_ns(last_ns + 20_000_000_000);
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(c["status"], "stale", "{c}");
    assert!((c["age_s"].as_f64().unwrap() - 20.0).abs() < 1e-9, "{c}");
    assert!(c["pose"].is_object(), "the last value is still given: {c}");
    let (_, links) = app.get("/api/v1/links").await;
    for name in ["C1_from_B", "C2_from_M", "C3_from_G"] {
        let l = link(&links, name);
        assert_eq!(l["status"], "stale", "{l}");
        assert!((l["age_s"].as_f64().unwrap() - 20.0).abs() < 1e-9, "{l}");
    }
    assert_eq!(link(&links, "C2_from_C1")["status"], "calibrated");
    let m = metrics(&app).await;
    assert_eq!(
        metric(
            &m,
            "brokenray_target_age_seconds{target=\"G\",status=\"stale\"}"
        ),
        Some(20.0),
        "{m}"
    );
    assert_eq!(
        metric(&m, "brokenray_link_stale{link=\"C1_from_B\"}"),
        Some(1.0)
    );
    assert_eq!(
        metric(&m, "brokenray_link_age_seconds{link=\"C1_from_B\"}"),
        Some(20.0)
    );
    let (status, h) = app.get("/healthz").await;
    assert_eq!(
        status,
        StatusCode::OK,
        "stale data is not an unhealthy service: {h}"
    );
    assert_eq!(h["status"], "ok");
    assert_eq!(h["targets"]["G"]["status"], "stale", "{h}");
    assert_eq!(h["targets"]["G"]["age_s"], 20.0, "{h}");

    // The alarm: the first check starts the dwell (1 s), one after it raises the alarm.
    assert_eq!(app.service.check_liveness().await.unwrap(), 0);
    app.clock.advance_s(0.5);
    assert_eq!(app.service.check_liveness().await.unwrap(), 0);
    assert!(alarms_of_kind(&app, "stale").await.is_empty());
    app.clock.advance_s(0.5);
    assert_eq!(app.service.check_liveness().await.unwrap(), 1);
    let stale = alarms_of_kind(&app, "stale").await;
    assert_eq!(stale.len(), 1, "{stale:?}");
    assert_eq!(
        (&stale[0]["from"], &stale[0]["to"]),
        (&"none".into(), &"alarm".into())
    );
    assert_eq!(stale[0]["unit"], "s");
    assert!(
        (stale[0]["value"].as_f64().unwrap() - 21.0).abs() < 1e-9,
        "{}",
        stale[0]
    );
    assert!(
        stale[0]["message"].as_str().unwrap().contains("_from_"),
        "{}",
        stale[0]
    );
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(c["alarm"], "alarm", "{c}");
    // Sent live.
    let sent = loop {
        match events.try_recv() {
            Ok(LiveEvent::Alarm(a)) => break a.transition,
            Ok(_) => continue,
            Err(e) => panic!("no live alarm: {e:?}"),
        }
    };
    assert_eq!(sent.kind.name(), "stale");
    // Repeated checks add nothing.
    for _ in 0..5 {
        app.clock.advance_s(1.0);
        assert_eq!(app.service.check_liveness().await.unwrap(), 0);
    }

    // The feed resumes: current again at once, the alarm clears after the dwell.
    let resume = (app.clock.now_ns() - T0_NS) / 40_000_000;
    feed(&app, resume, resume + 25).await;
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(c["status"], "ok", "{c}");
    assert_eq!(app.service.check_liveness().await.unwrap(), 0);
    app.clock.advance_s(1.0);
    assert_eq!(app.service.check_liveness().await.unwrap(), 1);
    let stale = alarms_of_kind(&app, "stale").await;
    assert_eq!(stale.len(), 2, "{stale:?}");
    assert_eq!(
        (&stale[1]["from"], &stale[1]["to"]),
        (&"alarm".into(), &"none".into())
    );
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(c["alarm"], "none", "{c}");
}

#[tokio::test]
async fn the_clock_tolerance_covers_a_late_feed_and_no_further() {
    let app = TestApp::start(None).await;
    feed(&app, 0, 25).await;
    let last_ns = T0_NS + 24 * 40_000_000;
    // Just inside the limit plus the tolerance, then just past it.
    app.clock.set_ns(last_ns + ((LIMIT_S - 0.01) * 1e9) as i64);
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(c["status"], "ok", "{c}");
    app.clock.set_ns(last_ns + ((LIMIT_S + 0.01) * 1e9) as i64);
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(c["status"], "stale", "{c}");
    // A wider tolerance keeps it current.
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML
        .replace("[server]", "[server]\nclock_tolerance_s = 10");
    let app = app.restart(Some(&text)).await;
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(c["status"], "ok", "{c}");
}

#[tokio::test]
async fn a_service_restarted_long_after_its_feed_stopped_reads_stale_at_once() {
    let app = TestApp::start(None).await;
    feed(&app, 0, 25).await;
    app.clock.set_ns(START_NS + 3_600_000_000_000);
    let app = app.restart(None).await;
    let (_, h) = app.get("/healthz").await;
    assert_eq!(h["targets"]["G"]["status"], "stale", "{h}");
    assert!(
        h["targets"]["G"]["age_s"].as_f64().unwrap() > 3_590.0,
        "{h}"
    );
    let (_, links) = app.get("/api/v1/links").await;
    assert_eq!(link(&links, "C1_from_B")["status"], "stale", "{links}");
}

#[tokio::test]
async fn a_target_without_results_has_no_age_and_raises_no_stale_alarm() {
    let app = TestApp::start(None).await;
    app.clock.advance_s(3_600.0);
    let (_, h) = app.get("/healthz").await;
    assert_eq!(h["targets"]["G"]["status"], "initializing", "{h}");
    assert!(h["targets"]["G"]["age_s"].is_null(), "{h}");
    let (_, links) = app.get("/api/v1/links").await;
    assert_eq!(link(&links, "C1_from_B")["status"], "no_data");
    assert!(link(&links, "C1_from_B")["age_s"].is_null());
    app.clock.advance_s(10.0);
    assert_eq!(app.service.check_liveness().await.unwrap(), 0);
    assert!(metric(&metrics(&app).await, "brokenray_target_age_seconds").is_none());
}
