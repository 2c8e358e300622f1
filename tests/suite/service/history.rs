//! History at scale: a million results over 30 days, downsampled to 2000 buckets whose min and
//! max contain every stored value of their span (checked against a direct scan).

use super::helpers::{Backend, ONE_LINK, T0_NS, TestApp, installation_at};
use axum::http::StatusCode;
use brokenray::bank::ResultSource;
use brokenray::geometry::{Mat6, Pose, PoseCov, rotation_from_euler};
use brokenray::model::TargetId;
use brokenray::store::{self, NewResult};
use nalgebra::Translation3;

const N: i64 = 1_000_000;
const SPAN_NS: i64 = 30 * 86_400 * 1_000_000_000;
const SPIKE: i64 = 654_321;

fn result(k: i64) -> NewResult {
    let t = k as f64 * 1e-4;
    let x = if k == SPIKE {
        500.0
    } else {
        (t * 3.1).sin() * 2.0 + (k % 7) as f64 * 0.01
    };
    let pose = Pose::from_parts(
        Translation3::new(x, -2952.0 + (t * 0.7).cos(), 532.0),
        rotation_from_euler([-0.0718 + 1e-5 * (t * 1.3).sin(), 0.026, 2.87]).unwrap(),
    );
    NewResult {
        target: TargetId(0),
        source: ResultSource::Filtered,
        time_ns: T0_NS + k * (SPAN_NS / N),
        estimate: brokenray::deformation::MeasuredPose {
            whole: PoseCov {
                pose,
                cov: Mat6::identity() * 1e-6,
            },
            systematic_cov: Mat6::zeros(),
            calibration: Some(brokenray::deformation::CalibrationStamp(0)),
        },
        status: brokenray::bank::TargetStatus::Ok,
        age_s: 0.0,
        chi2: None,
        deformation: None,
    }
}

on_both_backends!(
    a_month_of_results_downsamples_without_losing_a_spike,
    retention_prunes_old_rows_and_keeps_rollups,
    a_result_recomputed_at_the_same_time_counts_once_in_the_rollups,
);

async fn a_month_of_results_downsamples_without_losing_a_spike(backend: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let inst = installation_at(&backend.database(&dir), Some(ONE_LINK));
    {
        let (store, mut write) = store::open(&inst, 0).await.unwrap();
        for chunk_start in (0..N).step_by(100_000) {
            let rows: Vec<NewResult> = (chunk_start..chunk_start + 100_000).map(result).collect();
            let mut tx = write.begin(0).await.unwrap();
            tx.insert_results(&[&rows]).await.unwrap();
            tx.commit().await.unwrap();
        }
        write.close().await.unwrap();
        store.close().await;
    }
    let app = TestApp::start_with(dir, inst).await;
    let (status, h) = app.get("/api/v1/targets/G/history?max_points=2000").await;
    assert_eq!(status, StatusCode::OK);
    let times = h["time"].as_array().unwrap();
    assert!(
        !times.is_empty() && times.len() <= 2000,
        "{} buckets",
        times.len()
    );
    assert_eq!(
        h["resolution_s"], 600,
        "a month in 2000 buckets reads the 10-minute rollup"
    );
    let counts: Vec<i64> = serde_json::from_value(h["count"].clone()).unwrap();
    assert_eq!(counts.iter().sum::<i64>(), N, "every result is in a bucket");
    let width_ns = (h["bucket_s"].as_f64().unwrap() * 1e9).round() as i64;
    let starts: Vec<i64> = times
        .iter()
        .map(|t| brokenray::clock::parse_rfc3339_ns(t.as_str().unwrap()).unwrap())
        .collect();
    let x_min: Vec<f64> = serde_json::from_value(h["series"]["t_x_mm"]["min"].clone()).unwrap();
    let x_max: Vec<f64> = serde_json::from_value(h["series"]["t_x_mm"]["max"].clone()).unwrap();
    let x_mean: Vec<f64> = serde_json::from_value(h["series"]["t_x_mm"]["mean"].clone()).unwrap();
    // Direct scan: every stored value lies within its bucket's min and max, which it attains.
    let stored = app
        .service
        .store()
        .results(
            TargetId(0),
            ResultSource::Filtered,
            i64::MIN,
            i64::MAX,
            i64::MAX,
        )
        .await
        .unwrap();
    assert_eq!(stored.len() as i64, N);
    let mut scan_min = vec![f64::INFINITY; starts.len()];
    let mut scan_max = vec![f64::NEG_INFINITY; starts.len()];
    let mut scan_sum = vec![0.0; starts.len()];
    let mut scan_n = vec![0i64; starts.len()];
    for r in &stored {
        let b = starts.partition_point(|s| *s <= r.time_ns) - 1;
        assert!(
            r.time_ns < starts[b] + width_ns,
            "result outside every bucket"
        );
        let x = r.estimate.whole.pose.translation.vector.x;
        scan_min[b] = scan_min[b].min(x);
        scan_max[b] = scan_max[b].max(x);
        scan_sum[b] += x;
        scan_n[b] += 1;
    }
    for b in 0..starts.len() {
        assert_eq!(scan_n[b], counts[b]);
        assert_eq!(x_min[b], scan_min[b], "bucket {b} min");
        assert_eq!(x_max[b], scan_max[b], "bucket {b} max");
        assert!(
            (x_mean[b] - scan_sum[b] / scan_n[b] as f64).abs() < 1e-9,
            "bucket {b} mean"
        );
    }
    // The spike survives in its bucket's max.
    let spike_time = T0_NS + SPIKE * (SPAN_NS / N);
    let b = starts.partition_point(|s| *s <= spike_time) - 1;
    assert_eq!(x_max[b], 500.0);
    // A narrow window reads the results themselves; CSV has a header and one line a bucket.
    let narrow = format!(
        "/api/v1/targets/G/history?from={}&to={}&max_points=100",
        T0_NS,
        T0_NS + 60 * 1_000_000_000
    );
    let (_, n) = app.get(&narrow).await;
    assert_eq!(n["resolution_s"], serde_json::Value::Null);
    let (status, csv) = app.get(&format!("{narrow}&format=csv")).await;
    assert_eq!(status, StatusCode::OK);
    let text = csv.as_str().unwrap();
    assert!(text.starts_with("time,count,euler_x_deg_min,euler_x_deg_mean,euler_x_deg_max"));
    assert_eq!(
        text.lines().count(),
        n["time"].as_array().unwrap().len() + 1
    );
    // Only the components asked for, with the same values.
    let (status, some) = app
        .get(&format!("{narrow}&components=t_x_mm,sigma_rz_arcsec"))
        .await;
    assert_eq!(status, StatusCode::OK);
    let keys: Vec<&String> = some["series"].as_object().unwrap().keys().collect();
    assert_eq!(keys, ["sigma_rz_arcsec", "t_x_mm"]);
    assert_eq!(some["series"]["t_x_mm"], n["series"]["t_x_mm"]);
    assert_eq!(some["count"], n["count"]);
    let (_, csv) = app
        .get(&format!("{narrow}&components=t_x_mm&format=csv"))
        .await;
    let header = csv.as_str().unwrap().lines().next().unwrap().to_owned();
    assert_eq!(header, "time,count,t_x_mm_min,t_x_mm_mean,t_x_mm_max");
    let (status, body) = app
        .get(&format!("{narrow}&components=t_x_mm,tilt_deg"))
        .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    assert!(
        body.to_string().contains("`tilt_deg` is not a component"),
        "{body}"
    );
    // A choice out of its values is refused naming the field and the choices.
    for (query, field, message) in [
        (
            "source=fused",
            "source",
            "`fused` is not `raw` or `filtered`",
        ),
        ("format=xml", "format", "`xml` is not `json` or `csv`"),
    ] {
        let (status, body) = app.get(&format!("{narrow}&{query}")).await;
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{query}");
        assert_eq!(body["error"]["details"][0]["field"], field, "{body}");
        assert_eq!(body["error"]["details"][0]["message"], message, "{body}");
    }
}

async fn retention_prunes_old_rows_and_keeps_rollups(backend: Backend) {
    let app = TestApp::start_on(
        backend,
        Some(&format!(
            "{ONE_LINK}\n[retention]\nsamples_days = 1\nresults_days = 2\n"
        )),
    )
    .await;
    // Five days of samples, one an hour, ending an hour ago (later ones would be in the
    // future, which the service refuses).
    let hour = 3_600_000_000_000i64;
    let start = (app.service.now_ns() / hour - 121) * hour;
    let samples: Vec<serde_json::Value> = (0..120)
        .map(|h| {
            serde_json::json!({"link": "G_from_B", "time": start + h * hour,
                               "pose": {"t_mm": [1.0, 2.0, 3.0], "q_wxyz": [1, 0, 0, 0]}})
        })
        .collect();
    let (status, _) = app
        .post_json("/api/v1/samples", &serde_json::json!({"samples": samples}))
        .await;
    assert_eq!(status, StatusCode::OK);
    let (_, before) = app
        .get("/api/v1/targets/G/history?source=raw&max_points=5")
        .await;
    let (samples_gone, results_gone) = app.service.prune().await.unwrap();
    // The newest result is at hour 119: samples before hour 95 go, hour 95 itself stays.
    assert_eq!(
        samples_gone, 95,
        "samples older than a day before the newest"
    );
    assert!(results_gone > 0);
    let (_, left) = app.get("/api/v1/links/G_from_B/samples?limit=1000").await;
    assert_eq!(left["samples"].as_array().unwrap().len(), 25);
    // The coarse history still covers all five days from the rollups.
    let (_, after) = app
        .get("/api/v1/targets/G/history?source=raw&max_points=5")
        .await;
    assert_eq!(before["count"], after["count"]);
}

/// Each camera posting on its own: the samples of one time arrive in separate requests, and the
/// filtered result at that time is computed again with each. The rollups must count it once,
/// with its last value, as the results table does.
async fn a_result_recomputed_at_the_same_time_counts_once_in_the_rollups(backend: Backend) {
    use brokenray::feed::sample_items;
    use brokenray::sim::{Scenario, SimSettings, Simulator};
    let app = TestApp::start_on(backend, None).await;
    let inst = app.service.installation().clone();
    let mut sim = Simulator::new(
        &inst.model,
        SimSettings {
            scenario: Scenario::Drift,
            rate_hz: 0.5,
            start_ns: T0_NS,
            duration_s: None,
            pixel_sigma_px: None,
            outlier_rate: 0.0,
            seed: 5,
        },
    )
    .unwrap();
    let groups = 40;
    for _ in 0..groups {
        let group = sim.next_group();
        for item in sample_items(&group, sim.observer()) {
            let (status, body) = app
                .post_live("/api/v1/samples", &serde_json::json!({ "samples": [item] }))
                .await;
            assert_eq!(status, StatusCode::OK, "{body}");
        }
    }
    // From the results themselves (buckets under 1 s), and from the 10 s rollups.
    let (_, fine) = app.get("/api/v1/targets/G/history?max_points=100000").await;
    assert_eq!(fine["resolution_s"], serde_json::Value::Null);
    let (_, coarse) = app.get("/api/v1/targets/G/history?max_points=4").await;
    assert_eq!(coarse["resolution_s"], 10);
    let total = |h: &serde_json::Value| -> i64 {
        h["count"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c.as_i64().unwrap())
            .sum()
    };
    assert_eq!(total(&fine), groups, "one filtered result per time");
    assert_eq!(total(&coarse), groups, "the rollups count each result once");
    // The mean over everything, from either.
    let mean = |h: &serde_json::Value| -> f64 {
        let counts = h["count"].as_array().unwrap();
        let means = h["series"]["t_x_mm"]["mean"].as_array().unwrap();
        counts
            .iter()
            .zip(means)
            .map(|(c, m)| c.as_f64().unwrap() * m.as_f64().unwrap())
            .sum::<f64>()
            / groups as f64
    };
    approx::assert_abs_diff_eq!(mean(&fine), mean(&coarse), epsilon = 1e-9);
}

/// A site cut off from its centre with a disk budget: past it, every sample and raw result
/// goes before the first filtered result does, the oldest first, whatever their age and
/// though the centre never had them; rollups and references stay; the service says so in
/// `/healthz` and `/metrics`, and keeps working.
#[tokio::test]
async fn a_disk_budget_removes_the_oldest_raw_rows_first_and_says_so() {
    let site = |budget_mb: f64| {
        format!(
            "{ONE_LINK}\n[site]\nname = \"ship-1\"\n\n[upstream]\nurl = \"http://127.0.0.1:9\"\n\
             raw_kbit_s = 64\n\n[retention]\ndisk_budget_mb = {budget_mb}\n"
        )
    };
    let app = TestApp::start(Some(&site(1000.0))).await;
    // Three hours of a sample a second, ending an hour ago: well inside the 90 days' retention.
    let n = 10_800i64;
    let start = app.service.now_ns() - (n + 3_600) * 1_000_000_000;
    for chunk in (0..n).collect::<Vec<_>>().chunks(2_000) {
        let samples: Vec<serde_json::Value> = chunk
            .iter()
            .map(|k| {
                let wobble = (*k as f64 * 0.1).sin() * 0.01;
                serde_json::json!({"link": "G_from_B", "time": start + k * 1_000_000_000,
                                   "pose": {"t_mm": [1.0 + wobble, 2.0, 3.0], "q_wxyz": [1, 0, 0, 0]}})
            })
            .collect();
        let (status, body) = app
            .post_json("/api/v1/samples", &serde_json::json!({"samples": samples}))
            .await;
        assert_eq!(status, StatusCode::OK, "{body}");
    }
    app.set_straight_reference().await;
    let under = app.service.prune_report().await.unwrap();
    let used = under.budget.unwrap().used_bytes_after;
    assert_eq!(
        under.budget.unwrap().rows(),
        0,
        "under its budget nothing goes"
    );
    assert!(app.service.storage_problem().is_none());

    // The same file under a budget of 70 % of what it uses.
    let budget_bytes = used * 7 / 10;
    let app = app.restart(Some(&site(budget_bytes as f64 / 1e6))).await;
    let count = |source: &'static str| {
        let app = &app;
        async move {
            let (_, s) = app
                .get(&format!("/api/v1/targets/G/stats?source={source}"))
                .await;
            s["count"].as_u64().unwrap()
        }
    };
    let (filtered_before, raw_before) = (count("filtered").await, count("raw").await);
    let coarse = format!(
        "/api/v1/targets/G/history?max_points=6&from={start}&to={}",
        start + n * 1_000_000_000
    );
    let (_, coarse_before) = app.get(&coarse).await;
    assert!(
        coarse_before["count"][0].as_i64().unwrap() > 0,
        "{coarse_before}"
    );
    let pruned = app.service.prune_report().await.unwrap();
    let cut = pruned.budget.unwrap();
    assert_eq!(
        (pruned.samples, pruned.results),
        (0, 0),
        "nothing is old by age"
    );
    assert!(cut.used_bytes_before > budget_bytes, "{cut:?}");
    assert!(
        cut.used_bytes_after <= budget_bytes / 10 * 9,
        "{cut:?} {budget_bytes}"
    );
    assert!(cut.samples > 0 && cut.raw_results > 0, "{cut:?}");
    assert_eq!(
        cut.unsent,
        cut.rows(),
        "the centre had acknowledged nothing"
    );
    // Raw rows go first: filtered results only once none is left (this budget needs both).
    assert!(cut.results > 0, "{cut:?}");
    let (_, left) = app.get("/api/v1/links/G_from_B/samples?limit=1").await;
    assert_eq!(
        left["samples"],
        serde_json::json!([]),
        "every sample went first"
    );
    assert_eq!((cut.samples, cut.raw_results), (n as u64, raw_before));
    assert_eq!(count("raw").await, 0);
    // Then the oldest filtered results, as counted; the newest stay.
    assert_eq!(count("filtered").await, filtered_before - cut.results);
    let (_, first) = app.get("/api/v1/targets/G/stats?source=filtered").await;
    let first_left = brokenray::clock::parse_query_time(first["from"].as_str().unwrap()).unwrap();
    assert!(first_left >= cut.results_before_ns.unwrap(), "{first}");
    let (_, coarse_after) = app.get(&coarse).await;
    assert_eq!(
        coarse_before["count"], coarse_after["count"],
        "rollups stay"
    );
    let (status, _) = app.get("/api/v1/targets/G/reference").await;
    assert_eq!(status, StatusCode::OK, "the reference stays");

    // Said, not hidden: the health check (still 200) and the metrics.
    let (status, health) = app.get("/healthz").await;
    assert_eq!(status, StatusCode::OK);
    let problem = health["storage_problem"].as_str().unwrap();
    assert!(
        problem.contains(&format!("{} rows younger than their retention", cut.rows()))
            && problem.contains(&format!("{} of them not yet acknowledged", cut.unsent)),
        "{problem}"
    );
    let (status, metrics) = app.request("GET", "/metrics", None, None).await;
    assert_eq!(status, StatusCode::OK);
    let metrics = metrics.as_str().unwrap_or_default().to_owned();
    assert!(
        metrics.contains(&format!(
            "brokenray_budget_unsent_removed_total {}",
            cut.unsent
        )),
        "{metrics}"
    );
    // And it measures on.
    let (status, body) = app
        .post_json(
            "/api/v1/samples",
            &serde_json::json!({"samples": [{"link": "G_from_B", "time": app.service.now_ns() - 1_000_000_000,
                                            "pose": {"t_mm": [1.0, 2.0, 3.0], "q_wxyz": [1, 0, 0, 0]}}]}),
        )
        .await;
    assert_eq!(status, StatusCode::OK, "{body}");
}
