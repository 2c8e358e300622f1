//! What hostile or heavy requests cost the running service (the release binary, its own
//! process, on loopback):
//!
//! 1. the peak memory of a `max_body_bytes` (32 MiB) body of invalid samples, and its answer;
//! 2. `/stats` over `RESULTS` (default 4,000,000) stored results: time and peak memory above
//!    idle;
//! 3. `/healthz` latency with `IDLE` (default 2000) idle connections open.
//!
//! Memory is the server's `VmHWM` (peak resident set) from `/proc`, read before and after.
//!
//! Run: `cargo bench --bench robustness` (Linux).

#[path = "../tests/suite/common/hostile.rs"]
mod hostile;
#[path = "../tests/suite/common/process.rs"]
#[allow(
    dead_code,
    reason = "the bench lets Drop stop the server; the tests kill it"
)]
mod process;
mod support;

use hostile::rss_mb;

use process::Server;

use std::time::{Duration, Instant};

fn start(config: &std::path::Path) -> Server {
    process::start(
        config,
        "warn,brokenray=info",
        false,
        Duration::from_secs(120),
    )
}

fn config(dir: &std::path::Path, extra: &str) -> std::path::PathBuf {
    let text = format!(
        "[server]\nlisten = \"127.0.0.1:0\"\ndatabase = \"{}\"\nheader_timeout_s = 120\n{extra}\n\
         [[links]]\nname = \"G_from_B\"\nkind = \"measured\"\n\
         sigma = {{ rotation_arcsec = 30.0, translation_mm = 1.0 }}\nexpected_rate_hz = 25.0\n\
         [[targets]]\nname = \"G\"\nbase = \"B\"\n",
        dir.join("robustness.sqlite").display()
    );
    let path = dir.join("robustness.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// Fills the database with `n` filtered results (one target, 25 Hz).
async fn fill(config: &std::path::Path, n: i64) {
    let text = std::fs::read_to_string(config).unwrap();
    let inst = brokenray::config::parse("bench.toml", &text).expect("config");
    support::fill_filtered_results(&inst, n).await;
}

fn main() {
    if std::env::args().any(|a| a == "--test") || !std::env::args().any(|a| a == "--bench") {
        println!("robustness bench: run with `cargo bench --bench robustness`");
        return;
    }
    let n: i64 = std::env::var("RESULTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(4_000_000);
    let idle: usize = std::env::var("IDLE")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2000);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let client = reqwest::Client::new();

    // 1. A 32 MiB body of junk, on an empty database.
    let junk_dir = tempfile::tempdir().unwrap();
    let junk_config = config(junk_dir.path(), "");
    {
        let server = start(&junk_config);
        std::thread::sleep(Duration::from_millis(500));
        let (idle_mb, _) = rss_mb(server.child.id());
        let limit = 32 * 1024 * 1024;
        let item = "{\"link\": 1},";
        let mut body = String::with_capacity(limit);
        body.push_str("{\"samples\": [");
        while body.len() + item.len() + 16 < limit {
            body.push_str(item);
        }
        body.push_str("{\"link\": 1}]}");
        let items = body.matches("link").count();
        let t = Instant::now();
        let (status, answer_len) = runtime.block_on(async {
            let r = client
                .post(format!("{}/api/v1/samples", server.base))
                .header("content-type", "application/json")
                .body(body)
                .send()
                .await
                .unwrap();
            let status = r.status();
            (status, r.bytes().await.unwrap().len())
        });
        let elapsed = t.elapsed();
        let (now_mb, peak_mb) = rss_mb(server.child.id());
        println!(
            "junk body: 32 MiB, {items} invalid items: {status}, answer {answer_len} bytes in {:.2} s; \
             server RSS idle {idle_mb:.0} MB, peak {peak_mb:.0} MB (+{:.0} MB), after {now_mb:.0} MB",
            elapsed.as_secs_f64(),
            peak_mb - idle_mb
        );
    }

    // 2. /stats over n results.
    let dir = tempfile::tempdir().unwrap();
    let stats_config = config(dir.path(), "");
    let build = Instant::now();
    runtime.block_on(fill(&stats_config, n));
    println!(
        "built {n} filtered results in {:.1} s",
        build.elapsed().as_secs_f64()
    );
    let server = start(&stats_config);
    std::thread::sleep(Duration::from_millis(500));
    // Warm the page cache and the connections once, as a running service would be.
    let url = format!("{}/api/v1/targets/G/stats?source=filtered", server.base);
    let (idle_mb, _) = rss_mb(server.child.id());
    for round in 0..3 {
        let t = Instant::now();
        let answer: serde_json::Value = runtime
            .block_on(async { client.get(&url).send().await.unwrap().json().await.unwrap() });
        let (_, peak_mb) = rss_mb(server.child.id());
        println!(
            "stats over {} results (round {round}): {:.2} s; server RSS idle {idle_mb:.0} MB, peak {peak_mb:.0} MB (+{:.0} MB)",
            answer["count"],
            t.elapsed().as_secs_f64(),
            peak_mb - idle_mb
        );
    }

    // 3. /healthz with many idle connections open.
    let addr = server.base.trim_start_matches("http://").to_owned();
    let conns: Vec<std::net::TcpStream> = (0..idle)
        .filter_map(|_| std::net::TcpStream::connect(&addr).ok())
        .collect();
    std::thread::sleep(Duration::from_millis(500));
    let mut times: Vec<f64> = (0..50)
        .map(|_| {
            let t = Instant::now();
            let ok = runtime.block_on(async {
                reqwest::Client::new()
                    .get(format!("{}/healthz", server.base))
                    .send()
                    .await
                    .is_ok_and(|r| r.status().is_success())
            });
            assert!(ok, "healthz failed with {} idle connections", conns.len());
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(f64::total_cmp);
    println!(
        "healthz with {} idle connections open: median {:.2} ms, max {:.2} ms (50 requests, each on a new connection)",
        conns.len(),
        times[25],
        times[49]
    );
    drop(conns);
}
