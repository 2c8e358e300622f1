//! Alarms through the service: a deformation ramp stores exactly its transitions.

use super::helpers::{Backend, T0_NS, TestApp, alarms_after_turns, turned_sample};
use axum::http::StatusCode;
use serde_json::json;

on_both_backends!(
    a_deformation_ramp_stores_exactly_its_transitions,
    an_alarm_is_acknowledged_once_with_who_when_and_a_note,
);

const ONE_LINK: &str = r#"
[[links]]
name = "G_from_B"
kind = "measured"
sigma = { rotation_arcsec = 5.0, translation_mm = 0.05 }
expected_rate_hz = 25.0
random_walk = { rotation_arcsec_per_sqrt_s = 20.0, translation_mm_per_sqrt_s = 0.1 }

[[targets]]
name = "G"
base = "B"
[targets.alarms]
warn_rotation_arcsec = 60.0
alarm_rotation_arcsec = 120.0
hysteresis = 0.1
dwell_s = 1.0
"#;

async fn a_deformation_ramp_stores_exactly_its_transitions(backend: Backend) {
    let app = TestApp::start_on(backend, Some(ONE_LINK)).await;
    app.set_straight_reference().await;
    // Rotation about x: up to 150 arcsec at 5 arcsec/s, 10 s there, back down; 25 Hz.
    let mut samples = Vec::new();
    for k in 0..(70 * 25) {
        let t = k as f64 / 25.0;
        let v: f64 = if t < 30.0 {
            t * 5.0
        } else if t < 40.0 {
            150.0
        } else {
            (150.0 - (t - 40.0) * 5.0).max(0.0)
        };
        samples.push(turned_sample(T0_NS + k * 40_000_000, v));
    }
    for chunk in samples.chunks(250) {
        let (status, body) = app
            .post_live("/api/v1/samples", &json!({"samples": chunk}))
            .await;
        assert_eq!(status, StatusCode::OK, "{body}");
    }
    let (status, list) = app.get("/api/v1/alarms?target=G").await;
    assert_eq!(status, StatusCode::OK);
    let steps: Vec<(String, String, String)> = list["alarms"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| {
            (
                a["kind"].as_str().unwrap().into(),
                a["from"].as_str().unwrap().into(),
                a["to"].as_str().unwrap().into(),
            )
        })
        .collect();
    let expected = [
        ("none", "warn"),
        ("warn", "alarm"),
        ("alarm", "warn"),
        ("warn", "none"),
    ]
    .map(|(f, t)| ("deformation".to_owned(), f.to_owned(), t.to_owned()));
    assert_eq!(steps, expected);
    // Newest first, with a limit: the latest two, in reverse order.
    let (status, latest) = app.get("/api/v1/alarms?target=G&order=desc&limit=2").await;
    assert_eq!(status, StatusCode::OK);
    let latest = latest["alarms"].as_array().unwrap();
    let all = list["alarms"].as_array().unwrap();
    assert_eq!(latest.len(), 2);
    assert_eq!(latest[0], all[3]);
    assert_eq!(latest[1], all[2]);
    let (status, body) = app.get("/api/v1/alarms?order=newest").await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    assert!(body["error"].to_string().contains("order"), "{body}");
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(c["alarm"], "none");
    // The level survives a restart: the next ramp starts from where the last one ended.
    let app = app.restart(Some(ONE_LINK)).await;
    let (_, again) = app.get("/api/v1/alarms").await;
    assert_eq!(again["alarms"].as_array().unwrap().len(), 4);
}

/// A deformation alarm raised by the translation reports the translation, in mm, over HTTP
/// (the rotation, far under its threshold, used to be reported whatever decided).
#[tokio::test]
async fn an_alarm_decided_by_translation_reports_millimetres() {
    let config = ONE_LINK.replace(
        "hysteresis = 0.1",
        "warn_translation_mm = 1.0\nalarm_translation_mm = 2.0\nhysteresis = 0.1",
    );
    let app = TestApp::start(Some(&config)).await;
    app.set_straight_reference().await;
    // 1.5 mm along x for 5 s, no rotation.
    let samples: Vec<_> = (0..125)
        .map(|k| {
            json!({"link": "G_from_B", "time": T0_NS + k * 40_000_000,
                   "pose": {"t_mm": [1.5, 0, 3000], "q_wxyz": [1, 0, 0, 0]}})
        })
        .collect();
    let (status, body) = app
        .post_json("/api/v1/samples", &json!({"samples": samples}))
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let (_, list) = app.get("/api/v1/alarms?target=G").await;
    let first = &list["alarms"][0];
    assert_eq!(first["to"], "warn", "{list}");
    assert_eq!(first["unit"], "mm", "{list}");
    let value = first["value"].as_f64().unwrap();
    assert!((1.0..2.0).contains(&value), "{list}");
}

/// Alarms carry ids; an acknowledgement (admin) records who, when and a note, is shown with
/// the alarm, accepts its own retry, refuses a different second one and a return to `none`,
/// and survives a restart; the migration gave older rows ids too.
async fn an_alarm_is_acknowledged_once_with_who_when_and_a_note(backend: Backend) {
    let config = ONE_LINK.replace("dwell_s = 1.0", "dwell_s = 0.0");
    let app = TestApp::start_on(backend, Some(&config)).await;
    app.set_straight_reference().await;
    let mut events = app.service.subscribe();
    // 200 arcsec about x for 2 s, then back to 0: up to `alarm` and back to `none`.
    let alarms = alarms_after_turns(&app, &[200.0, 200.0, 0.0, 0.0]).await;
    let raised = alarms.iter().find(|a| a["to"] == "alarm").expect("raised");
    let cleared = alarms.iter().find(|a| a["to"] == "none").expect("cleared");
    assert!(raised["acknowledged_by"].is_null() && raised["acknowledged_at"].is_null());
    let ids: Vec<i64> = alarms.iter().map(|a| a["id"].as_i64().unwrap()).collect();
    let mut unique = ids.clone();
    unique.dedup();
    assert_eq!(unique.len(), ids.len(), "ids are distinct: {ids:?}");
    // The live event carries the same id.
    let mut live_ids = Vec::new();
    while let Ok(e) = events.try_recv() {
        if let brokenray::service::LiveEvent::Alarm(a) = e {
            live_ids.push(a.id);
        }
    }
    assert_eq!(live_ids, ids);

    let id = raised["id"].as_i64().unwrap();
    let uri = format!("/api/v1/alarms/{id}/ack");
    let ack = json!({"by": "watch officer", "note": "hatch cover moved, checked"});
    let (status, a) = app.post_json(&uri, &ack).await;
    assert_eq!(status, StatusCode::OK, "{a}");
    assert_eq!(a["id"], id);
    assert_eq!(a["acknowledged_by"], "watch officer");
    assert_eq!(a["note"], "hatch cover moved, checked");
    assert_eq!(
        brokenray::clock::parse_rfc3339_ns(a["acknowledged_at"].as_str().unwrap()).unwrap(),
        app.service.now_ns(),
        "stamped with the server's clock"
    );
    // The same again (a retry) is fine; another is a conflict and changes nothing.
    let (status, again) = app.post_json(&uri, &ack).await;
    assert_eq!((status, &again), (StatusCode::OK, &a));
    let (status, body) = app.post_json(&uri, &json!({"by": "someone else"})).await;
    assert_eq!(status, StatusCode::CONFLICT, "{body}");
    assert!(body.to_string().contains("watch officer"), "{body}");
    // Nothing to acknowledge, nothing found, nothing said.
    let (status, body) = app
        .post_json(
            &format!("/api/v1/alarms/{}/ack", cleared["id"]),
            &json!({"by": "x"}),
        )
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    let (status, _) = app
        .post_json("/api/v1/alarms/999999/ack", &json!({"by": "x"}))
        .await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    for (body, field) in [
        (json!({"note": "who?"}), "by"),
        (json!({"by": "  "}), "by"),
        (json!({"by": "x".repeat(1001)}), "by"),
        // Text PostgreSQL cannot hold (a centre keeps a copy) never enters.
        (json!({"by": "a\u{0}b"}), "by"),
        (json!({"by": "x", "note": "\u{0}"}), "note"),
    ] {
        let (status, e) = app.post_json(&uri, &body).await;
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{e}");
        assert!(e["error"].to_string().contains(field), "{e}");
    }
    let (status, e) = app.post_json("/api/v1/alarms/abc/ack", &ack).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{e}");
    assert_eq!(e["error"]["details"][0]["field"], "id", "{e}");
    // Listed with the alarm, and kept across a restart.
    let app = app.restart(Some(&config)).await;
    let (_, list) = app.get("/api/v1/alarms?target=G").await;
    let shown = list["alarms"]
        .as_array()
        .unwrap()
        .iter()
        .find(|x| x["id"] == id)
        .unwrap()
        .clone();
    assert_eq!(shown, a);
}

/// A damaged alarm row (a level no version writes) refuses the acknowledgement of that alarm
/// alone, as a failure of the service (500, its detail logged, not told) rather than as a
/// storage outage to retry; another alarm is acknowledged in the same breath.
#[tokio::test]
async fn a_damaged_alarm_row_refuses_its_own_acknowledgement_alone() {
    let config = ONE_LINK.replace("dwell_s = 1.0", "dwell_s = 0.0");
    let app = TestApp::start(Some(&config)).await;
    app.set_straight_reference().await;
    // Raised and cleared twice.
    let raised: Vec<i64> = alarms_after_turns(&app, &[200.0, 0.0, 200.0, 0.0])
        .await
        .iter()
        .filter(|a| a["to"] != "none")
        .map(|a| a["id"].as_i64().unwrap())
        .collect();
    assert!(raised.len() >= 2, "{raised:?}");
    let conn = rusqlite::Connection::open(&app.database).unwrap();
    conn.busy_timeout(std::time::Duration::from_secs(5))
        .unwrap();
    let changed = conn
        .execute(
            "update alarms set to_level = 'purple' where alarm_id = ?1",
            [raised[0]],
        )
        .unwrap();
    assert_eq!(changed, 1);
    drop(conn);
    let ack = json!({"by": "watch officer"});
    let (status, body) = app
        .post_json(&format!("/api/v1/alarms/{}/ack", raised[0]), &ack)
        .await;
    assert_eq!(status, StatusCode::INTERNAL_SERVER_ERROR, "{body}");
    assert_eq!(body["error"]["code"], "internal");
    assert!(
        !body.to_string().contains("purple"),
        "the detail is logged, not told: {body}"
    );
    let (status, body) = app
        .post_json(&format!("/api/v1/alarms/{}/ack", raised[1]), &ack)
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["acknowledged_by"], "watch officer");
}
