//! A fleet's uploads, measured: release binaries in their own processes, a centre on a
//! throwaway PostgreSQL cluster (fsync and synchronous commit on), sites on SQLite, all on
//! loopback on this machine. Prints its figures.
//!
//! 1. Steady state: a site measuring at 25 Hz (one target, three links) with the centre up,
//!    for `STEADY_S` (60) seconds: bytes sent per tier and second (kbit/s).
//! 2. Catch-up: a site cut off for `HOURS` (24) of 25 Hz measurement, then the centre back:
//!    the time to deliver the events and results tiers (raw samples not sent, `raw_kbit_s = 0`),
//!    rows/s, bytes per hour of measurement per tier, compression ratios.
//! 3. Raw samples: a site with `RAW_HOURS` (2) of backlog sends its raw tier unbudgeted:
//!    sample rows applied per second at the centre; then four such sites at once.
//! 4. The centre alone: the raw tier of the same backlog, read and compressed into uploads
//!    beforehand (as the site would send them), posted by one client as fast as the centre
//!    answers, then by four clients for four sites at once: the sample rows the centre
//!    applies per second, without the sites' own work on the same two cores.
//!
//! Run: `cargo bench --bench fleet` (Linux; PostgreSQL 15 with pg_partman installed);
//! `CENTRE_ONLY=1` runs only phase 4 (with the backlog it needs).

#[path = "../tests/suite/common/postgres.rs"]
mod postgres;
#[path = "../tests/suite/common/process.rs"]
#[allow(
    dead_code,
    reason = "the bench lets Drop stop the servers; the tests kill them"
)]
mod process;

use process::Server;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// A blocking HTTP client (an async client on a runtime of its own).
struct Http {
    rt: tokio::runtime::Runtime,
    client: reqwest::Client,
}

impl Http {
    fn new() -> Http {
        Http {
            rt: tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .expect("a runtime"),
            client: reqwest::Client::builder()
                .timeout(Duration::from_secs(600))
                .build()
                .expect("a client"),
        }
    }

    fn post_json(&self, url: &str, body: String) -> reqwest::StatusCode {
        self.rt.block_on(async {
            self.client
                .post(url)
                .header("content-type", "application/json")
                .body(body)
                .send()
                .await
                .expect("the server answers")
                .status()
        })
    }

    fn get_json(&self, url: &str) -> Value {
        self.rt.block_on(async {
            self.client
                .get(url)
                .send()
                .await
                .expect("the server answers")
                .json()
                .await
                .expect("JSON")
        })
    }
}

const T0: i64 = 1_795_255_200_000_000_000;
const TOKEN: &str = "bench-sync-token";

fn env_f64(name: &str, default: f64) -> f64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn start(config: &Path) -> Server {
    process::start(
        config,
        "warn,brokenray::cli=info",
        false,
        Duration::from_secs(300),
    )
}

/// A free loopback port (bound, then released).
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free port")
}

/// The built-in installation on `listen` with `database` and `extra`, written to `path`.
fn installation(path: &Path, listen: &str, database: &str, extra: &str) {
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML
        .replace("127.0.0.1:7878", listen)
        .replace(
            "database = \"brokenray.db\"",
            &format!("database = \"{database}\""),
        );
    std::fs::write(path, format!("{text}\n{extra}\n")).expect("installation written");
}

fn site_config(dir: &Path, name: &str, db: &Path, centre_port: u16, raw_kbit_s: f64) -> PathBuf {
    let path = dir.join(format!("{name}.toml"));
    installation(
        &path,
        "127.0.0.1:0",
        &db.display().to_string(),
        &format!(
            "[site]\nname = \"{name}\"\n\n[upstream]\nurl = \"http://127.0.0.1:{centre_port}\"\n\
             token = \"{}\"\nraw_kbit_s = {raw_kbit_s:?}\n\n[retention]\nsamples_days = 3650\nresults_days = 3650\n",
            token_of(name)
        ),
    );
    path
}

fn centre_config(dir: &Path, port: u16, url: &str, sites: &[&str]) -> PathBuf {
    let path = dir.join("centre.toml");
    let mut extra = String::from("[central]\nenabled = true\n\n");
    for site in sites {
        extra.push_str(&format!(
            "[[auth.tokens]]\nname = \"{site}\"\nsha256 = \"{}\"\nscopes = [\"sync\"]\nsite = \"{site}\"\n\n",
            brokenray::config::sha256_hex(&token_of(site))
        ));
    }
    installation(&path, &format!("127.0.0.1:{port}"), url, &extra);
    path
}

/// Each site's token.
fn token_of(site: &str) -> String {
    format!("{TOKEN}-{site}")
}

/// Posts `groups` 25 Hz groups of the three links from `T0 + first * 40 ms`.
fn post_groups(client: &Http, base: &str, first: i64, groups: i64) {
    let per_request = 3000;
    let mut k = first;
    while k < first + groups {
        let end = (k + per_request).min(first + groups);
        let mut s = String::with_capacity(((end - k) * 3 * 130) as usize);
        s.push_str("{\"samples\":[");
        for j in k..end {
            let time = T0 + j * 40_000_000;
            let noise = ((j as f64 * 12.9898).sin() * 43758.5453).fract() * 0.05;
            if j > k {
                s.push(',');
            }
            s.push_str(&format!(
                "{{\"link\":\"C1_from_B\",\"time\":{time},\"pose\":{{\"t_mm\":[{:.4},10.0,2991.7],\"euler_deg\":[178.6589,1.245,-0.0291]}}}},\
                 {{\"link\":\"C2_from_M\",\"time\":{time},\"pose\":{{\"t_mm\":[0.0,{:.4},3156.6],\"euler_deg\":[180.0,0.0,0.0]}}}},\
                 {{\"link\":\"C3_from_G\",\"time\":{time},\"pose\":{{\"t_mm\":[-25.0,-40.0,{:.4}],\"euler_deg\":[179.137,0.257,164.5782]}}}}",
                -20.0 + noise,
                noise,
                2999.6 + noise
            ));
        }
        s.push_str("]}");
        let status = client.post_json(&format!("{base}/api/v1/samples"), s);
        assert!(status.is_success(), "{status}");
        k = end;
    }
}

fn upstream(client: &Http, base: &str) -> Value {
    client.get_json(&format!("{base}/api/v1/upstream"))
}

/// Waits until the tiers named have nothing left (and no stream stopped); returns the time.
fn wait_tiers(client: &Http, base: &str, tiers: &[usize]) -> Duration {
    let start = Instant::now();
    // The uploader counts its backlog on start and with each report (every 10 s).
    std::thread::sleep(Duration::from_secs(1));
    loop {
        let u = upstream(client, base);
        for t in u["tiers"].as_array().into_iter().flatten() {
            assert!(t["stopped"].is_null(), "a stream stopped: {u:#}");
        }
        if tiers
            .iter()
            .all(|&i| u["tiers"][i]["backlog"]["rows"].as_u64() == Some(0))
        {
            return start.elapsed();
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn tier_line(u: &Value, i: usize, hours: f64, seconds: f64) {
    let t = &u["tiers"][i];
    let rows = t["sent"]["rows"].as_f64().unwrap_or(0.0);
    let bytes = t["sent"]["bytes"].as_f64().unwrap_or(0.0);
    println!(
        "  {:<8} rows {:>10.0}  rows/s {:>8.0}  bytes {:>12.0}  per hour of measurement {:>10.0} B  compression {:>5.1}x",
        t["tier"].as_str().unwrap_or("?"),
        rows,
        rows / seconds,
        bytes,
        bytes / hours,
        t["compression_ratio"].as_f64().unwrap_or(f64::NAN)
    );
}

fn main() {
    let hours = env_f64("HOURS", 24.0);
    let raw_hours = env_f64("RAW_HOURS", 2.0);
    let steady_s = env_f64("STEADY_S", 60.0);
    let dir = tempfile::tempdir().expect("a temporary folder");
    let client = Http::new();
    let url = postgres::fresh_database();
    let sites = [
        "ship-0", "ship-1", "ship-a", "ship-b", "ship-c", "ship-d", "ship-e",
    ];
    let centre_port = free_port();
    let mut all_sites = sites.to_vec();
    all_sites.extend(SOLO_SITES);
    let centre_cfg = centre_config(dir.path(), centre_port, &url, &all_sites);
    if std::env::var("CENTRE_ONLY").is_ok() {
        let raw_db = dir.path().join("raw-template.db");
        let raw_groups = (raw_hours * 3600.0 * 25.0) as i64;
        let template_cfg = site_config(dir.path(), "template", &raw_db, free_port(), 0.0);
        let template = start(&template_cfg);
        post_groups(&client, &template.base, 0, raw_groups);
        drop(template);
        let centre = start(&centre_cfg);
        centre_alone(&centre.base, &template_cfg, raw_hours);
        drop(centre);
        return;
    }
    // 1. Steady state.
    let centre = start(&centre_cfg);
    let live_db = dir.path().join("live.db");
    let live_cfg = site_config(dir.path(), "ship-0", &live_db, centre_port, 0.0);
    let live = start(&live_cfg);
    let began = Instant::now();
    let mut k = 0;
    while began.elapsed().as_secs_f64() < steady_s {
        // 25 Hz in real time, posted once a second.
        post_groups(&client, &live.base, k, 25);
        k += 25;
        std::thread::sleep(Duration::from_secs(1).saturating_sub(Duration::from_millis(5)));
    }
    std::thread::sleep(Duration::from_secs(2));
    let u = upstream(&client, &live.base);
    let seconds = began.elapsed().as_secs_f64();
    println!("steady state, {seconds:.0} s at 25 Hz (one target, three links):");
    for i in 0..2 {
        let t = &u["tiers"][i];
        println!(
            "  {:<8} {:>6.2} kbit/s  ({} batches, compression {:.1}x)",
            t["tier"].as_str().unwrap_or("?"),
            t["sent"]["bytes"].as_f64().unwrap_or(0.0) * 8.0 / seconds / 1000.0,
            t["sent"]["batches"],
            t["compression_ratio"].as_f64().unwrap_or(f64::NAN)
        );
    }
    drop(live);
    drop(centre);

    // 2. Catch-up after HOURS cut off: the site fills its outbox with the centre down.
    let site_db = dir.path().join("ship-1.db");
    let cfg = site_config(dir.path(), "ship-1", &site_db, centre_port, 0.0);
    let site = start(&cfg);
    let groups = (hours * 3600.0 * 25.0) as i64;
    let fill = Instant::now();
    post_groups(&client, &site.base, 0, groups);
    println!(
        "\nsite cut off: {hours} h of 25 Hz measurement ({groups} groups) stored in {:.0} s",
        fill.elapsed().as_secs_f64()
    );
    drop(site);
    let centre = start(&centre_cfg);
    let site = start(&cfg);
    let took = wait_tiers(&client, &site.base, &[0, 1]);
    let u = upstream(&client, &site.base);
    println!(
        "catch-up of the events and results tiers: {:.1} s",
        took.as_secs_f64()
    );
    for i in 0..2 {
        tier_line(&u, i, hours, took.as_secs_f64());
    }
    println!(
        "  raw      backlog {} rows kept (raw_kbit_s = 0)",
        u["tiers"][2]["backlog"]["rows"]
    );
    drop(site);

    // 3. Raw samples, unbudgeted: one site, then four at once.
    let raw_groups = (raw_hours * 3600.0 * 25.0) as i64;
    let raw_db = dir.path().join("raw-template.db");
    let template_cfg = site_config(dir.path(), "template", &raw_db, free_port(), 0.0);
    let template = start(&template_cfg);
    post_groups(&client, &template.base, 0, raw_groups);
    drop(template);
    let run_raw = |names: &[&str]| {
        let servers: Vec<(Server, PathBuf)> = names
            .iter()
            .map(|name| {
                let db = dir.path().join(format!("{name}.db"));
                let _ = std::fs::remove_file(&db);
                std::fs::copy(&raw_db, &db).expect("a copy of the template");
                // The template was stopped with SIGKILL: its last commits are in the WAL.
                let wal = |p: &Path| PathBuf::from(format!("{}-wal", p.display()));
                let _ = std::fs::remove_file(wal(&db));
                if wal(&raw_db).exists() {
                    std::fs::copy(wal(&raw_db), wal(&db)).expect("a copy of the WAL");
                }
                let cfg = site_config(dir.path(), name, &db, centre_port, 1e9);
                (start(&cfg), cfg)
            })
            .collect();
        let began = Instant::now();
        let mut rows = 0.0;
        for (server, _) in &servers {
            wait_tiers(&client, &server.base, &[0, 1, 2]);
            let u = upstream(&client, &server.base);
            rows += (0..3)
                .map(|i| u["tiers"][i]["sent"]["rows"].as_f64().unwrap_or(0.0))
                .sum::<f64>();
        }
        let seconds = began.elapsed().as_secs_f64();
        let samples = (raw_groups * 3) as f64 * names.len() as f64;
        println!(
            "{} site(s) at once, {raw_hours} h of backlog each, every tier: {rows:.0} rows in \
             {seconds:.1} s: {:.0} rows/s, of them {:.0} sample rows/s",
            names.len(),
            rows / seconds,
            samples / seconds
        );
        tier_line(
            &upstream(&client, &servers[0].0.base),
            2,
            raw_hours,
            seconds,
        );
    };
    println!();
    run_raw(&["ship-a"]);
    run_raw(&["ship-b", "ship-c", "ship-d", "ship-e"]);
    println!();
    centre_alone(&centre.base, &template_cfg, raw_hours);
    drop(centre);
}

/// The sites of phase 4.
const SOLO_SITES: [&str; 5] = ["solo-a", "solo-b", "solo-c", "solo-d", "solo-e"];

/// Phase 4: the raw tier of the site database behind `site_cfg`, read and compressed into
/// uploads beforehand, posted to the centre at `base` by one client, then by four at once (one
/// site each); prints the sample rows applied per second.
fn centre_alone(base: &str, site_cfg: &Path, raw_hours: f64) {
    use brokenray::fleet::protocol::{SyncRequest, ZSTD_LEVEL};
    use brokenray::store::outbox::{SyncTable, Tier};
    let inst = brokenray::config::load(site_cfg).expect("the site's installation");
    let batch_rows = inst
        .fleet
        .upstream
        .as_ref()
        .map_or(20_000, |u| u.batch_rows);
    let rt = tokio::runtime::Runtime::new().expect("a runtime");
    let prepared = Instant::now();
    let bodies: Vec<(Vec<u8>, usize, usize)> = rt.block_on(async {
        let store = brokenray::store::open_reader(&inst, 0)
            .await
            .expect("the site's store");
        let identity = store.outbox_identity().await.expect("its outbox");
        let head_seq = store.outbox_head().await.expect("its newest commit");
        let registry = store.registry().await.expect("its registry");
        let mut after = None;
        let mut bodies = Vec::new();
        let mut part = None;
        while let Some((batch, rest)) = store
            .outbox_batch(Tier::Raw, after, batch_rows, part.as_ref())
            .await
            .expect("a batch")
        {
            if rest.is_none() {
                after = Some(batch.upto_seq);
            }
            part = rest;
            let samples = batch
                .tables
                .iter()
                .filter(|t| t.table == SyncTable::Samples)
                .map(|t| t.rows())
                .sum();
            let rows = batch.rows();
            let request = SyncRequest {
                outbox_id: identity.outbox_id.clone(),
                generation: Some(identity.generation.clone()),
                lineage: identity.lineage.clone(),
                head_seq: Some(head_seq),
                registry: registry.clone(),
                batch: Some(batch.into()),
                status: None,
                backlog: Vec::new(),
                requested: None,
            };
            let json = serde_json::to_vec(&request).expect("JSON");
            bodies.push((
                zstd::bulk::compress(&json, ZSTD_LEVEL).expect("zstd"),
                samples,
                rows,
            ));
        }
        store.close().await;
        bodies
    });
    let samples: usize = bodies.iter().map(|(_, n, _)| n).sum();
    let rows: usize = bodies.iter().map(|(_, _, n)| n).sum();
    let bytes: usize = bodies.iter().map(|(b, _, _)| b.len()).sum();
    println!(
        "the centre alone: {} uploads of {batch_rows} rows ({samples} samples, {:.1} MB compressed, \
         {raw_hours} h of raw tier), prepared in {:.0} s",
        bodies.len(),
        bytes as f64 / 1e6,
        prepared.elapsed().as_secs_f64()
    );
    let post_all = |site: &str| {
        let client = Http::new();
        let url = format!("{base}/api/v1/sites/{site}/sync");
        for (body, _, _) in &bodies {
            let answer = client.rt.block_on(async {
                client
                    .client
                    .post(&url)
                    .bearer_auth(token_of(site))
                    .header("content-type", "application/json")
                    .header("content-encoding", "zstd")
                    .body(body.clone())
                    .send()
                    .await
                    .expect("the centre answers")
                    .text()
                    .await
                    .expect("an answer")
            });
            assert!(answer.contains("\"applied\""), "{site}: {answer}");
        }
    };
    let began = Instant::now();
    post_all(SOLO_SITES[0]);
    let seconds = began.elapsed().as_secs_f64();
    println!(
        "  one site:    {:.1} s, {:.0} sample rows/s ({:.0} rows/s with the raw results)",
        seconds,
        samples as f64 / seconds,
        rows as f64 / seconds
    );
    let began = Instant::now();
    std::thread::scope(|s| {
        for site in &SOLO_SITES[1..] {
            let post_all = &post_all;
            s.spawn(move || post_all(site));
        }
    });
    let seconds = began.elapsed().as_secs_f64();
    println!(
        "  four sites:  {:.1} s, {:.0} sample rows/s in all, {:.0} per site",
        seconds,
        samples as f64 * 4.0 / seconds,
        samples as f64 / seconds
    );
}
