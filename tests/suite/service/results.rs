//! Results through the API: ground truth, the paper's statistics, history, references,
//! calibrations, restarts.

use super::helpers::{Backend, ONE_LINK, T0_NS, TestApp, pose_json, time_text};
use crate::common::paper::{self, TABLE_4, TABLE_5};
use axum::http::StatusCode;
use brokenray::config;
use brokenray::geometry::{
    ARCSEC_PER_RAD, Pose, PoseCov, Twist, rotation_from_euler, se3_exp, se3_log,
};
use brokenray::model::LinkKind;
use rand::SeedableRng;
use rand::rngs::StdRng;
use rand_distr::{Distribution, StandardNormal};
use serde_json::{Value, json};

on_both_backends!(
    noise_free_samples_give_the_true_chain,
    the_papers_samples_give_back_table_4_and_5_through_stats,
    retries_store_one_copy_and_changed_values_conflict,
    compensation_at_a_past_time_is_interpolated_and_a_later_one_predicted,
    a_window_reference_gives_deformation_and_correction,
    a_new_calibration_is_versioned_and_used,
    a_restart_restores_the_filters_and_answers_the_same_compensation,
    a_reference_of_the_same_calibrations_cancels_their_error,
);

const MEASURED: [&str; 3] = ["C1_from_B", "C2_from_M", "C3_from_G"];

/// The true link poses: the nominal ones, each moved a little (so the truth is not the file).
fn truth() -> Vec<(String, Pose)> {
    let inst = config::default_installation();
    MEASURED
        .iter()
        .enumerate()
        .map(|(i, name)| {
            let LinkKind::Measured(m) = &inst.model.link_by_name(name).unwrap().kind else {
                panic!()
            };
            let f = i as f64 + 1.0;
            let nudge = se3_exp(&Twist::new(0.7 * f, -0.4 * f, 1.1, 2e-4 * f, -1e-4, 3e-4));
            (name.to_string(), nudge * m.nominal.unwrap())
        })
        .collect()
}

fn g_from_b(links: &[(String, Pose)]) -> Pose {
    let inst = config::default_installation();
    let get = |n: &str| links.iter().find(|(k, _)| k == n).map(|(_, p)| *p).unwrap();
    let cal = |n: &str| match &inst.model.link_by_name(n).unwrap().kind {
        LinkKind::Calibrated { parent_from_child } => parent_from_child.pose,
        _ => panic!(),
    };
    get("C3_from_G").inverse()
        * cal("C3_from_M")
        * get("C2_from_M").inverse()
        * cal("C2_from_C1")
        * get("C1_from_B")
}

fn pose_of(v: &Value) -> Pose {
    let t: Vec<f64> = serde_json::from_value(v["t_mm"].clone()).unwrap();
    let q: Vec<f64> = serde_json::from_value(v["q_wxyz"].clone()).unwrap();
    brokenray::geometry::pose_from_parts(
        [t[0], t[1], t[2]],
        brokenray::geometry::rotation_from_quaternion_wxyz([q[0], q[1], q[2], q[3]]).unwrap(),
    )
    .unwrap()
}

fn group(k: i64, links: &[(String, Pose)]) -> Vec<Value> {
    links
        .iter()
        .map(|(name, pose)| json!({"link": name, "time": time_text(k), "pose": pose_json(pose)}))
        .collect()
}

async fn noise_free_samples_give_the_true_chain(backend: Backend) {
    let app = TestApp::start_on(backend, None).await;
    let links = truth();
    let mut samples = Vec::new();
    for k in 0..20 {
        samples.extend(group(k, &links));
    }
    let (status, body) = app
        .post_json("/api/v1/samples", &json!({"samples": samples}))
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["stored"], 60);
    assert_eq!(body["raw_results"], 20);
    let (status, c) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(c["status"], "ok");
    assert_eq!(c["time"], time_text(19));
    let got = pose_of(&c["pose"]);
    let want = g_from_b(&links);
    let e = se3_log(&(got * want.inverse()));
    let t_err = (got.translation.vector - want.translation.vector).amax();
    let rot_err_deg = e.fixed_rows::<3>(3).amax().to_degrees();
    assert!(t_err < 1e-6, "translation off by {t_err} mm");
    assert!(rot_err_deg < 1e-6, "rotation off by {rot_err_deg} degree");
}

/// `groups` groups of the true links, each sample drawn with `scale` times its link's default
/// sigmas (and posted without them, so the service takes the defaults).
fn noisy_samples(groups: i64, scale: f64, seed: u64) -> Vec<Value> {
    let inst = config::default_installation();
    let links = truth();
    let mut rng = StdRng::seed_from_u64(seed);
    let mut samples = Vec::new();
    for k in 0..groups {
        for (name, pose) in &links {
            let LinkKind::Measured(m) = &inst.model.link_by_name(name).unwrap().kind else {
                panic!()
            };
            let cov = PoseCov::from_reported_sigmas(*pose, &m.default_sigmas).cov;
            let l = cov.cholesky().unwrap().l() * scale;
            let z = Twist::from_fn(|_, _| StandardNormal.sample(&mut rng));
            let noisy = se3_exp(&(l * z)) * pose;
            samples.push(json!({"link": name, "time": time_text(k), "pose": pose_json(&noisy)}));
        }
    }
    samples
}

#[tokio::test]
async fn noisy_samples_give_the_truth_within_three_reported_sigmas() {
    let app = TestApp::start(None).await;
    let links = truth();
    let samples = noisy_samples(250, 1.0, 5);
    let (status, body) = app
        .post_live("/api/v1/samples", &json!({"samples": samples}))
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    let got = pose_of(&c["pose"]);
    let want = g_from_b(&links);
    let sigma_rot: Vec<f64> =
        serde_json::from_value(c["sigma"]["rotation_arcsec"].clone()).unwrap();
    let sigma_t: Vec<f64> = serde_json::from_value(c["sigma"]["translation_mm"].clone()).unwrap();
    // Rotation error about the left frame's axes, translation error per component.
    let phi =
        brokenray::geometry::so3_log(&(got.rotation * want.rotation.inverse())) * ARCSEC_PER_RAD;
    let dt = got.translation.vector - want.translation.vector;
    for i in 0..3 {
        assert!(
            phi[i].abs() < 3.0 * sigma_rot[i],
            "rotation axis {i}: {:.2} arcsec vs sigma {:.2}",
            phi[i],
            sigma_rot[i]
        );
        assert!(
            dt[i].abs() < 3.0 * sigma_t[i],
            "translation {i}: {:.3} mm vs sigma {:.3}",
            dt[i],
            sigma_t[i]
        );
    }
    // The filter has averaged the noise: the random part of its sigma is well below a single
    // raw composition's scatter; the systematic part (the cameras' calibrations) it cannot
    // average, and the whole sigma holds both.
    let (_, raw) = app.get("/api/v1/targets/G/stats?source=raw").await;
    let raw_rms: Vec<f64> = serde_json::from_value(raw["t_mm"]["rms"].clone()).unwrap();
    let random_t: Vec<f64> =
        serde_json::from_value(c["sigma_random"]["translation_mm"].clone()).unwrap();
    let systematic_t: Vec<f64> =
        serde_json::from_value(c["sigma_systematic"]["translation_mm"].clone()).unwrap();
    assert!(
        random_t.iter().zip(&raw_rms).all(|(s, r)| s < r),
        "{random_t:?} vs raw scatter {raw_rms:?}"
    );
    for i in 0..3 {
        let whole = (random_t[i].powi(2) + systematic_t[i].powi(2)).sqrt();
        assert!(
            (whole - sigma_t[i]).abs() <= 1e-9 * sigma_t[i],
            "axis {i}: random {} and systematic {} do not make the whole {}",
            random_t[i],
            systematic_t[i],
            sigma_t[i]
        );
        assert!(
            systematic_t[i] > 0.0,
            "the built-in cameras' calibrations count"
        );
    }
}

async fn the_papers_samples_give_back_table_4_and_5_through_stats(backend: Backend) {
    let app = TestApp::start_on(backend, Some(ONE_LINK)).await;
    let samples: Vec<Value> = (0..8)
        .map(|i| json!({"link": "G_from_B", "time": time_text(i as i64 * 25), "pose": {"t_mm": TABLE_5[i], "euler_deg": TABLE_4[i]}}))
        .collect();
    let (status, body) = app
        .post_json("/api/v1/samples", &json!({"samples": samples}))
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let (status, s) = app.get("/api/v1/targets/G/stats?source=raw").await;
    assert_eq!(status, StatusCode::OK, "{s}");
    assert_eq!(s["count"], 8);
    // Means and rms may differ from the paper's by the rounding of its printed samples (see
    // tests/common/paper.rs).
    paper::assert_all_printed(|section, stat| {
        serde_json::from_value(s[section][stat].clone()).expect("three numbers")
    });
}

async fn retries_store_one_copy_and_changed_values_conflict(backend: Backend) {
    let app = TestApp::start_on(backend, None).await;
    let links = truth();
    let batch = json!({"samples": group(0, &links)});
    let (s1, b1) = app.post_json("/api/v1/samples", &batch).await;
    let (s2, b2) = app.post_json("/api/v1/samples", &batch).await;
    assert_eq!((s1, s2), (StatusCode::OK, StatusCode::OK), "{b1} {b2}");
    assert_eq!(b2["duplicates"], 3);
    assert_eq!(b2["stored"], 0);
    let (_, samples) = app.get("/api/v1/links/C1_from_B/samples").await;
    assert_eq!(samples["samples"].as_array().unwrap().len(), 1);
    let mut changed = group(0, &links);
    changed[1]["pose"]["t_mm"][0] = json!(12.5);
    changed
        .push(json!({"link": "C1_from_B", "time": time_text(1), "pose": pose_json(&links[0].1)}));
    let (status, body) = app
        .post_json("/api/v1/samples", &json!({"samples": changed}))
        .await;
    assert_eq!(status, StatusCode::CONFLICT, "{body}");
    assert_eq!(body["error"]["details"][0]["index"], 1);
    assert_eq!(body["error"]["details"][0]["field"], "time");
    // Atomic: the new sample of the refused batch was not stored either.
    let (_, samples) = app.get("/api/v1/links/C1_from_B/samples").await;
    assert_eq!(samples["samples"].as_array().unwrap().len(), 1);
}

async fn compensation_at_a_past_time_is_interpolated_and_a_later_one_predicted(backend: Backend) {
    let app = TestApp::start_on(backend, None).await;
    let links = truth();
    // The target drifts: C3_from_G slides 0.01 mm per group along x (a fifth of its sigma).
    let mut samples = Vec::new();
    for k in 0..10 {
        let mut l = links.clone();
        l[2].1 = Pose::from_parts(
            nalgebra::Translation3::from(
                l[2].1.translation.vector + nalgebra::Vector3::new(0.01 * k as f64, 0.0, 0.0),
            ),
            l[2].1.rotation,
        );
        samples.extend(group(k, &l));
    }
    let (status, _) = app
        .post_json("/api/v1/samples", &json!({"samples": samples}))
        .await;
    assert_eq!(status, StatusCode::OK);
    let at = |k: i64, frac: f64| {
        brokenray::clock::format_ns(T0_NS + k * 40_000_000 + (frac * 40e6) as i64)
    };
    let (s3, c3) = app
        .get(&format!("/api/v1/targets/G/compensation?at={}", at(3, 0.0)))
        .await;
    let (s4, c4) = app
        .get(&format!("/api/v1/targets/G/compensation?at={}", at(4, 0.0)))
        .await;
    let (sm, cm) = app
        .get(&format!("/api/v1/targets/G/compensation?at={}", at(3, 0.5)))
        .await;
    assert_eq!(
        (s3, s4, sm),
        (StatusCode::OK, StatusCode::OK, StatusCode::OK),
        "{c3} {c4} {cm}"
    );
    assert_eq!(cm["source"], "history");
    let (p3, p4, pm) = (
        pose_of(&c3["pose"]),
        pose_of(&c4["pose"]),
        pose_of(&cm["pose"]),
    );
    let mid = (p3.translation.vector + p4.translation.vector) / 2.0;
    assert!(
        (pm.translation.vector - mid).amax() < 1e-6,
        "{} vs {}",
        pm.translation.vector,
        mid
    );
    let (status, future) = app
        .get(&format!(
            "/api/v1/targets/G/compensation?at={}",
            at(12, 0.0)
        ))
        .await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(future["status"], "predicted");
    assert_eq!(future["source"], "predicted");
    assert!((future["age_s"].as_f64().unwrap() - 0.12).abs() < 1e-9);
    let (status, _) = app
        .get(&format!(
            "/api/v1/targets/G/compensation?at={}",
            at(-5, 0.0)
        ))
        .await;
    assert_eq!(status, StatusCode::NOT_FOUND);
}

async fn a_window_reference_gives_deformation_and_correction(backend: Backend) {
    let app = TestApp::start_on(backend, None).await;
    let links = truth();
    let mut samples = Vec::new();
    for k in 0..10 {
        samples.extend(group(k, &links));
    }
    app.post_json("/api/v1/samples", &json!({"samples": samples}))
        .await;
    let (status, r) = app
        .post_json(
            "/api/v1/targets/G/reference",
            &json!({"from": time_text(0), "to": time_text(9)}),
        )
        .await;
    assert_eq!(status, StatusCode::CREATED, "{r}");
    assert_eq!(r["version"], 1);
    assert_eq!(r["window"]["count"], 10);
    // The target then turns by 100 arc-seconds about C3's x axis.
    let mut moved = links.clone();
    let turn = rotation_from_euler([(100.0 / 3600.0f64).to_radians(), 0.0, 0.0]).unwrap();
    moved[2].1 = Pose::from_parts(moved[2].1.translation, turn * moved[2].1.rotation);
    let mut samples = Vec::new();
    for k in 10..400 {
        samples.extend(group(k, &moved));
    }
    app.post_live("/api/v1/samples", &json!({"samples": samples}))
        .await;
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    let def: Vec<f64> =
        serde_json::from_value(c["deformation"]["rotation_arcsec"].clone()).unwrap();
    let magnitude = (def[0] * def[0] + def[1] * def[1] + def[2] * def[2]).sqrt();
    assert!(
        (magnitude - 100.0).abs() < 1.0,
        "deformation {magnitude:.2} arcsec, expected 100"
    );
    assert_eq!(
        c["alarm"], "warn",
        "100 arcsec is between warn (60) and alarm (120)"
    );
    let corr: Vec<f64> =
        serde_json::from_value(c["correction"]["rotation_arcsec"].clone()).unwrap();
    for i in 0..3 {
        assert!(
            (corr[i] + def[i]).abs() < 0.5,
            "correction undoes the deformation: {corr:?} vs {def:?}"
        );
    }
    // An explicit reference makes version 2; the history lists both.
    let (status, r2) = app
        .post_json("/api/v1/targets/G/reference", &json!({"pose": c["pose"]}))
        .await;
    assert_eq!(status, StatusCode::CREATED, "{r2}");
    let (_, list) = app.get("/api/v1/targets/G/references").await;
    assert_eq!(list["references"].as_array().unwrap().len(), 2);
    // The alarm state follows results: two more seconds against the new zero (longer than
    // the 1 s dwell) clear it.
    let mut samples = Vec::new();
    for k in 400..450 {
        samples.extend(group(k, &moved));
    }
    app.post_json("/api/v1/samples", &json!({"samples": samples}))
        .await;
    let (_, c2) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(c2["alarm"], "none");
    let (_, alarms) = app.get("/api/v1/alarms?target=G").await;
    let levels: Vec<&str> = alarms["alarms"]
        .as_array()
        .unwrap()
        .iter()
        .map(|a| a["to"].as_str().unwrap())
        .collect();
    assert_eq!(levels, ["warn", "none"]);
    let (status, _) = app
        .post_json(
            "/api/v1/targets/G/reference",
            &json!({"from": time_text(-100), "to": time_text(-50)}),
        )
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
}

/// A new calibration of `C2_from_C1`: its translation `t_mm` (the built-in rotation, 5
/// arc-seconds and 0.05 mm), valid from group `from_group`.
async fn recalibrate_station(
    app: &TestApp,
    t_mm: [f64; 3],
    from_group: i64,
) -> (StatusCode, Value) {
    app.request(
        "PUT",
        "/api/v1/links/C2_from_C1/calibration",
        Some((
            "application/json",
            json!({"pose": {"t_mm": t_mm, "euler_deg": [76.6492, 8.9522, 176.3952]},
                   "sigma": {"rotation_arcsec": 5.0, "translation_mm": 0.05},
                   "valid_from": time_text(from_group)})
            .to_string(),
        )),
        None,
    )
    .await
}

async fn a_new_calibration_is_versioned_and_used(backend: Backend) {
    let app = TestApp::start_on(backend, None).await;
    let links = truth();
    app.post_json("/api/v1/samples", &json!({"samples": group(0, &links)}))
        .await;
    let (_, before) = app.get("/api/v1/targets/G/compensation").await;
    let (status, body) = recalibrate_station(&app, [-67.2, 37.5, -96.8], 0).await;
    assert_eq!(status, StatusCode::CREATED, "{body}");
    app.post_json("/api/v1/samples", &json!({"samples": group(1, &links)}))
        .await;
    let (_, after) = app.get("/api/v1/targets/G/compensation").await;
    let moved = (pose_of(&after["pose"]).translation.vector
        - pose_of(&before["pose"]).translation.vector)
        .norm();
    assert!(
        moved > 5.0,
        "a 10 mm change of the station moves the result ({moved:.2} mm)"
    );
    let (_, list) = app.get("/api/v1/links/C2_from_C1/calibrations").await;
    let versions: Vec<i64> = list["calibrations"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["version"].as_i64().unwrap())
        .collect();
    assert_eq!(versions, [0, 1]);
    let (status, _) = app
        .request("PUT", "/api/v1/links/C1_from_B/calibration", Some(("application/json", json!({"pose": {"t_mm": [0,0,0], "q_wxyz": [1,0,0,0]}, "sigma": {"rotation_arcsec": 1, "translation_mm": 1}}).to_string())), None)
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
}

async fn a_restart_restores_the_filters_and_answers_the_same_compensation(backend: Backend) {
    let app = TestApp::start_on(backend, None).await;
    let links = truth();
    let mut rng = StdRng::seed_from_u64(9);
    let mut samples = Vec::new();
    for k in 0..50 {
        for (name, pose) in &links {
            let z = Twist::from_fn(|i, _| {
                let n: f64 = StandardNormal.sample(&mut rng);
                n * if i < 3 { 0.1 } else { 5e-5 }
            });
            samples.push(json!({"link": name, "time": time_text(k), "pose": pose_json(&(se3_exp(&z) * pose))}));
        }
    }
    app.post_json("/api/v1/samples", &json!({"samples": samples}))
        .await;
    let (_, before) = app.get("/api/v1/targets/G/compensation").await;
    let (_, links_before) = app.get("/api/v1/links").await;
    let app = app.restart(None).await;
    let (_, after) = app.get("/api/v1/targets/G/compensation").await;
    assert_eq!(before, after);
    let (_, links_after) = app.get("/api/v1/links").await;
    for (a, b) in links_before
        .as_array()
        .unwrap()
        .iter()
        .zip(links_after.as_array().unwrap())
    {
        assert_eq!(a["n_samples"], b["n_samples"]);
        assert_eq!(a["last_time"], b["last_time"]);
    }
    // And the filters continue where they were: the next group is fused, not a fresh start.
    let (_, next) = app
        .post_json("/api/v1/samples", &json!({"samples": group(50, &links)}))
        .await;
    assert_eq!(next["filtered_results"], 1);
    let (_, samples) = app
        .get(&format!(
            "/api/v1/links/C1_from_B/samples?from={}",
            time_text(50)
        ))
        .await;
    assert_eq!(samples["samples"][0]["disposition"], "fused");
}

/// `GET /api/v1/targets/{name}/filter` answers the target filter's model with only the terms
/// that model has, and its innovations' mean and band; an unknown target is a 404 naming it.
#[tokio::test]
async fn the_target_filter_is_reported_with_its_model_and_consistency() {
    let app = TestApp::start(None).await;
    let links = truth();
    let mut samples = Vec::new();
    for k in 0..20 {
        samples.extend(group(k, &links));
    }
    app.post_json("/api/v1/samples", &json!({ "samples": samples }))
        .await;
    let (status, f) = app.get("/api/v1/targets/G/filter").await;
    assert_eq!(status, StatusCode::OK, "{f}");
    // The built-in links are static: so is the target's filter, with a random walk and no
    // oscillation or acceleration.
    assert_eq!(f["model"], "static");
    assert_eq!(f["fitted"], false);
    assert!(
        f["oscillation_period_s"].is_null()
            && f["acceleration_rotation_arcsec_per_s_sqrt_s"].is_null()
    );
    assert_eq!(f["drift_rotation_arcsec_per_sqrt_s"], 2.0);
    // Twenty groups: the first starts the filter, nineteen are innovations.
    assert_eq!(f["nis_samples"], 19);
    let band = f["nis_band"].as_array().unwrap();
    assert!(band[0].as_f64().unwrap() < 6.0 && band[1].as_f64().unwrap() > 6.0);
    assert!(f["consistent"].is_boolean());
    let (status, e) = app.get("/api/v1/targets/nope/filter").await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    assert!(
        e["error"]["message"].as_str().unwrap().contains("nope"),
        "{e}"
    );
}

/// The sigmas of a JSON `{rotation_arcsec, translation_mm}`, rotation first.
fn sigmas_of(v: &Value) -> Vec<f64> {
    let mut out: Vec<f64> = serde_json::from_value(v["rotation_arcsec"].clone()).unwrap();
    out.extend(serde_json::from_value::<Vec<f64>>(v["translation_mm"].clone()).unwrap());
    out
}

/// A deformation against a reference measured with the same calibrations carries no
/// systematic part (the calibrations' error is in both and cancels); after a calibration
/// changed, both parts add. The reference keeps its calibrations across a restart of the
/// store (it is read back from it).
async fn a_reference_of_the_same_calibrations_cancels_their_error(backend: Backend) {
    let app = TestApp::start_on(backend, None).await;
    let links = truth();
    let post = |from: i64, to: i64| {
        let samples: Vec<Value> = (from..to).flat_map(|k| group(k, &links)).collect();
        json!({"samples": samples})
    };
    app.post_json("/api/v1/samples", &post(0, 10)).await;
    let (status, r) = app
        .post_json(
            "/api/v1/targets/G/reference",
            &json!({"from": time_text(0), "to": time_text(9)}),
        )
        .await;
    assert_eq!(status, StatusCode::CREATED, "{r}");
    assert!(
        sigmas_of(&r["sigma_systematic"]).iter().all(|s| *s > 0.0),
        "{r}"
    );
    app.post_json("/api/v1/samples", &post(10, 20)).await;
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    let d = &c["deformation"];
    assert!(
        sigmas_of(&d["sigma_systematic"]).iter().all(|s| *s < 1e-9),
        "the same calibrations: {d}"
    );
    for (whole, random) in sigmas_of(&d["sigma"])
        .iter()
        .zip(sigmas_of(&d["sigma_random"]))
    {
        assert!((whole - random).abs() <= 1e-9 * whole, "{d}");
    }
    // The result itself keeps its systematic part: it is what G_from_B's truth is within.
    let result_sigma = sigmas_of(&c["sigma"]);
    assert!(
        sigmas_of(&d["sigma"])[0] < result_sigma[0],
        "the deformation {d} is known better than the pose {}",
        c["sigma"]
    );

    // A new calibration of a station: the reference was measured with the old one.
    let (status, body) = recalibrate_station(&app, [-67.21, 37.5, -106.8], 20).await;
    assert_eq!(status, StatusCode::CREATED, "{body}");
    app.post_json("/api/v1/samples", &post(20, 30)).await;
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    let d = &c["deformation"];
    let systematic = sigmas_of(&d["sigma_systematic"]);
    let random = sigmas_of(&d["sigma_random"]);
    for (i, whole) in sigmas_of(&d["sigma"]).iter().enumerate() {
        assert!(systematic[i] > random[i], "axis {i}: {d}");
        assert!(
            (whole.powi(2) - systematic[i].powi(2) - random[i].powi(2)).abs()
                <= 1e-9 * whole * whole,
            "axis {i}: {d}"
        );
    }
}

/// `GET .../budget`: every contributor of the newest result, its shares adding up to one on
/// each axis, the largest first; the sigmas its parts make; 404 before any result, 422 for an
/// unknown source.
#[tokio::test]
async fn the_budget_names_every_contributor_largest_first() {
    let app = TestApp::start(None).await;
    let (status, body) = app.get("/api/v1/targets/G/budget").await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{body}");
    assert_eq!(body["error"]["code"], "not_found");
    let samples = noisy_samples(50, 1.0, 4);
    let (status, body) = app
        .post_live("/api/v1/samples", &json!({"samples": samples}))
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let (_, c) = app.get("/api/v1/targets/G/compensation").await;
    for source in ["raw", "filtered"] {
        let (status, b) = app
            .get(&format!("/api/v1/targets/G/budget?source={source}"))
            .await;
        assert_eq!(status, StatusCode::OK, "{b}");
        assert_eq!(b["source"], source);
        let lines = b["contributions"].as_array().unwrap();
        let mut kinds: Vec<(String, String)> = lines
            .iter()
            .map(|l| {
                (
                    l["kind"].as_str().unwrap().to_owned(),
                    l["name"].as_str().unwrap().to_owned(),
                )
            })
            .collect();
        kinds.sort();
        let expected: Vec<(String, String)> = [
            ("calibration", "C2_from_C1"),
            ("calibration", "C3_from_M"),
            ("intrinsics", "C1"),
            ("intrinsics", "C2"),
            ("intrinsics", "C3"),
            ("noise", "C1_from_B"),
            ("noise", "C2_from_M"),
            ("noise", "C3_from_G"),
        ]
        .iter()
        .map(|(a, b)| ((*a).to_owned(), (*b).to_owned()))
        .collect();
        assert_eq!(kinds, expected);
        for w in lines.windows(2) {
            assert!(w[0]["largest_share"].as_f64() >= w[1]["largest_share"].as_f64());
        }
        for (axes, i) in [
            ("rotation", 0),
            ("rotation", 1),
            ("rotation", 2),
            ("translation", 0),
        ] {
            let shares: f64 = lines
                .iter()
                .map(|l| l["share"][axes][i].as_f64().unwrap())
                .sum();
            assert!(
                (shares - 1.0).abs() < 1e-9,
                "{source} {axes}[{i}]: {shares}"
            );
            // The whole sigma is the root of the summed variances, and the parts make it.
            let whole = b["sigma"][axes][i].as_f64().unwrap();
            let summed: f64 = lines
                .iter()
                .map(|l| l["sigma"][axes][i].as_f64().unwrap().powi(2))
                .sum();
            assert!((summed.sqrt() - whole).abs() <= 1e-9 * whole);
            let parts = b["sigma_random"][axes][i].as_f64().unwrap().powi(2)
                + b["sigma_systematic"][axes][i].as_f64().unwrap().powi(2);
            assert!((parts.sqrt() - whole).abs() <= 1e-9 * whole);
        }
        if source == "filtered" {
            // The filtered budget is the compensation's sigma, split.
            let key = |axes: &str| {
                if axes == "rotation" {
                    "rotation_arcsec"
                } else {
                    "translation_mm"
                }
            };
            for axes in ["rotation", "translation"] {
                for i in 0..3 {
                    let budget = b["sigma"][axes][i].as_f64().unwrap();
                    let compensation = c["sigma"][key(axes)][i].as_f64().unwrap();
                    assert!(
                        (budget - compensation).abs() <= 1e-6 * compensation,
                        "{axes}[{i}]: budget {budget}, compensation {compensation}"
                    );
                }
            }
        }
    }
    let (status, body) = app.get("/api/v1/targets/G/budget?source=smoothed").await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert!(
        body["error"]["message"]
            .as_str()
            .unwrap()
            .contains("source"),
        "{body}"
    );
    let (status, _) = app.get("/api/v1/targets/Nope/budget").await;
    assert_eq!(status, StatusCode::NOT_FOUND);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_read_right_after_an_acknowledged_write_sees_it() {
    // Readers are given the commit before its request is answered: each compensation read just
    // after a write is the result of that write, never the one before.
    let app = TestApp::start(Some(&super::helpers::alarmed_installation(""))).await;
    for k in 0..60 {
        let time = T0_NS + k * 40_000_000;
        let (status, body) = app
            .post_live(
                "/api/v1/samples",
                &json!({"samples": [super::helpers::turned_sample(time, 1.0)]}),
            )
            .await;
        assert_eq!(status, StatusCode::OK, "{body}");
        let (_, compensation) = app.get("/api/v1/targets/G/compensation").await;
        assert_eq!(
            brokenray::clock::parse_json_time(&compensation["time"]).ok(),
            Some(time),
            "sample {k}: {compensation}"
        );
    }
}
