//! The acceptance procedure end to end through the API, the simulator playing the operator:
//! it keeps the target still, makes each stated move when the run asks, and says ready.

use super::helpers::{Backend, START_NS, TestApp};
use axum::body::Body;
use axum::http::StatusCode;
use brokenray::acceptance::Displacement;
use brokenray::clock::Clock as _;
use brokenray::feed::observation_items;
use brokenray::model::Model;
use brokenray::sim::{Scenario, SimSettings, Simulator};
use serde_json::{Value, json};
use statrs::distribution::{ChiSquared, ContinuousCDF};

fn simulator(model: &Model, seed: u64) -> Simulator {
    Simulator::new(
        model,
        SimSettings {
            scenario: Scenario::Static,
            rate_hz: 25.0,
            start_ns: START_NS - 1_000_000_000,
            duration_s: None,
            pixel_sigma_px: None,
            outlier_rate: 0.0,
            seed,
        },
    )
    .unwrap()
}

/// The displacement a planned step states.
fn stated(step: &Value) -> Displacement {
    serde_json::from_value(step["stated"].clone()).unwrap()
}

/// Runs one acceptance with `sim` as the operator; returns the finished run.
async fn accept(app: &TestApp, sim: &mut Simulator, by: &str) -> Value {
    let (status, run) = app
        .post_json(
            "/api/v1/acceptance/run",
            &json!({"by": by, "note": "simulated"}),
        )
        .await;
    assert_eq!(status, StatusCode::CREATED, "{run}");
    assert_eq!(run["phase"], "awaiting_operator", "{run}");
    for _ in 0..100_000 {
        let mut items = Vec::new();
        for _ in 0..5 {
            items.extend(observation_items(&sim.next_group()));
        }
        let (status, body) = app
            .post_live("/api/v1/observations", &json!({ "observations": items }))
            .await;
        assert_eq!(status, StatusCode::OK, "{body}");
        let (status, run) = app.get("/api/v1/acceptance/run").await;
        assert_eq!(status, StatusCode::OK, "{run}");
        match run["phase"].as_str().unwrap() {
            "measuring" => {}
            "finished" => {
                sim.displace_target("G", &Displacement::ZERO).unwrap();
                return run;
            }
            "awaiting_operator" => {
                let step = &run["steps"][run["step"].as_u64().unwrap() as usize];
                sim.displace_target("G", &stated(step)).unwrap();
                if run["step"] == 0 {
                    // The rig measures before the first step is placed.
                    let items = observation_items(&sim.next_group());
                    app.post_live("/api/v1/observations", &json!({ "observations": items }))
                        .await;
                }
                let (status, body) = app
                    .post_json("/api/v1/acceptance/run/ready", &json!({}))
                    .await;
                assert_eq!(status, StatusCode::OK, "{body}");
                assert_eq!(body["phase"], "measuring", "{body}");
            }
            other => panic!("phase {other}"),
        }
    }
    panic!("the acceptance did not finish");
}

/// The sum of the moves' NEES of a recorded acceptance, and how many moves.
fn moves_nees(acceptance: &Value) -> (f64, usize) {
    let steps = acceptance["record"]["steps"].as_array().unwrap();
    let moves: Vec<&Value> = steps.iter().filter(|s| s["kind"] == "move").collect();
    let sum = moves
        .iter()
        .map(|s| s["moved"]["nees"].as_f64().unwrap_or_else(|| panic!("{s}")))
        .sum();
    (sum, moves.len())
}

/// Ten acceptances of the built-in rig in the simulator pass, and their deviations are what
/// their uncertainties say: the moves' summed NEES lies in the chi-square band with 6
/// degrees of freedom a move, and the still windows' scatter under its repeatability bound.
#[tokio::test]
async fn ten_simulated_acceptances_pass_with_deviations_their_uncertainty_covers() {
    let app = TestApp::start_on(Backend::Sqlite, None).await;
    let model = app.service.installation().model.clone();
    let mut sim = simulator(&model, 11);
    let (mut sum, mut moves) = (0.0, 0);
    for k in 0..10 {
        let run = accept(&app, &mut sim, &format!("operator {k}")).await;
        let id = run["acceptance_id"].as_i64().unwrap();
        let (status, acceptance) = app.get(&format!("/api/v1/acceptance/{id}")).await;
        assert_eq!(status, StatusCode::OK);
        assert_eq!(run["passed"], true, "{run:#}");
        let (s, n) = moves_nees(&acceptance);
        sum += s;
        moves += n;
        let still = &acceptance["record"]["steps"][0]["still"][0];
        assert!(still["chi2"].as_f64().unwrap() <= still["threshold"].as_f64().unwrap());
        assert_eq!(acceptance["standing"], "valid");
    }
    let dof = 6.0 * moves as f64;
    eprintln!("ten acceptances: the moves' summed NEES {sum:.1} over {dof} degrees of freedom");
    let chi = ChiSquared::new(dof).unwrap();
    assert!(
        (chi.inverse_cdf(0.0005)..=chi.inverse_cdf(0.9995)).contains(&sum),
        "summed NEES {sum:.1} over {dof} degrees of freedom"
    );
    let (_, list) = app.get("/api/v1/acceptance").await;
    assert_eq!(list["acceptances"].as_array().unwrap().len(), 10);
    assert_eq!(list["standing"], "valid");
}

/// One camera's focal length wrong by 1 % in the world (the simulator's camera), the
/// service not told: the move along that camera's line of sight comes out 1 % long, beyond
/// its limit, and the acceptance fails naming that step; the lateral moves still pass.
#[tokio::test]
async fn a_focal_length_wrong_by_one_percent_fails_the_acceptance_naming_the_step() {
    let app = TestApp::start_on(Backend::Sqlite, None).await;
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML;
    let wrong = text.replacen("fx = 5370.0\nfy = 5370.0", "fx = 5423.7\nfy = 5423.7", 1);
    assert_ne!(
        wrong, text,
        "C3's focal length is where the test looks for it"
    );
    let world = brokenray::config::parse("world.toml", &wrong).unwrap();
    let mut sim = simulator(&world.model, 12);
    let run = accept(&app, &mut sim, "operator").await;
    assert_eq!(run["passed"], false, "{run:#}");
    let id = run["acceptance_id"].as_i64().unwrap();
    let (_, acceptance) = app.get(&format!("/api/v1/acceptance/{id}")).await;
    let failed: Vec<&str> = acceptance["failed"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_str().unwrap())
        .collect();
    assert!(failed.contains(&"z +100 mm"), "{failed:?}");
    assert!(
        !failed.contains(&"x +20 mm") && !failed.contains(&"still"),
        "{failed:?}"
    );
    let z = acceptance["record"]["steps"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == "z +100 mm")
        .unwrap();
    // 1 % of 100 mm along z, measured to its uncertainty.
    let dz = z["moved"]["deviation"][5].as_f64().unwrap();
    let u = z["moved"]["uncertainty"][5].as_f64().unwrap();
    eprintln!("z +100 mm with C3's focal length 1 % long: deviation {dz:.3} mm, u {u:.3} mm");
    assert!((dz.abs() - 1.0).abs() < 4.0 * u + 0.1, "{dz} +- {u}");
    assert_eq!(acceptance["standing"], "failed");
    let (_, health) = app.get("/healthz").await;
    let problem = health["acceptance_problem"].as_str().unwrap();
    assert!(
        problem.contains("failed") && problem.contains("z +100 mm"),
        "{problem}"
    );
}

/// The built-in installation with short windows and wide move limits: an acceptance that
/// passes in a few hundred groups, for the tests of where it stands.
fn short_installation() -> String {
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML
        .replace("still_s = 60\n", "still_s = 4\n")
        .replace("step_s = 20\n", "step_s = 2\n")
        .replace("move_arcsec = 40.0\n", "move_arcsec = 400.0\n")
        .replace("move_mm = 0.4\n", "move_mm = 4.0\n");
    assert!(text.contains("still_s = 4\n") && text.contains("move_mm = 4.0\n"));
    text
}

/// Where a recorded acceptance stands, through `GET /api/v1/acceptance` and `/healthz`:
/// none recorded, valid, due once its interval is over, no longer holding once a link it
/// accepted is calibrated again. The record survives a restart.
async fn an_acceptance_is_due_after_its_interval_and_void_after_a_calibration(backend: Backend) {
    let text = short_installation();
    let app = TestApp::start_on(backend, Some(&text)).await;
    let (_, health) = app.get("/healthz").await;
    assert!(
        health["acceptance_problem"]
            .as_str()
            .is_some_and(|p| p.contains("no acceptance")),
        "{health}"
    );
    let (status, list) = app.get("/api/v1/acceptance").await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(list["configured"], true);
    assert!(list.get("standing").is_none(), "{list}");
    let model = app.service.installation().model.clone();
    let mut sim = simulator(&model, 13);
    let run = accept(&app, &mut sim, "Ada").await;
    assert_eq!(run["passed"], true, "{run:#}");
    let id = run["acceptance_id"].as_i64().unwrap();
    let (_, health) = app.get("/healthz").await;
    assert!(health.get("acceptance_problem").is_none(), "{health}");
    let app = app.restart(Some(&text)).await;
    let (status, one) = app.get(&format!("/api/v1/acceptance/{id}")).await;
    assert_eq!(status, StatusCode::OK, "{one}");
    assert_eq!(one["by"], "Ada");
    assert_eq!(one["note"], "simulated");
    assert_eq!(one["standing"], "valid");
    assert_eq!(one["record"]["steps"].as_array().unwrap().len(), 6);
    assert!(
        one["record"]["targets"][0]["calibration_stamp"].is_i64(),
        "{one}"
    );
    // The period's report holds it, where it stands and each step.
    let (status, _, page) = app
        .request_raw("GET", "/api/v1/report", &[], Body::empty())
        .await;
    assert_eq!(status, StatusCode::OK);
    let page = String::from_utf8(page.to_vec()).unwrap();
    assert!(
        page.contains("data-standing=\"valid\">Acceptance 1 by Ada"),
        "{page}"
    );
    let section = &page[page.find("<h2>Acceptance</h2>").unwrap()..];
    let section = &section[..section.find("</table>").unwrap()];
    assert_eq!(
        section.matches("<td class=\"l\">pass</td>").count(),
        6,
        "{section}"
    );
    assert!(
        section.contains("z +100 mm") && section.contains("deviation"),
        "{section}"
    );
    // Its certificate: the limits, the rule, each step and the lines to sign.
    let (status, headers, page) = app
        .request_raw(
            "GET",
            &format!("/api/v1/acceptance/{id}/certificate"),
            &[],
            Body::empty(),
        )
        .await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(headers["content-type"], "text/html; charset=utf-8");
    assert!(
        headers["content-security-policy"]
            .to_str()
            .unwrap()
            .contains("default-src 'none'")
    );
    let page = String::from_utf8(page.to_vec()).unwrap();
    for needle in [
        "Acceptance certificate 1",
        "ISO 14253-1",
        "C3_from_G",
        "Performed by",
        "x +20 mm",
    ] {
        assert!(page.contains(needle), "{needle}: {page}");
    }
    let (status, _, _) = app
        .request_raw(
            "GET",
            "/api/v1/acceptance/7/certificate",
            &[],
            Body::empty(),
        )
        .await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    // A year and a day on: due.
    app.clock
        .set_ns(app.clock.now_ns() + 366 * 86_400 * 1_000_000_000);
    let (_, list) = app.get("/api/v1/acceptance").await;
    assert_eq!(list["standing"], "due", "{list}");
    let (_, health) = app.get("/healthz").await;
    assert!(
        health["acceptance_problem"]
            .as_str()
            .is_some_and(|p| p.contains("due")),
        "{health}"
    );
    // A station calibrated again: what was accepted no longer holds.
    let (status, body) = app
        .request(
            "PUT",
            "/api/v1/links/C2_from_C1/calibration",
            Some((
                "application/json",
                json!({"pose": {"t_mm": [-67.2, 37.5, -106.8], "euler_deg": [76.6492, 8.9522, 176.3952]},
                       "sigma": {"rotation_arcsec": 5.0, "translation_mm": 0.05},
                       "valid_from": brokenray::clock::format_ns(app.clock.now_ns())})
                .to_string(),
            )),
            None,
        )
        .await;
    assert_eq!(status, StatusCode::CREATED, "{body}");
    let (_, list) = app.get("/api/v1/acceptance").await;
    assert_eq!(list["standing"], "no_longer_holds", "{list}");
    let changed = list["acceptances"][0]["changed"][0].as_str().unwrap();
    assert!(
        changed.contains("C2_from_C1") && changed.contains("calibrated"),
        "{changed}"
    );
    // A measured link's filter reset (a station that moved) is named too.
    let (status, body) = app
        .post_json(
            "/api/v1/links/C3_from_G/reset",
            &json!({"by": "Bob", "note": "C3 knocked"}),
        )
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let (_, list) = app.get("/api/v1/acceptance").await;
    let changed = list["acceptances"][0]["changed"].to_string();
    assert!(
        changed.contains("C3_from_G") && changed.contains("reset") && changed.contains("Bob"),
        "{changed}"
    );
    let (status, missing) = app.get("/api/v1/acceptance/999").await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{missing}");
}

#[tokio::test]
async fn an_acceptance_is_due_after_its_interval_and_void_after_a_calibration_on_sqlite() {
    an_acceptance_is_due_after_its_interval_and_void_after_a_calibration(Backend::Sqlite).await;
}

#[tokio::test]
async fn an_acceptance_is_due_after_its_interval_and_void_after_a_calibration_on_postgres() {
    if crate::common::skip_without(
        crate::common::Needs::Postgres,
        "an_acceptance_is_due_after_its_interval_and_void_after_a_calibration_on_postgres",
    ) {
        return;
    }
    an_acceptance_is_due_after_its_interval_and_void_after_a_calibration(Backend::Postgres).await;
}

/// Asserts a refusal: its status, and its message holding `says`.
fn refused((status, body): (StatusCode, Value), want: StatusCode, says: &str) {
    assert_eq!(status, want, "{body}");
    let message = body["error"]["message"].as_str().unwrap_or_default();
    assert!(message.contains(says), "want `{says}` in: {body}");
}

/// The run refuses what does not fit where it is: a second run while one measures, a step
/// placed twice, a run without `by`; abandoning it records nothing.
#[tokio::test]
async fn the_run_refuses_out_of_turn_requests_and_abandoning_records_nothing() {
    let text = short_installation();
    let app = TestApp::start_on(Backend::Sqlite, Some(&text)).await;
    let (status, body) = app.get("/api/v1/acceptance/run").await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{body}");
    let (status, body) = app
        .post_json("/api/v1/acceptance/run", &json!({"by": " "}))
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert_eq!(body["error"]["details"][0]["field"], "by", "{body}");
    let (status, body) = app
        .post_json("/api/v1/acceptance/run", &json!({"by": "Ada", "colour": 1}))
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert_eq!(body["error"]["details"][0]["field"], "colour", "{body}");
    let (status, _) = app
        .post_json("/api/v1/acceptance/run", &json!({"by": "Ada"}))
        .await;
    assert_eq!(status, StatusCode::CREATED);
    // Nothing measured yet: no step can be placed.
    refused(
        app.post_json("/api/v1/acceptance/run/ready", &json!({}))
            .await,
        StatusCode::CONFLICT,
        "no raw result yet",
    );
    let model = app.service.installation().model.clone();
    let mut sim = simulator(&model, 14);
    let items: Vec<Value> = (0..5)
        .flat_map(|_| observation_items(&sim.next_group()))
        .collect();
    let (status, body) = app
        .post_live("/api/v1/observations", &json!({ "observations": items }))
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let (status, body) = app
        .post_json("/api/v1/acceptance/run/ready", &json!({}))
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    refused(
        app.post_json("/api/v1/acceptance/run/ready", &json!({}))
            .await,
        StatusCode::CONFLICT,
        "being measured",
    );
    refused(
        app.post_json("/api/v1/acceptance/run", &json!({"by": "Bob"}))
            .await,
        StatusCode::CONFLICT,
        "Ada",
    );
    let (status, _) = app
        .request("DELETE", "/api/v1/acceptance/run", None, None)
        .await;
    assert_eq!(status, StatusCode::NO_CONTENT);
    let (status, _) = app
        .request("DELETE", "/api/v1/acceptance/run", None, None)
        .await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    let (_, list) = app.get("/api/v1/acceptance").await;
    assert!(list["acceptances"].as_array().unwrap().is_empty(), "{list}");
    // An installation without [acceptance] has no procedure to run.
    let plain = text[..text.find("[acceptance]").unwrap()].to_owned();
    let app = TestApp::start_on(Backend::Sqlite, Some(&plain)).await;
    refused(
        app.post_json("/api/v1/acceptance/run", &json!({"by": "Ada"}))
            .await,
        StatusCode::UNPROCESSABLE_ENTITY,
        "[acceptance]",
    );
    let (_, health) = app.get("/healthz").await;
    assert!(health.get("acceptance_problem").is_none(), "{health}");
}
