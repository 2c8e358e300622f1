//! A period's report of 30 days of one-second results (raw and filtered, with a deformation,
//! twenty ten-minute gaps and a hundred alarm transitions): the time `GET /api/v1/report` takes
//! through the router in process, and the memory it takes (the process' peak resident set,
//! reset before the reports, less what was resident before them).
//!
//! Run: `cargo bench --bench report` (`DAYS` sets the period, default 30; `BACKENDS` the stores,
//! by default `sqlite,postgres`, PostgreSQL in a throwaway cluster of this run).

use axum::body::Body;
use axum::http::Request;
use brokenray::bank::ResultSource;
use brokenray::deformation::SmallMotion;
use brokenray::geometry::{Mat6, Pose, PoseCov, ReportedSigmas, rotation_from_euler};
use brokenray::model::TargetId;
use brokenray::store::NewResult;
use http_body_util::BodyExt;
use nalgebra::Translation3;
use std::time::Instant;
use tower::ServiceExt;

#[path = "../tests/suite/common/postgres.rs"]
mod postgres;

/// The first result: 2026-10-01T00:00:00Z.
const T0: i64 = 1_790_812_800_000_000_000;
const SECOND: i64 = 1_000_000_000;

fn main() {
    if std::env::args().any(|a| a == "--test") || !std::env::args().any(|a| a == "--bench") {
        println!("report bench: run with `cargo bench --bench report`");
        return;
    }
    let days: i64 = std::env::var("DAYS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(30);
    let dir = tempfile::tempdir().expect("temp dir");
    let backends = std::env::var("BACKENDS").unwrap_or_else(|_| "sqlite,postgres".into());
    for backend in backends.split(',').map(str::trim) {
        let database = match backend {
            "sqlite" => dir.path().join("report.sqlite").display().to_string(),
            "postgres" => postgres::fresh_database(),
            other => panic!("BACKENDS: unknown backend `{other}` (sqlite, postgres)"),
        };
        println!("== backend: {backend}");
        measure(&database, days);
    }
}

/// Whether second `k` lies in one of the twenty ten-minute gaps, spread over the period.
fn in_gap(k: i64, n: i64) -> bool {
    let spacing = n / 20;
    k % spacing >= spacing / 2 && k % spacing < spacing / 2 + 600
}

fn result(k: i64, source: ResultSource) -> NewResult {
    let t = k as f64;
    let sway = (t / 3600.0).sin();
    let noise = if source == ResultSource::Raw {
        ((k * 7919) % 101) as f64 / 101.0 - 0.5
    } else {
        0.0
    };
    let rx = 4.0 * sway + 2.0 * noise + 1e-5 * t;
    let pose = Pose::from_parts(
        Translation3::new(0.2 * sway + 0.02 * noise, -2952.0, 532.0),
        rotation_from_euler([-0.0718 + rx / 3600.0, 0.026, 2.87]).expect("rotation"),
    );
    let sigma = if source == ResultSource::Raw {
        3.0
    } else {
        0.8
    };
    NewResult {
        target: TargetId(0),
        source,
        time_ns: T0 + k * SECOND,
        estimate: brokenray::deformation::MeasuredPose {
            whole: PoseCov {
                pose,
                cov: Mat6::identity() * 1e-9,
            },
            systematic_cov: Mat6::identity() * 1e-10,
            calibration: Some(brokenray::deformation::CalibrationStamp(0)),
        },
        status: brokenray::bank::TargetStatus::Ok,
        age_s: 0.0,
        chi2: None,
        deformation: Some((
            1,
            SmallMotion {
                rotation_arcsec: [rx, 0.5 * sway, -0.3 * sway],
                translation_mm: [0.2 * sway, 0.01 * noise, 0.0],
                sigmas: ReportedSigmas {
                    rotation_arcsec: [sigma; 3],
                    translation_mm: [0.05; 3],
                },
            },
        )),
    }
}

/// The process' resident set now and at its peak (kB), from `/proc/self/status`.
fn resident_kb() -> (u64, u64) {
    let status = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    let field = |name: &str| {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    };
    (field("VmRSS:"), field("VmHWM:"))
}

/// Fills `database` with `days` of one-second results and times reports of the whole period.
fn measure(database: &str, days: i64) {
    let text = format!(
        "[server]\ndatabase = \"{database}\"\n[[links]]\nname = \"G_from_B\"\nkind = \"measured\"\n\
         sigma = {{ rotation_arcsec = 3.0, translation_mm = 0.05 }}\nexpected_rate_hz = 1.0\n\
         [[targets]]\nname = \"G\"\nbase = \"B\"\n"
    );
    let inst = brokenray::config::parse("bench.toml", &text).expect("config");
    let n = days * 86_400;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    runtime.block_on(async {
        let build = Instant::now();
        {
            let (store, mut write) = brokenray::store::open(&inst, 0).await.expect("open");
            let chunk = 100_000;
            for start in (0..n).step_by(chunk) {
                let rows: Vec<NewResult> = (start..(start + chunk as i64).min(n))
                    .filter(|k| !in_gap(*k, n))
                    .flat_map(|k| [result(k, ResultSource::Raw), result(k, ResultSource::Filtered)])
                    .collect();
                let mut tx = write.begin(0).await.expect("begin");
                tx.insert_results(&[&rows]).await.expect("insert");
                tx.commit().await.expect("commit");
            }
            // A hundred alarm transitions, half of them acknowledged.
            let mut tx = write.begin(0).await.expect("begin");
            for i in 0..100 {
                use brokenray::alarms::{AlarmKind, Level, Transition, ValueUnit};
                let (from, to) = if i % 2 == 0 {
                    (Level::None, Level::Warn)
                } else {
                    (Level::Warn, Level::None)
                };
                let transition = Transition {
                    kind: AlarmKind::Deformation,
                    time_ns: T0 + (i * n / 100 + 1) * SECOND,
                    from,
                    to,
                    value: 61.0,
                    unit: ValueUnit::Arcsec,
                    message: format!("deformation {} -> {}: 61.0 arcsec", from.name(), to.name()),
                };
                tx.insert_alarm(TargetId(0), &transition, T0).await.expect("alarm");
            }
            tx.commit().await.expect("commit");
            // On PostgreSQL the results lie before the partitions made at start-up: a
            // retention pass that removes nothing moves them into day partitions of their own.
            let mut tx = write.begin(0).await.expect("begin");
            tx.prune(i64::MIN, i64::MIN, Default::default())
                .await
                .expect("maintenance");
            tx.commit().await.expect("commit");
            write.close().await.expect("close");
            store.close().await;
        }
        println!(
            "built {} raw and as many filtered results ({days} days at 1 Hz, 20 gaps of 10 min) in {:.1} s",
            n - (0..n).filter(|k| in_gap(*k, n)).count() as i64,
            build.elapsed().as_secs_f64()
        );

        let (service, _pipeline) = brokenray::service::Service::start(inst)
            .await
            .expect("service");
        let app = brokenray::api::router(
            brokenray::api::AppState::new(service).expect("the frame archive"),
        );
        let uri = format!(
            "/api/v1/report?from={}&to={}",
            T0,
            T0 + n * SECOND
        );
        // Reset the peak resident set (Linux: `5` into clear_refs), so that the peak read
        // after the reports is theirs, not the fill's.
        let _ = std::fs::write("/proc/self/clear_refs", "5");
        let (before_kb, _) = resident_kb();
        let mut times = Vec::new();
        let mut size = 0;
        for _ in 0..5 {
            let t = Instant::now();
            let resp = app
                .clone()
                .oneshot(Request::get(&uri).body(Body::empty()).expect("request"))
                .await
                .expect("response");
            assert!(resp.status().is_success(), "{}", resp.status());
            let bytes = resp.into_body().collect().await.expect("body").to_bytes();
            times.push(t.elapsed().as_secs_f64());
            size = bytes.len();
            let page = String::from_utf8_lossy(&bytes);
            assert!(page.contains("20 gaps"), "the gaps are found");
        }
        let (_, peak_kb) = resident_kb();
        times.sort_by(f64::total_cmp);
        println!(
            "report of {days} days: median {:.2} s, max {:.2} s (5 reports, {} kB page); \
             peak resident set {:.0} MB over the {:.0} MB before",
            times[2],
            times[4],
            size / 1000,
            peak_kb.saturating_sub(before_kb) as f64 / 1e3,
            before_kb as f64 / 1e3
        );
    });
}
