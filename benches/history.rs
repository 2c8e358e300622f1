//! History query latency over 10 million stored filtered results (one target, 25 Hz, about 4.6
//! days): 24 h and full-range queries at `max_points=2000`, through the router in process.
//!
//! Run: `cargo bench --bench history` (`RESULTS` sets the count; `BACKENDS` the stores, by
//! default `sqlite,postgres`, PostgreSQL in a throwaway cluster of this run; each database is
//! built once per run, which takes minutes).

use axum::body::Body;
use axum::http::Request;
use brokenray::api::{AppState, router};
use brokenray::service::Service;
use http_body_util::BodyExt;
use std::time::Instant;
use support::{PERIOD_NS, T0};
use tower::ServiceExt;

mod support;

#[path = "../tests/suite/common/postgres.rs"]
mod postgres;

fn main() {
    if std::env::args().any(|a| a == "--test") || !std::env::args().any(|a| a == "--bench") {
        println!("history latency bench: run with `cargo bench --bench history`");
        return;
    }
    let n: i64 = std::env::var("RESULTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(10_000_000);
    let dir = tempfile::tempdir().expect("temp dir");
    let backends = std::env::var("BACKENDS").unwrap_or_else(|_| "sqlite,postgres".into());
    for backend in backends.split(',').map(str::trim) {
        let database = match backend {
            "sqlite" => dir.path().join("history.sqlite").display().to_string(),
            "postgres" => postgres::fresh_database(),
            other => panic!("BACKENDS: unknown backend `{other}` (sqlite, postgres)"),
        };
        println!("== backend: {backend}");
        measure(&database, n);
    }
}

/// Fills `database` with `n` results and times history queries on it.
fn measure(database: &str, n: i64) {
    let text = format!(
        "[server]\ndatabase = \"{}\"\n[[links]]\nname = \"G_from_B\"\nkind = \"measured\"\nsigma = {{ rotation_arcsec = 30.0, translation_mm = 1.0 }}\nexpected_rate_hz = 25.0\n[[targets]]\nname = \"G\"\nbase = \"B\"\n",
        database
    );
    let inst = brokenray::config::parse("bench.toml", &text).expect("config");
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    runtime.block_on(async {
        let build = Instant::now();
        support::fill_filtered_results(&inst, n).await;
        println!(
            "built {n} filtered results in {:.1} s",
            build.elapsed().as_secs_f64()
        );
        // On PostgreSQL the results lie before the partitions made at start-up: a retention
        // pass that removes nothing moves them into day partitions of their own.
        let settle = Instant::now();
        {
            let (store, mut write) = brokenray::store::open(&inst, 0).await.expect("open");
            let mut tx = write.begin(0).await.expect("begin");
            tx.prune(i64::MIN, i64::MIN, Default::default()).await.expect("maintenance");
            tx.commit().await.expect("commit");
            write.close().await.expect("close");
            store.close().await;
        }
        println!(
            "a retention pass that removes nothing (PostgreSQL: rows into day partitions) in {:.1} s",
            settle.elapsed().as_secs_f64()
        );

        let (service, _pipeline) = Service::start(inst).await.expect("service");
        let app = router(AppState::new(service).expect("the frame archive"));
        let last = T0 + (n - 1) * PERIOD_NS;
        let day = 86_400 * 1_000_000_000i64;
        for (label, uri) in [
            (
                "last 24 h",
                format!(
                    "/api/v1/targets/G/history?from={}&to={}&max_points=2000",
                    last - day,
                    last
                ),
            ),
            (
                "full range",
                "/api/v1/targets/G/history?max_points=2000".to_owned(),
            ),
            (
                "full range, csv",
                "/api/v1/targets/G/history?max_points=2000&format=csv".to_owned(),
            ),
        ] {
            let mut times = Vec::new();
            for _ in 0..21 {
                let t = Instant::now();
                let resp = app
                    .clone()
                    .oneshot(Request::get(&uri).body(Body::empty()).expect("request"))
                    .await
                    .expect("response");
                assert!(resp.status().is_success());
                let bytes = resp.into_body().collect().await.expect("body").to_bytes();
                times.push(t.elapsed().as_secs_f64() * 1e3);
                assert!(!bytes.is_empty());
            }
            times.sort_by(f64::total_cmp);
            println!(
                "history {label}: median {:.1} ms, max {:.1} ms (21 queries, max_points=2000)",
                times[10], times[20]
            );
        }
    });
}
