//! Load generator: ingest over HTTP on loopback and compensation latency, against the release
//! binary in its own process, on each store backend in turn, with two raw SQLite baselines:
//! the samples alone inserted into the samples table, and (SQLite backend) every row the
//! service stored in the run written again in the service's own commits. Prints its figures.
//!
//! Run: `cargo bench --bench ingest` (options through the environment: `BACKENDS`
//! (`sqlite,postgres`: PostgreSQL in a throwaway cluster of this run, fsync and synchronous
//! commit on), `CLIENTS` (4),
//! `BATCHES` (300), `BATCH` (1000 samples), `SSE_CLIENTS` (0): that many clients reading
//! `/api/v1/events` while the batches go in; `BROKENRAY_BIN`: another build of the binary to
//! measure, for A/B comparisons; `EXACT_CAMERAS=1`: the built-in cameras without their
//! `intrinsics_covariance` (for a build that predates it, or to measure what it costs);
//! `OUTPUTS=1`: the plant's three outputs on (an MQTT broker this run starts, `mosquitto`, with a
//! subscriber reading everything; a Modbus server polled for a target's block ten times a
//! second; NMEA sentences to a UDP socket of this run), for A/B runs against `OUTPUTS=0`;
//! `PG_LOG`: print the PostgreSQL cluster's log at the end, with
//! `BROKENRAY_PG_SETTINGS="-c log_min_duration_statement=3"` the slow statements).

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

#[path = "../tests/suite/common/postgres.rs"]
mod postgres;

const T0: i64 = 1_795_255_200_000_000_000;
const LINKS: [(&str, [f64; 3], [f64; 4]); 3] = [
    (
        "C1_from_B",
        [-20.0, 10.0, 2991.7],
        [0.0118, 0.9999, 0.0108, -0.0002],
    ),
    ("C2_from_M", [0.0, 0.0, 3156.6], [0.0, 1.0, 0.0, 0.0]),
    (
        "C3_from_G",
        [-25.0, -40.0, 2999.6],
        [0.0021, 0.2167, 0.9762, 0.0017],
    ),
];

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Batch `b` of `n` samples: groups of the three links at 25 Hz, with a little noise.
fn batch_body(b: usize, n: usize) -> String {
    let mut s = String::with_capacity(n * 120);
    s.push_str("{\"samples\":[");
    let groups = n / 3;
    for g in 0..groups {
        let k = (b * groups + g) as i64;
        let time = T0 + k * 40_000_000;
        for (i, (link, t, q)) in LINKS.iter().enumerate() {
            if g > 0 || i > 0 {
                s.push(',');
            }
            let noise =
                ((k as f64 * 12.9898 + i as f64 * 78.233).sin() * 43758.5453).fract() * 0.05;
            s.push_str(&format!(
                "{{\"link\":\"{link}\",\"time\":{time},\"pose\":{{\"t_mm\":[{:.4},{:.4},{:.4}],\"q_wxyz\":[{},{},{},{}]}}}}",
                t[0] + noise,
                t[1] - noise,
                t[2] + noise,
                q[0],
                q[1],
                q[2],
                q[3]
            ));
        }
    }
    s.push_str("]}");
    s
}

fn peak_rss_mb(pid: u32) -> f64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("VmHWM:")).and_then(|l| {
                l.split_whitespace()
                    .nth(1)
                    .and_then(|v| v.parse::<f64>().ok())
            })
        })
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// A new SQLite file with the service's pragmas: WAL, `synchronous = FULL`.
fn open_like_the_service(path: &std::path::Path) -> rusqlite::Connection {
    let conn = rusqlite::Connection::open(path).expect("open");
    conn.pragma_update(None, "journal_mode", "WAL")
        .expect("wal");
    conn.pragma_update(None, "synchronous", "FULL")
        .expect("sync");
    conn
}

/// The raw baseline: the first migration's samples table, one prepared statement, one
/// transaction per batch.
fn raw_sqlite_baseline(dir: &std::path::Path, batches: usize, n: usize) -> f64 {
    let path = dir.join("raw.sqlite");
    let conn = open_like_the_service(&path);
    let schema = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/migrations/0001_initial.sql"
    ))
    .expect("schema");
    conn.execute_batch(&schema).expect("schema");
    conn.execute("insert into links (link_id, name, created_ns) values (1, 'a', 0), (2, 'b', 0), (3, 'c', 0)", [])
        .expect("links");
    let mut conn = conn;
    let start = Instant::now();
    for b in 0..batches {
        let tx = conn.transaction().expect("tx");
        {
            let mut stmt = tx
                .prepare_cached(
                    "insert into samples (link_id, time_ns, tx_mm, ty_mm, tz_mm, qw, qx, qy, qz, uncertainty_kind, \
                     uncertainty, reprojection_rms_px, points, disposition, outlier, nis, received_ns) \
                     values (?, ?, ?, ?, ?, ?, ?, ?, ?, 0, null, null, null, 'fused', 0, 1.0, 0)",
                )
                .expect("prepare");
            for g in 0..n / 3 {
                let k = (b * (n / 3) + g) as i64;
                for (i, (_, t, q)) in LINKS.iter().enumerate() {
                    stmt.execute(rusqlite::params![
                        i as i64 + 1,
                        T0 + k * 40_000_000,
                        t[0],
                        t[1],
                        t[2],
                        q[0],
                        q[1],
                        q[2],
                        q[3]
                    ])
                    .expect("insert");
                }
            }
        }
        tx.commit().expect("commit");
    }
    (batches * (n / 3) * 3) as f64 / start.elapsed().as_secs_f64()
}

/// SQLite alone writing the service's own rows: every row the service stored during the run
/// (`service_db`, read after it stopped) inserted again into a fresh database of the same
/// schema (every migration), one transaction per commit of the service, in its order, with
/// prepared statements, the same pragmas. Samples, results, alarms and commit numbers are
/// written once in both; the service rewrites the rollup rows and its filter state a commit
/// touches in every commit, the replay each rollup row once (at the commit of its last version)
/// and the filter state once a commit.
fn replay_service_rows(dir: &std::path::Path, service_db: &std::path::Path) -> Replay {
    use rusqlite::types::Value;
    use std::collections::BTreeMap;
    let source = rusqlite::Connection::open_with_flags(
        service_db,
        rusqlite::OpenFlags::SQLITE_OPEN_READ_ONLY,
    )
    .expect("open the service's database");
    let path = dir.join("replay.sqlite");
    let conn = open_like_the_service(&path);
    let mut migrations: Vec<_> =
        std::fs::read_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/migrations"))
            .expect("migrations")
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "sql"))
            .collect();
    migrations.sort();
    for m in &migrations {
        conn.execute_batch(&std::fs::read_to_string(m).expect("migration"))
            .expect("migration applies");
    }
    // Per commit, per table: the rows (every column, in the table's order).
    let tables = [
        "links",
        "targets",
        "commits",
        "samples",
        "results",
        "rollups",
        "alarms",
        "target_references",
        "filter_state",
    ];
    let mut per_commit: BTreeMap<i64, Vec<(usize, Vec<Value>)>> = BTreeMap::new();
    // Each table's insert, written before the clock starts.
    let mut inserts = Vec::new();
    let (mut samples, mut rows, mut bytes) = (0usize, 0usize, 0usize);
    let mut state = None;
    for (k, table) in tables.iter().enumerate() {
        let mut stmt = source
            .prepare(&format!("select * from {table}"))
            .expect("select");
        let names: Vec<String> = stmt.column_names().iter().map(|c| c.to_string()).collect();
        let seq_at = names
            .iter()
            .position(|c| c == "commit_seq" || (*table == "commits" && c == "seq"));
        let marks = vec!["?"; names.len()].join(", ");
        inserts.push(if *table == "filter_state" {
            format!("insert or replace into {table} values ({marks})")
        } else {
            format!("insert into {table} values ({marks})")
        });
        let mut q = stmt.query([]).expect("query");
        while let Some(row) = q.next().expect("row") {
            let values: Vec<Value> = (0..names.len())
                .map(|i| row.get(i).expect("value"))
                .collect();
            let seq = match seq_at {
                Some(i) => match values[i] {
                    Value::Integer(s) => s,
                    _ => 0,
                },
                None => i64::MIN,
            };
            bytes += values
                .iter()
                .map(|v| match v {
                    Value::Null => 1,
                    Value::Integer(_) | Value::Real(_) => 8,
                    Value::Text(t) => t.len(),
                    Value::Blob(b) => b.len(),
                })
                .sum::<usize>();
            rows += 1;
            if *table == "samples" {
                samples += 1;
            }
            if *table == "filter_state" {
                state = Some((k, values));
            } else {
                per_commit.entry(seq).or_default().push((k, values));
            }
        }
    }
    let state = state.expect("the service saved its filter state");
    let mut conn = conn;
    let start = Instant::now();
    for (seq, rows) in &per_commit {
        let tx = conn.transaction().expect("tx");
        for (k, values) in rows {
            tx.prepare_cached(&inserts[*k])
                .expect("prepare")
                .execute(rusqlite::params_from_iter(values.iter()))
                .expect("insert");
        }
        if *seq != i64::MIN {
            tx.prepare_cached(&inserts[state.0])
                .expect("prepare")
                .execute(rusqlite::params_from_iter(state.1.iter()))
                .expect("state");
        }
        tx.commit().expect("commit");
    }
    Replay {
        samples_per_s: samples as f64 / start.elapsed().as_secs_f64(),
        rows_per_sample: rows as f64 / samples as f64,
        bytes_per_sample: bytes as f64 / samples as f64,
        commits: per_commit.keys().filter(|seq| **seq != i64::MIN).count(),
    }
}

/// What [`replay_service_rows`] measured.
struct Replay {
    samples_per_s: f64,
    /// Rows and bytes the service stored per sample.
    rows_per_sample: f64,
    bytes_per_sample: f64,
    /// The service's commits, each one transaction of the replay (and its `fsync`).
    commits: usize,
}

fn main() {
    // Criterion-style benches also run under `cargo test --benches`: do nothing there.
    if std::env::args().any(|a| a == "--test") || !std::env::args().any(|a| a == "--bench") {
        println!("ingest load generator: run with `cargo bench --bench ingest`");
        return;
    }
    let clients = env_usize("CLIENTS", 4);
    let batches = env_usize("BATCHES", 300);
    let n = env_usize("BATCH", 1000) / 3 * 3;
    let dir = tempfile::tempdir().expect("temp dir");
    let backends = std::env::var("BACKENDS").unwrap_or_else(|_| "sqlite,postgres".into());
    for backend in backends.split(',').map(str::trim) {
        measure(backend, dir.path(), clients, batches, n);
    }
    if std::env::var_os("PG_LOG").is_some() {
        println!("{}", postgres::cluster().log());
    }
    let raw = raw_sqlite_baseline(dir.path(), batches.min(200), n);
    println!(
        "raw SQLite baseline (rusqlite, one prepared statement, one transaction per batch, WAL, synchronous=FULL): {raw:.0} samples/s"
    );
}

/// Runs the service on `backend` and measures ingest and compensation latency.
fn measure(backend: &str, dir: &std::path::Path, clients: usize, batches: usize, n: usize) {
    let config = dir.join(format!("site-{backend}.toml"));
    let database = match backend {
        "sqlite" => dir.join("bench.sqlite").display().to_string(),
        "postgres" => postgres::fresh_database(),
        other => panic!("BACKENDS: unknown backend `{other}` (sqlite, postgres)"),
    };
    println!("== backend: {backend}");
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML
        .replace("127.0.0.1:7878", "127.0.0.1:0")
        .replace(
            "database = \"brokenray.db\"",
            &format!("database = \"{database}\""),
        );
    // RERUN=off (default) | save | connect (to an address where nothing listens).
    let rerun_mode = std::env::var("RERUN").unwrap_or_else(|_| "off".into());
    let recordings = dir.join("recordings");
    let rerun_section = match rerun_mode.as_str() {
        "off" => "mode = \"off\"".to_owned(),
        "save" => format!(
            "mode = \"save\"\nrecordings_dir = \"{}\"",
            recordings.display()
        ),
        "connect" => "mode = \"connect\"\nurl = \"rerun+http://127.0.0.1:1/proxy\"".to_owned(),
        other => panic!("RERUN={other}: use off, save or connect"),
    };
    // Decimation rates other than the defaults: RERUN_SERIES_HZ, RERUN_SCENE_HZ.
    let mut rerun_section = rerun_section;
    for (var, key) in [
        ("RERUN_SERIES_HZ", "series_hz"),
        ("RERUN_SCENE_HZ", "scene_hz"),
    ] {
        if let Ok(v) = std::env::var(var) {
            let hz: f64 = v
                .parse()
                .unwrap_or_else(|_| panic!("{var}={v}: not a number"));
            rerun_section.push_str(&format!("\n{key} = {hz:?}"));
        }
    }
    let text = text.replace(
        "[rerun]\nmode = \"off\"\nrecordings_dir = \"recordings\"\nurl = \"rerun+http://127.0.0.1:9876/proxy\"\n",
        &format!("[rerun]\n{rerun_section}\n"),
    );
    println!("rerun: {rerun_mode}");
    let text = if std::env::var_os("EXACT_CAMERAS").is_some() {
        println!("cameras taken as exact (no intrinsics_covariance)");
        without_intrinsics_covariance(&text)
    } else {
        text
    };
    // OUTPUTS=1: MQTT to a broker of this run, Modbus on a free port, NMEA to a socket here.
    let outputs = std::env::var("OUTPUTS").is_ok_and(|v| v == "1");
    let mut plant = None;
    let text = if outputs {
        let p = Plant::start(dir);
        let text = format!(
            "{text}\n[[outputs.mqtt]]\nurl = \"mqtt://127.0.0.1:{}\"\nrate_hz = 25\n\n\
             [[outputs.modbus]]\nlisten = \"127.0.0.1:{}\"\n\n\
             [[outputs.nmea]]\nto = \"{}\"\nrate_hz = 10\n",
            p.mqtt_port,
            p.modbus_port,
            p.nmea.local_addr().expect("udp")
        );
        plant = Some(p);
        println!("outputs: MQTT, Modbus (polled at 10 Hz), NMEA");
        text
    } else {
        println!("outputs: none");
        text
    };
    std::fs::write(&config, text).expect("config");

    println!("preparing {batches} batches of {n} samples ...");
    let bodies: Arc<Vec<String>> = Arc::new((0..batches).map(|b| batch_body(b, n)).collect());
    let binary =
        std::env::var("BROKENRAY_BIN").unwrap_or_else(|_| env!("CARGO_BIN_EXE_brokenray").into());
    let mut child = Command::new(binary)
        .args(["serve", "--config", config.to_str().expect("utf-8 path")])
        .env("RUST_LOG", "warn,brokenray=info")
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .expect("server starts");
    let pid = child.id();
    let stderr = child.stderr.take().expect("stderr");
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(rest) = line.split("serving on http://").nth(1) {
                let _ = tx.send(rest.split('/').next().unwrap_or_default().to_owned());
            }
        }
    });
    let addr = rx
        .recv_timeout(Duration::from_secs(30))
        .expect("server address");
    let base = format!("http://{addr}");

    let mut ingest_rate = f64::NAN;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    runtime.block_on(async {
        let client = reqwest::Client::new();
        // Live subscribers, reading every event while ingest runs.
        let sse_clients = env_usize("SSE_CLIENTS", 0);
        let events_seen = Arc::new(AtomicUsize::new(0));
        let mut subscribers = Vec::new();
        for _ in 0..sse_clients {
            let (client, base, seen) = (client.clone(), base.clone(), Arc::clone(&events_seen));
            subscribers.push(tokio::spawn(async move {
                let mut resp = client.get(format!("{base}/api/v1/events")).send().await.expect("events");
                while let Ok(Some(chunk)) = resp.chunk().await {
                    let n = chunk.windows(13).filter(|w| w == b"event: result").count();
                    seen.fetch_add(n, Ordering::Relaxed);
                }
            }));
        }
        // A reference (the nominal G_from_B), so that every result carries its deformation.
        let r = client
            .post(format!("{base}/api/v1/targets/G/reference"))
            .header("content-type", "application/json")
            .body(r#"{"pose": {"t_mm": [-1283.2, -2952.2, 532.5], "euler_deg": [-4.115, 1.488, 164.442]}}"#)
            .send()
            .await
            .expect("reference");
        assert!(r.status().is_success(), "reference refused: {}", r.status());
        // The plant's clients: a Modbus poller reading the first target's block at 10 Hz.
        let poller = plant.as_ref().map(|p| {
            let addr: std::net::SocketAddr = ([127, 0, 0, 1], p.modbus_port).into();
            tokio::spawn(async move {
                use tokio_modbus::prelude::*;
                let mut ctx = tcp::connect(addr).await.expect("modbus connects");
                let mut tick = tokio::time::interval(Duration::from_millis(100));
                // Until aborted when the batches are in.
                loop {
                    tick.tick().await;
                    let read = ctx.read_holding_registers(100, 60).await;
                    assert!(read.is_ok_and(|r| r.is_ok()), "a Modbus read failed");
                }
            })
        });
        // Ingest: clients take batches from a shared counter until none are left.
        let next = Arc::new(AtomicUsize::new(0));
        let start = Instant::now();
        let mut tasks = Vec::new();
        for _ in 0..clients {
            let (client, base, bodies, next) = (client.clone(), base.clone(), Arc::clone(&bodies), Arc::clone(&next));
            tasks.push(tokio::spawn(async move {
                loop {
                    let b = next.fetch_add(1, Ordering::Relaxed);
                    if b >= bodies.len() {
                        return;
                    }
                    let r = client
                        .post(format!("{base}/api/v1/samples"))
                        .header("content-type", "application/json")
                        .body(bodies[b].clone())
                        .send()
                        .await
                        .expect("post");
                    assert!(r.status().is_success(), "ingest refused: {}", r.status());
                }
            }));
        }
        for t in tasks {
            t.await.expect("client");
        }
        let elapsed = start.elapsed().as_secs_f64();
        let total = batches * n;
        let rate = total as f64 / elapsed;
        let rss = peak_rss_mb(pid);
        if let Some(poller) = poller {
            poller.abort();
        }
        ingest_rate = rate;
        println!("ingest over HTTP: {total} samples in {elapsed:.2} s = {rate:.0} samples/s ({clients} clients, batches of {n}, durable before each answer)");
        println!("server peak RSS during ingest: {rss:.1} MB");
        // How the writer grouped the requests: commits, groups filtered while the commit
        // before was written, and requests read first (arrived out of order, so they may
        // repeat stored samples).
        let metrics = client.get(format!("{base}/metrics")).send().await.expect("metrics");
        let text = metrics.text().await.expect("metrics text");
        let counters: Vec<&str> = text
            .lines()
            .filter(|l| {
                [
                    "brokenray_commit_seconds_count ",
                    "brokenray_groups_filtered_ahead_total ",
                    "brokenray_ingest_read_first_total ",
                    "brokenray_ingest_read_during_commit_total ",
                    "brokenray_ingest_old_groups_from_store_total ",
                ]
                .iter()
                .any(|name| l.starts_with(name))
            })
            .collect();
        println!("writer: {}", counters.join(", "));
        if sse_clients > 0 {
            println!(
                "{sse_clients} event-stream clients connected, {} result events delivered to them",
                events_seen.load(Ordering::Relaxed)
            );
            for s in &subscribers {
                s.abort();
            }
        }

        // Compensation under load: a fixed rate over many connections, latency per request.
        let target_rps = env_usize("RPS", 5000);
        let seconds = 5;
        let workers = 64;
        let per_worker = target_rps / workers;
        let interval = Duration::from_secs_f64(1.0 / per_worker as f64);
        let mut tasks = Vec::new();
        let begin = Instant::now();
        for _ in 0..workers {
            let (client, base) = (client.clone(), base.clone());
            tasks.push(tokio::spawn(async move {
                let mut latencies = Vec::with_capacity(per_worker * seconds);
                let mut ticker = tokio::time::interval(interval);
                ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Burst);
                for _ in 0..per_worker * seconds {
                    ticker.tick().await;
                    let t = Instant::now();
                    let r = client.get(format!("{base}/api/v1/targets/G/compensation")).send().await.expect("get");
                    let _ = r.bytes().await.expect("body");
                    latencies.push(t.elapsed());
                }
                latencies
            }));
        }
        let mut all = Vec::new();
        for t in tasks {
            all.extend(t.await.expect("worker"));
        }
        let wall = begin.elapsed().as_secs_f64();
        all.sort();
        let pct = |p: f64| all[((all.len() as f64 * p) as usize).min(all.len() - 1)].as_secs_f64() * 1e3;
        println!(
            "GET compensation: {} requests in {wall:.2} s = {:.0} req/s, p50 {:.3} ms, p99 {:.3} ms, max {:.3} ms",
            all.len(),
            all.len() as f64 / wall,
            pct(0.50),
            pct(0.99),
            pct(1.0)
        );
    });
    // SIGTERM: the service commits, the logger closes its recording.
    let _ = Command::new("kill")
        .args(["-TERM", &pid.to_string()])
        .status();
    let _ = child.wait();
    if backend == "sqlite" {
        let replay = replay_service_rows(dir, std::path::Path::new(&database));
        println!(
            "raw SQLite writing the service's own rows ({:.2} rows and {:.0} bytes a sample, one transaction per commit of the service, {} commits): {:.0} samples/s; ingest / that: {:.2}",
            replay.rows_per_sample,
            replay.bytes_per_sample,
            replay.commits,
            replay.samples_per_s,
            ingest_rate / replay.samples_per_s
        );
    }
    if let Some(p) = plant {
        println!(
            "outputs: {} NMEA datagrams and {} MQTT lines received",
            p.nmea_datagrams(),
            p.mqtt_lines()
        );
    }
    if rerun_mode == "save" {
        let bytes: u64 = std::fs::read_dir(&recordings)
            .map(|d| {
                d.filter_map(|e| e.ok()?.metadata().ok())
                    .map(|m| m.len())
                    .sum()
            })
            .unwrap_or(0);
        println!("recordings: {:.1} MB", bytes as f64 / 1e6);
    }
}

/// The installation file without its cameras' `intrinsics_covariance` blocks.
fn without_intrinsics_covariance(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut skipping = false;
    for line in text.lines() {
        if line.starts_with("intrinsics_covariance = [") {
            skipping = !line.trim_end().ends_with(']');
            continue;
        }
        if skipping {
            skipping = line.trim() != "]";
            continue;
        }
        out.push_str(line);
        out.push('\n');
    }
    out
}

/// The plant's side of `OUTPUTS=1`: a Mosquitto broker with a subscriber, a free port for the
/// Modbus server, a UDP socket counting NMEA datagrams.
struct Plant {
    mqtt_port: u16,
    modbus_port: u16,
    nmea: std::net::UdpSocket,
    broker: std::process::Child,
    subscriber: std::process::Child,
    mqtt_out: std::path::PathBuf,
}

impl Plant {
    fn start(dir: &std::path::Path) -> Plant {
        let free = || {
            std::net::TcpListener::bind("127.0.0.1:0")
                .and_then(|l| l.local_addr())
                .expect("a free port")
                .port()
        };
        let (mqtt_port, modbus_port) = (free(), free());
        let conf = dir.join("mosquitto.conf");
        std::fs::write(
            &conf,
            format!("listener {mqtt_port} 127.0.0.1\nallow_anonymous true\npersistence false\n"),
        )
        .expect("broker config");
        let bin = ["/usr/sbin/mosquitto", "mosquitto"]
            .into_iter()
            .find(|b| std::path::Path::new(b).is_file())
            .unwrap_or("mosquitto");
        let broker = Command::new(bin)
            .arg("-c")
            .arg(&conf)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("mosquitto starts (Debian: apt-get install mosquitto)");
        for _ in 0..500 {
            if std::net::TcpStream::connect(("127.0.0.1", mqtt_port)).is_ok() {
                break;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let mqtt_out = dir.join("mqtt.txt");
        let subscriber = Command::new("mosquitto_sub")
            .args([
                "-h",
                "127.0.0.1",
                "-p",
                &mqtt_port.to_string(),
                "-t",
                "brokenray/#",
            ])
            .stdout(std::fs::File::create(&mqtt_out).expect("subscriber output"))
            .stderr(Stdio::null())
            .spawn()
            .expect("mosquitto_sub starts (Debian: apt-get install mosquitto-clients)");
        let nmea = std::net::UdpSocket::bind("127.0.0.1:0").expect("udp");
        nmea.set_nonblocking(true).expect("nonblocking");
        Plant {
            mqtt_port,
            modbus_port,
            nmea,
            broker,
            subscriber,
            mqtt_out,
        }
    }

    fn nmea_datagrams(&self) -> usize {
        let mut buf = [0u8; 256];
        std::iter::from_fn(|| self.nmea.recv(&mut buf).ok()).count()
    }

    fn mqtt_lines(&self) -> usize {
        std::fs::read_to_string(&self.mqtt_out).map_or(0, |t| t.lines().count())
    }
}

impl Drop for Plant {
    fn drop(&mut self) {
        let _ = self.subscriber.kill();
        let _ = self.subscriber.wait();
        let _ = self.broker.kill();
        let _ = self.broker.wait();
    }
}
