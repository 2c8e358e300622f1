//! What small hostile requests cost the running service (the release binary, its own process,
//! on loopback), with the health check polled every 50 ms throughout:
//!
//! 1. a centre (on a throwaway PostgreSQL cluster) under three concurrent zstd bombs to
//!    `/sync` (about 20 KB each, 200 MB of JSON once inflated);
//! 2. a site under sixteen concurrent 1280 x 1024 PNG frames whose colour profile inflates to
//!    400 MB each.
//!
//! Printed: the answers, the server's peak resident set above idle (`VmHWM` against `VmRSS`
//! before), and the slowest `/healthz` answer. Run: `cargo bench --bench bombs` (Linux,
//! PostgreSQL 15 as `scripts/test` installs it).

#[path = "../tests/suite/common/hostile.rs"]
mod hostile;
#[path = "../tests/suite/common/postgres.rs"]
mod postgres;
#[path = "../tests/suite/common/process.rs"]
#[allow(dead_code, reason = "the bench lets Drop stop the server")]
mod process;

use std::time::Duration;

/// Posts `n` copies of `body` at once to `url`; the statuses, counted.
async fn burst(
    url: String,
    content_type: &'static str,
    encoding: Option<&'static str>,
    body: Vec<u8>,
    n: usize,
) -> std::collections::BTreeMap<u16, usize> {
    let client = reqwest::Client::new();
    let posts: Vec<_> = (0..n)
        .map(|_| {
            let mut post = client
                .post(url.clone())
                .header("content-type", content_type)
                .body(body.clone());
            if let Some(e) = encoding {
                post = post.header("content-encoding", e);
            }
            tokio::spawn(async move { post.send().await.map(|r| r.status().as_u16()) })
        })
        .collect();
    let mut statuses = std::collections::BTreeMap::new();
    for p in posts {
        *statuses.entry(p.await.unwrap().unwrap_or(0)).or_insert(0) += 1;
    }
    statuses
}

async fn measure(
    what: &str,
    server: &process::Server,
    url: String,
    content_type: &'static str,
    encoding: Option<&'static str>,
    body: Vec<u8>,
    n: usize,
) {
    let pid = server.child.id();
    let (idle_mb, _) = hostile::rss_mb(pid);
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let health = tokio::spawn(hostile::watch_health(server.base.clone(), stop_rx));
    let started = std::time::Instant::now();
    let statuses = burst(url, content_type, encoding, body.clone(), n).await;
    let took = started.elapsed();
    stop_tx.send(true).unwrap();
    let seen = health.await.unwrap();
    let (_, peak_mb) = hostile::rss_mb(pid);
    println!(
        "{what}: {n} x {} KB -> statuses {statuses:?} in {:.2} s; peak RSS {peak_mb:.0} MB, \
         {:.0} MB above idle ({idle_mb:.0} MB); /healthz {} asked, {} failed, slowest {:.1} ms",
        body.len() / 1024,
        took.as_secs_f64(),
        peak_mb - idle_mb,
        seen.asked,
        seen.failed,
        seen.slowest.as_secs_f64() * 1e3
    );
}

fn main() {
    if std::env::args().any(|a| a == "--test") || !std::env::args().any(|a| a == "--bench") {
        println!("bombs bench: run with `cargo bench --bench bombs`");
        return;
    }
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let dir = tempfile::tempdir().unwrap();
        let url = postgres::fresh_database();
        let centre = process::start(
            &hostile::builtin_installation(dir.path(), &url, "[central]\nenabled = true\n"),
            "warn,brokenray=info",
            false,
            Duration::from_secs(120),
        );
        // Warm the centre's pools with one ordinary report.
        reqwest::Client::new()
            .post(format!("{}/api/v1/sites/s1/sync", centre.base))
            .json(&serde_json::json!({"outbox_id": "a", "registry": {"links": [], "targets": []}}))
            .send()
            .await
            .unwrap();
        measure(
            "centre, zstd bombs to /sync",
            &centre,
            format!("{}/api/v1/sites/s1/sync", centre.base),
            "application/json",
            Some("zstd"),
            hostile::zstd_bomb(40_000_000),
            3,
        )
        .await;
        drop(centre);

        let db = dir.path().join("site.db");
        let site = process::start(
            &hostile::builtin_installation(dir.path(), &db.display().to_string(), ""),
            "warn,brokenray=info",
            false,
            Duration::from_secs(120),
        );
        let time = brokenray::clock::format_ns(brokenray::clock::wall_now_ns() - 1_000_000_000);
        measure(
            "site, colour-profile bombs to /frames",
            &site,
            format!("{}/api/v1/frames?camera=C1&time={time}", site.base),
            "image/png",
            None,
            hostile::colour_profile_bomb(1280, 1024, 400),
            16,
        )
        .await;
    });
}
