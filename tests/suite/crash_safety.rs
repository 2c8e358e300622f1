//! The binary on a real port, killed with SIGKILL mid-stream: nothing acknowledged is lost, and
//! the compensation after a restart is the one before the kill.

use crate::common::process::{self, Server};
use crate::service::helpers::Backend;
use serde_json::{Value, json};
use std::process::Command;
use std::sync::{Arc, Mutex};
use std::time::Duration;

fn group_time(k: i64) -> i64 {
    1_795_255_200_000_000_000 + k * 40_000_000
}

/// Runs `brokenray ARGS` to completion.
fn brokenray(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_brokenray"))
        .args(args)
        .output()
        .expect("the binary runs")
}

/// Posts group `k`, which must be accepted.
async fn post_group(client: &reqwest::Client, base: &str, k: i64) {
    let r = client
        .post(format!("{base}/api/v1/samples"))
        .json(&group(k))
        .send()
        .await
        .unwrap();
    assert!(r.status().is_success(), "group {k}: {}", r.status());
}

/// Every acknowledged group is stored, on each of `links`.
async fn assert_stored(
    client: &reqwest::Client,
    base: &str,
    links: &[&str],
    acked: &[i64],
    after: &str,
) {
    for link in links {
        let stored: std::collections::HashSet<i64> =
            stored_times(client, base, link).await.into_iter().collect();
        for k in acked {
            assert!(
                stored.contains(&group_time(*k)),
                "acknowledged group {k} of {link} is missing after {after}"
            );
        }
    }
}

/// Starts `brokenray serve` and waits for the line that says where it listens.
fn start(config: &std::path::Path) -> Server {
    process::start(config, "info", true, Duration::from_secs(30))
}

/// A temporary directory with the built-in installation on port 0 and a database inside it.
fn site() -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let database = dir.path().join("db.sqlite").display().to_string();
    let config = site_with_database(&dir, &database);
    (dir, config)
}

/// The built-in installation on port 0 with `database` (a file or a URL), written into `dir`.
fn site_with_database(dir: &tempfile::TempDir, database: &str) -> std::path::PathBuf {
    let config = dir.path().join("site.toml");
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML
        .replace("127.0.0.1:7878", "127.0.0.1:0")
        .replace(
            "database = \"brokenray.db\"",
            &format!("database = \"{database}\""),
        );
    std::fs::write(&config, text).unwrap();
    config
}

/// Four writers streaming groups (every fourth each) until the server goes away; each
/// acknowledged group is recorded. A refusal fails the test unless `refusals_expected` (a
/// server stopping answers 503).
fn spawn_writers(
    client: &reqwest::Client,
    base: &str,
    acknowledged: &Arc<Mutex<Vec<i64>>>,
    refusals_expected: bool,
) -> Vec<tokio::task::JoinHandle<()>> {
    (0..4i64)
        .map(|w| {
            let (client, base, acknowledged) =
                (client.clone(), base.to_owned(), Arc::clone(acknowledged));
            tokio::spawn(async move {
                for k in (w..100_000).step_by(4) {
                    match client
                        .post(format!("{base}/api/v1/samples"))
                        .json(&group(k))
                        .send()
                        .await
                    {
                        Ok(r) if r.status().is_success() => acknowledged.lock().unwrap().push(k),
                        Ok(r) if !refusals_expected => panic!("refused: {}", r.status()),
                        _ => return,
                    }
                }
            })
        })
        .collect()
}

fn group(k: i64) -> Value {
    let time = group_time(k);
    let wobble = (k as f64 * 0.37).sin() * 0.02;
    json!({"samples": [
        {"link": "C1_from_B", "time": time, "pose": {"t_mm": [-20.0 + wobble, 10.0, 2991.7], "euler_deg": [178.6589, 1.245, -0.0291]}},
        {"link": "C2_from_M", "time": time, "pose": {"t_mm": [0.0, wobble, 3156.6], "euler_deg": [180.0, 0.0, 0.0]}},
        {"link": "C3_from_G", "time": time, "pose": {"t_mm": [-25.0, -40.0, 2999.6 + wobble], "euler_deg": [179.137, 0.257, 164.5782]}}
    ]})
}

async fn stored_times(client: &reqwest::Client, base: &str, link: &str) -> Vec<i64> {
    let v: Value = client
        .get(format!("{base}/api/v1/links/{link}/samples?limit=100000"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    v["samples"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| brokenray::clock::parse_rfc3339_ns(s["time"].as_str().unwrap()).unwrap())
        .collect()
}

on_both_backends!(multi_thread: sigkill_loses_nothing_acknowledged_and_the_restart_answers_the_same);

async fn sigkill_loses_nothing_acknowledged_and_the_restart_answers_the_same(backend: Backend) {
    let dir = tempfile::tempdir().unwrap();
    let config = site_with_database(&dir, &backend.database(&dir));
    let client = reqwest::Client::new();

    // Phase 1: four writers stream groups; the server is killed while they do.
    let server = start(&config);
    let acknowledged = Arc::new(Mutex::new(Vec::<i64>::new()));
    let writers = spawn_writers(&client, &server.base, &acknowledged, false);
    while acknowledged.lock().unwrap().len() < 300 {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    server.kill();
    for w in writers {
        w.await.unwrap();
    }
    let acked = acknowledged.lock().unwrap().clone();
    assert!(acked.len() >= 300);

    let server = start(&config);
    assert_stored(
        &client,
        &server.base,
        &["C1_from_B", "C2_from_M", "C3_from_G"],
        &acked,
        "SIGKILL",
    )
    .await;

    // Phase 2: quiet, read the compensation, kill, restart, read again.
    let next = acked.iter().max().unwrap() + 1_000;
    for k in next..next + 20 {
        post_group(&client, &server.base, k).await;
    }
    let get = |base: String| {
        let client = client.clone();
        async move {
            client
                .get(format!("{base}/api/v1/targets/G/compensation"))
                .send()
                .await
                .unwrap()
                .json::<Value>()
                .await
                .unwrap()
        }
    };
    let mut before = get(server.base.clone()).await;
    // A day-old feed on the real clock: stale, with its last value.
    assert_eq!(before["status"], "stale", "{before}");
    assert!(before["pose"].is_object(), "{before}");
    server.kill();
    let server = start(&config);
    let mut after = get(server.base.clone()).await;
    // The age counts on the server's clock (and the status follows it): only the answer's
    // substance must survive.
    let age = |v: &mut Value| {
        v["status"].take();
        v["age_s"].take().as_f64().expect("an age")
    };
    assert!(age(&mut after) >= age(&mut before));
    assert_eq!(
        before, after,
        "compensation changed across SIGKILL and restart"
    );
    server.kill();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_finishes_in_flight_writes_and_exits_cleanly() {
    let (_dir, config) = site();
    let client = reqwest::Client::new();
    let mut server = start(&config);
    let acknowledged = Arc::new(Mutex::new(Vec::<i64>::new()));
    let writers = spawn_writers(&client, &server.base, &acknowledged, true);
    while acknowledged.lock().unwrap().len() < 200 {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let status = Command::new("kill")
        .args(["-TERM", &server.child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    let exit = server.child.wait().unwrap();
    assert!(exit.success(), "SIGTERM ends the service cleanly: {exit}");
    for w in writers {
        w.await.unwrap();
    }
    let acked = acknowledged.lock().unwrap().clone();
    let server = start(&config);
    assert_stored(&client, &server.base, &["C3_from_G"], &acked, "SIGTERM").await;
    server.kill();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn backup_while_serving_gives_a_consistent_copy() {
    let (dir, config) = site();
    let out = dir.path().join("copy.sqlite");
    backup_while_serving(&config, &out, 400).await;
    // The copy is a sound database holding at least what was acknowledged before it began,
    // with whole groups only (each commit is all or nothing).
    let conn = rusqlite::Connection::open(&out).unwrap();
    let ok: String = conn
        .query_row("pragma integrity_check", [], |r| r.get(0))
        .unwrap();
    assert_eq!(ok, "ok");
    let n: i64 = conn
        .query_row("select count(*) from samples", [], |r| r.get(0))
        .unwrap();
    assert!(n >= 150 && n % 3 == 0, "{n} samples in the copy");
    assert_backup_refuses_to_overwrite(&config, &out);
}

/// Starts the service on `config`, posts 50 groups, then takes a backup to `out` while a
/// writer posts groups up to `until`, which must succeed saying so; stops the service.
async fn backup_while_serving(config: &std::path::Path, out: &std::path::Path, until: i64) {
    let client = reqwest::Client::new();
    let server = start(config);
    for k in 0..50 {
        post_group(&client, &server.base, k).await;
    }
    // A writer keeps going while the backup runs.
    let (c, base) = (client.clone(), server.base.clone());
    let writer = tokio::spawn(async move {
        for k in 50..until {
            post_group(&c, &base, k).await;
        }
    });
    let backup = brokenray(&backup_args(config, out));
    assert!(
        backup.status.success(),
        "{}",
        String::from_utf8_lossy(&backup.stderr)
    );
    assert!(String::from_utf8_lossy(&backup.stdout).contains("a consistent copy"));
    writer.await.unwrap();
    server.kill();
}

fn backup_args<'a>(config: &'a std::path::Path, out: &'a std::path::Path) -> [&'a str; 5] {
    [
        "backup",
        "--config",
        config.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]
}

/// A second backup to the same file is refused rather than overwriting it.
fn assert_backup_refuses_to_overwrite(config: &std::path::Path, out: &std::path::Path) {
    let again = brokenray(&backup_args(config, out));
    assert!(!again.status.success());
    assert!(String::from_utf8_lossy(&again.stderr).contains("already exists"));
}

/// The container health check: `brokenray healthcheck` succeeds against a running service, with
/// tokens configured (health checks carry none), and fails once the service is gone.
#[test]
fn healthcheck_answers_for_a_running_service_and_fails_without_one() {
    let (dir, config) = site();
    let tokens = format!(
        "\n[[auth.tokens]]\nname = \"viewer\"\nsha256 = \"{}\"\nscopes = [\"read\"]\n",
        brokenray::config::sha256_hex("secret")
    );
    let text = std::fs::read_to_string(&config).unwrap() + &tokens;
    std::fs::write(&config, &text).unwrap();
    let server = start(&config);
    // The same installation, naming the port the service got.
    let port = server.base.rsplit(':').next().unwrap().to_owned();
    let with_tokens = dir.path().join("bound.toml");
    std::fs::write(
        &with_tokens,
        text.replace("127.0.0.1:0", &format!("127.0.0.1:{port}")),
    )
    .unwrap();
    let check = || {
        brokenray(&[
            "healthcheck",
            "--config",
            with_tokens.to_str().unwrap(),
            "--timeout-s",
            "5",
        ])
    };
    let ok = check();
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let body: Value = serde_json::from_slice(&ok.stdout).expect("the health JSON");
    assert_eq!(body["status"], "ok");
    server.kill();
    let down = check();
    assert!(!down.status.success());
    assert!(
        String::from_utf8_lossy(&down.stderr).contains("nothing answers"),
        "{}",
        String::from_utf8_lossy(&down.stderr)
    );
}

/// A site whose database lives in `db_dir`, with `server_extra` added to `[server]`.
fn site_at(
    dir: &std::path::Path,
    db_dir: &std::path::Path,
    server_extra: &str,
) -> std::path::PathBuf {
    let config = dir.join("site.toml");
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML
        .replace("127.0.0.1:7878", "127.0.0.1:0")
        .replace(
            "database = \"brokenray.db\"",
            &format!(
                "database = \"{}\"\n{server_extra}",
                db_dir.join("db.sqlite").display()
            ),
        );
    std::fs::write(&config, text).unwrap();
    config
}

/// Posts group `k`; its status.
async fn try_group(client: &reqwest::Client, base: &str, k: i64) -> reqwest::StatusCode {
    client
        .post(format!("{base}/api/v1/samples"))
        .json(&group(k))
        .send()
        .await
        .unwrap()
        .status()
}

async fn health(client: &reqwest::Client, base: &str) -> (reqwest::StatusCode, Value) {
    let r = client.get(format!("{base}/healthz")).send().await.unwrap();
    let status = r.status();
    (status, r.json().await.unwrap())
}

/// SIGTERM and the exit status with everything the process wrote to stderr afterwards.
fn terminate(mut server: Server) -> std::process::ExitStatus {
    let status = Command::new("kill")
        .args(["-TERM", &server.child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    for _ in 0..300 {
        if let Some(exit) = server.child.try_wait().unwrap() {
            return exit;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    server.child.kill().unwrap();
    panic!("the service did not exit within 30 s of SIGTERM");
}

/// Writes go on until the disk is full: every acknowledged group is stored, every refused one
/// is absent, the health check says what is wrong while it is, and the writer recovers by
/// itself once there is room again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_refuses_writes_honestly_and_recovers() {
    let dir = tempfile::tempdir().unwrap();
    let mount = dir.path().join("small");
    std::fs::create_dir(&mount).unwrap();
    let mounted = Command::new("mount")
        .args([
            "-t",
            "tmpfs",
            "-o",
            "size=4m",
            "tmpfs",
            mount.to_str().unwrap(),
        ])
        .status()
        .is_ok_and(|s| s.success());
    if !mounted {
        eprintln!("skipped: mounting a tmpfs needs root (this test runs in CI as root)");
        return;
    }
    struct Unmount(std::path::PathBuf);
    impl Drop for Unmount {
        fn drop(&mut self) {
            let _ = Command::new("umount").arg("-l").arg(&self.0).status();
        }
    }
    let _unmount = Unmount(mount.clone());
    // Room to free later (each commit appends some 50 KB of pages to the WAL).
    std::fs::write(mount.join("ballast"), vec![7u8; 2 * 1024 * 1024]).unwrap();
    let config = site_at(dir.path(), &mount, "");
    let client = reqwest::Client::new();
    let server = start(&config);
    let mut acked = Vec::new();
    let mut refused = Vec::new();
    let mut k = 0;
    while refused.len() < 20 {
        match try_group(&client, &server.base, k).await {
            s if s.is_success() => acked.push(k),
            s => {
                assert_eq!(s, reqwest::StatusCode::SERVICE_UNAVAILABLE);
                refused.push(k);
            }
        }
        k += 1;
        assert!(k < 100_000, "the disk never filled");
    }
    let (status, body) = health(&client, &server.base).await;
    assert_eq!(status, reqwest::StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert_eq!(body["writer"], false, "{body}");
    assert!(
        body["problem"].as_str().is_some_and(|p| !p.is_empty()),
        "{body}"
    );
    // Room again: the next commit succeeds and the health check clears.
    std::fs::remove_file(mount.join("ballast")).unwrap();
    for j in 0..10 {
        let k = 1_000_000 + j;
        assert!(
            try_group(&client, &server.base, k).await.is_success(),
            "after freeing space"
        );
        acked.push(k);
    }
    let (status, body) = health(&client, &server.base).await;
    assert_eq!(status, reqwest::StatusCode::OK, "{body}");
    let exit = terminate(server);
    assert!(exit.success(), "{exit}");
    // After a restart: exactly the acknowledged groups.
    assert_exactly_acknowledged(&client, &config, "C1_from_B", &acked).await;
}

/// Restarts the service on `config` and checks that `link` holds exactly the acknowledged
/// groups: none lost, none stored that was refused.
async fn assert_exactly_acknowledged(
    client: &reqwest::Client,
    config: &std::path::Path,
    link: &str,
    acked: &[i64],
) {
    let server = start(config);
    let stored: std::collections::BTreeSet<i64> = stored_times(client, &server.base, link)
        .await
        .into_iter()
        .collect();
    let expected: std::collections::BTreeSet<i64> = acked.iter().map(|k| group_time(*k)).collect();
    assert_eq!(
        stored, expected,
        "stored groups differ from the acknowledged ones"
    );
    server.kill();
}

/// The WAL made unwritable for a while (as by `chattr +i`): refusals, never a false
/// acknowledgement, and recovery when it is writable again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unwritable_wal_never_gives_a_false_acknowledgement() {
    let dir = tempfile::tempdir().unwrap();
    let config = site_at(dir.path(), dir.path(), "");
    let wal = dir.path().join("db.sqlite-wal");
    let client = reqwest::Client::new();
    let server = start(&config);
    let mut acked = Vec::new();
    for k in 0..20 {
        assert!(try_group(&client, &server.base, k).await.is_success());
        acked.push(k);
    }
    let locked = Command::new("chattr")
        .arg("+i")
        .arg(&wal)
        .status()
        .is_ok_and(|s| s.success());
    if !locked {
        server.kill();
        eprintln!("skipped: chattr +i needs root and a file system with attributes");
        return;
    }
    let mut refused = 0;
    for k in 20..60 {
        let s = try_group(&client, &server.base, k).await;
        if s.is_success() {
            acked.push(k);
        } else {
            assert_eq!(s, reqwest::StatusCode::SERVICE_UNAVAILABLE);
            refused += 1;
        }
    }
    assert!(refused > 0, "an immutable WAL refused nothing");
    let (status, body) = health(&client, &server.base).await;
    assert_eq!(status, reqwest::StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert!(
        Command::new("chattr")
            .arg("-i")
            .arg(&wal)
            .status()
            .unwrap()
            .success()
    );
    for k in 100..140 {
        assert!(
            try_group(&client, &server.base, k).await.is_success(),
            "after the WAL is writable"
        );
        acked.push(k);
    }
    let (status, _) = health(&client, &server.base).await;
    assert_eq!(status, reqwest::StatusCode::OK);
    server.kill();
    assert_exactly_acknowledged(&client, &config, "C3_from_G", &acked).await;
}

/// The database file deleted under the running service: writes are refused, the health check
/// says so, and the stop says the data went with the file.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_deleted_database_file_stops_writes_and_says_so() {
    let (dir, config) = site();
    let client = reqwest::Client::new();
    let server = start(&config);
    for k in 0..10 {
        post_group(&client, &server.base, k).await;
    }
    std::fs::remove_file(dir.path().join("db.sqlite")).unwrap();
    assert_eq!(
        try_group(&client, &server.base, 10).await,
        reqwest::StatusCode::SERVICE_UNAVAILABLE
    );
    let (status, body) = health(&client, &server.base).await;
    assert_eq!(status, reqwest::StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert_eq!(body["database"], false, "{body}");
    assert!(
        body["problem"]
            .as_str()
            .unwrap()
            .contains("removed or replaced"),
        "{body}"
    );
    let exit = terminate(server);
    assert!(!exit.success(), "a stop after losing the file is not clean");
}

/// After a clean stop the database file alone holds everything (the WAL is checkpointed).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_a_clean_stop_the_database_file_alone_is_complete() {
    let (dir, config) = site();
    let client = reqwest::Client::new();
    let server = start(&config);
    for k in 0..40 {
        post_group(&client, &server.base, k).await;
    }
    let exit = terminate(server);
    assert!(exit.success(), "{exit}");
    let copy = dir.path().join("copy");
    std::fs::create_dir(&copy).unwrap();
    std::fs::copy(dir.path().join("db.sqlite"), copy.join("db.sqlite")).unwrap();
    let conn = rusqlite::Connection::open(copy.join("db.sqlite")).unwrap();
    let n: i64 = conn
        .query_row("select count(*) from samples", [], |r| r.get(0))
        .unwrap();
    assert_eq!(n, 120);
}

/// Another program's SQLite file is refused, the file named once; nothing is written to it.
#[test]
fn another_programs_database_is_refused_and_named_once() {
    let dir = tempfile::tempdir().unwrap();
    let config = site_at(dir.path(), dir.path(), "");
    let db = dir.path().join("db.sqlite");
    {
        let conn = rusqlite::Connection::open(&db).unwrap();
        conn.execute_batch("create table invoices (id integer primary key, total real); insert into invoices (total) values (12.5);")
            .unwrap();
    }
    let out = brokenray(&["serve", "--config", config.to_str().unwrap()]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("is not a brokenray database"), "{stderr}");
    assert_eq!(stderr.matches(db.to_str().unwrap()).count(), 1, "{stderr}");
    let conn = rusqlite::Connection::open(&db).unwrap();
    let tables: i64 = conn
        .query_row(
            "select count(*) from sqlite_master where type = 'table'",
            [],
            |r| r.get(0),
        )
        .unwrap();
    assert_eq!(tables, 1, "nothing was migrated into the foreign file");
}

/// Idle and slow clients are closed after the header timeout, connections past the limit are
/// closed on arrival, and SIGTERM ends the process with an event stream and a drip-feeding
/// client connected.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_and_slow_clients_cannot_hold_the_service() {
    use std::io::{Read, Write};
    let dir = tempfile::tempdir().unwrap();
    let config = site_at(
        dir.path(),
        dir.path(),
        "max_connections = 20\nmax_connections_per_address = 20\nheader_timeout_s = 1\nshutdown_grace_s = 2",
    );
    let client = reqwest::Client::new();
    let server = start(&config);
    let addr = server.base.trim_start_matches("http://").to_owned();
    // Twenty idle connections fill the limit.
    let mut idle: Vec<std::net::TcpStream> = (0..20)
        .map(|_| {
            let s = std::net::TcpStream::connect(&addr).unwrap();
            std::thread::sleep(Duration::from_millis(5));
            s
        })
        .collect();
    std::thread::sleep(Duration::from_millis(200));
    // A newcomer past the limit closes the idle connection that waited longest, and is
    // answered.
    let mut extra = std::net::TcpStream::connect(&addr).unwrap();
    extra
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let _ =
        extra.write_all(b"GET /healthz HTTP/1.1\r\nhost: 127.0.0.1\r\nconnection: close\r\n\r\n");
    let mut answer = Vec::new();
    let _ = extra.read_to_end(&mut answer);
    assert!(
        String::from_utf8_lossy(&answer).starts_with("HTTP/1.1 200 "),
        "the newcomer is answered: {}",
        String::from_utf8_lossy(&answer)
    );
    let mut oldest = idle.remove(0);
    oldest
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let mut rest = Vec::new();
    let _ = oldest.read_to_end(&mut rest);
    assert!(
        rest.is_empty(),
        "the oldest idle connection was closed to make room"
    );
    // The other idle ones are closed by the header timeout (within 5 s: the timeout is 1 s),
    // each told why in the error envelope; then the service answers again.
    for (i, mut s) in idle.into_iter().enumerate() {
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let mut rest = Vec::new();
        s.read_to_end(&mut rest)
            .expect("an idle connection is answered and closed");
        let text = String::from_utf8_lossy(&rest);
        assert!(
            text.starts_with("HTTP/1.1 408 ") && text.contains("\"code\":\"request_timeout\""),
            "idle connection {i}: {text}"
        );
    }
    let (status, _) = health(&client, &server.base).await;
    assert_eq!(status, reqwest::StatusCode::OK);
    // What hyper refuses before any handler runs also speaks JSON, and is counted.
    let raw = |request: Vec<u8>| {
        let mut s = std::net::TcpStream::connect(&addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let _ = s.write_all(&request);
        let mut answer = Vec::new();
        let _ = s.read_to_end(&mut answer);
        let text = String::from_utf8_lossy(&answer).into_owned();
        let body: serde_json::Value = text
            .split_once("\r\n\r\n")
            .and_then(|(_, b)| serde_json::from_str(b).ok())
            .unwrap_or_else(|| panic!("no JSON body: {text}"));
        (text[9..12].to_owned(), body)
    };
    let mut huge = b"GET /healthz HTTP/1.1\r\nhost: 127.0.0.1\r\nx-big: ".to_vec();
    // Well over the limit: hyper checks its buffer against the limit before each read, and one
    // read can take more than what is left below it (a loaded machine lets the whole head
    // arrive at once), so a head only a little over the limit can still be parsed.
    huge.extend(std::iter::repeat_n(b'a', 1_500_000));
    huge.extend(b"\r\n\r\n");
    let (code, body) = raw(huge);
    assert_eq!(
        (code.as_str(), &body["error"]["details"][0]["field"]),
        ("431", &"headers".into()),
        "{body}"
    );
    let mut many = b"GET /healthz HTTP/1.1\r\nhost: 127.0.0.1\r\n".to_vec();
    for i in 0..200 {
        many.extend(format!("x-{i}: 1\r\n").as_bytes());
    }
    many.extend(b"\r\n");
    let (code, body) = raw(many);
    assert_eq!(code, "431", "{body}");
    let (code, body) = raw(b"NOT HTTP AT ALL\r\n\r\n".to_vec());
    assert_eq!(
        (code.as_str(), &body["error"]["code"]),
        ("400", &"malformed_request".into()),
        "{body}"
    );
    let metrics = client
        .get(format!("{}/metrics", server.base))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    for (status, at_least) in [("408", 19), ("431", 2), ("400", 1)] {
        let n: u64 = metrics
            .lines()
            .find_map(|l| {
                l.strip_prefix(&format!(
                    "brokenray_requests_rejected_total{{status=\"{status}\"}} "
                ))
            })
            .and_then(|v| v.parse().ok())
            .unwrap_or(0);
        assert!(n >= at_least, "{status}: {n}");
    }
    // A live event stream and a client that drip-feeds header lines, then SIGTERM.
    let events = client
        .get(format!("{}/api/v1/events", server.base))
        .send()
        .await
        .unwrap();
    assert!(events.status().is_success());
    let drip_addr = addr.clone();
    std::thread::spawn(move || {
        let mut s = std::net::TcpStream::connect(drip_addr).unwrap();
        let _ = s.write_all(b"GET /healthz HTTP/1.1\r\n");
        for i in 0..100 {
            std::thread::sleep(Duration::from_millis(300));
            if s.write_all(format!("x-drip-{i}: 1\r\n").as_bytes())
                .is_err()
            {
                return;
            }
        }
    });
    std::thread::sleep(Duration::from_millis(500));
    let exit = terminate(server);
    assert!(exit.success(), "{exit}");
    drop(events);
}

/// PostgreSQL crashes (an immediate stop) and comes back while four writers stream: during the
/// outage every request answers 503 and the health check says why; afterwards the writer
/// reconnects by itself. Nothing acknowledged is lost, and a refused group retried is taken
/// once (a commit whose answer was lost with the connection may already be stored).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_postgres_crash_during_ingest_loses_nothing_acknowledged() {
    if crate::common::skip_without(
        crate::common::Needs::Postgres,
        concat!(
            module_path!(),
            "::a_postgres_crash_during_ingest_loses_nothing_acknowledged"
        ),
    ) {
        return;
    }
    let cluster = crate::common::postgres::Cluster::own();
    let dir = tempfile::tempdir().unwrap();
    let config = site_with_database(&dir, &cluster.create_database());
    let client = reqwest::Client::new();
    let server = start(&config);
    let acknowledged = Arc::new(Mutex::new(Vec::<i64>::new()));
    let refused = Arc::new(Mutex::new(Vec::<(i64, reqwest::StatusCode)>::new()));
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let writers: Vec<_> = (0..4i64)
        .map(|w| {
            let (client, base) = (client.clone(), server.base.clone());
            let (acknowledged, refused, stop) = (
                Arc::clone(&acknowledged),
                Arc::clone(&refused),
                Arc::clone(&stop),
            );
            tokio::spawn(async move {
                let mut k = w;
                while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                    let status = try_group(&client, &base, k).await;
                    if status.is_success() {
                        acknowledged.lock().unwrap().push(k);
                    } else {
                        refused.lock().unwrap().push((k, status));
                        tokio::time::sleep(Duration::from_millis(20)).await;
                    }
                    k += 4;
                }
            })
        })
        .collect();
    let count = |v: &Arc<Mutex<Vec<i64>>>| v.lock().unwrap().len();
    while count(&acknowledged) < 300 {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    cluster.stop("immediate");
    while refused.lock().unwrap().len() < 20 {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let (status, body) = health(&client, &server.base).await;
    assert_eq!(status, reqwest::StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert!(
        body["problem"].as_str().is_some_and(|p| !p.is_empty()),
        "{body}"
    );
    // A retry of a stored group (older than its links' newest, so what is stored is read
    // before it is filtered, and that read fails now) is refused, not taken as new.
    let first = acknowledged.lock().unwrap()[0];
    assert_eq!(
        try_group(&client, &server.base, first).await,
        reqwest::StatusCode::SERVICE_UNAVAILABLE
    );
    let before_restart = count(&acknowledged);
    cluster.start();
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while count(&acknowledged) < before_restart + 300 {
        assert!(
            std::time::Instant::now() < deadline,
            "writes did not resume after PostgreSQL came back"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    for w in writers {
        w.await.unwrap();
    }
    let (status, body) = health(&client, &server.base).await;
    assert_eq!(status, reqwest::StatusCode::OK, "{body}");
    let refused = refused.lock().unwrap().clone();
    assert!(
        refused
            .iter()
            .all(|(_, s)| *s == reqwest::StatusCode::SERVICE_UNAVAILABLE),
        "refusals other than 503: {refused:?}"
    );
    // A refused group, retried now, is taken (stored once, whether or not it was already);
    // so is the retry refused during the outage.
    for (k, _) in &refused {
        assert!(try_group(&client, &server.base, *k).await.is_success());
    }
    assert!(try_group(&client, &server.base, first).await.is_success());
    let mut expected = acknowledged.lock().unwrap().clone();
    expected.extend(refused.iter().map(|(k, _)| *k));
    let stored = stored_times(&client, &server.base, "C1_from_B").await;
    let stored_set: std::collections::BTreeSet<i64> = stored.iter().copied().collect();
    assert_eq!(stored.len(), stored_set.len(), "a group stored twice");
    let expected: std::collections::BTreeSet<i64> =
        expected.iter().map(|k| group_time(*k)).collect();
    assert_eq!(
        stored_set, expected,
        "stored groups differ from the acknowledged and retried ones"
    );
    server.kill();
}

/// `backup` of a PostgreSQL site while it is written to: a `pg_dump` archive that
/// `pg_restore` turns into a database holding whole groups, at least those acknowledged before
/// the backup began; never over an existing file.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_postgres_backup_while_serving_restores_with_pg_restore() {
    if crate::common::skip_without(
        crate::common::Needs::Postgres,
        concat!(
            module_path!(),
            "::a_postgres_backup_while_serving_restores_with_pg_restore"
        ),
    ) {
        return;
    }
    let cluster = crate::common::postgres::cluster();
    let dir = tempfile::tempdir().unwrap();
    let config = site_with_database(&dir, &cluster.create_database());
    let out = dir.path().join("site.dump");
    backup_while_serving(&config, &out, 300).await;
    let restored = cluster.create_database();
    let restore = Command::new("pg_restore")
        .args(["--no-owner", "--dbname", &restored])
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        restore.status.success(),
        "{}",
        String::from_utf8_lossy(&restore.stderr)
    );
    let name = restored.rsplit('/').next().unwrap();
    let n: i64 = cluster
        .psql(name, "select count(*) from samples")
        .parse()
        .unwrap();
    assert!(n >= 150 && n % 3 == 0, "{n} samples in the copy");
    assert_backup_refuses_to_overwrite(&config, &out);
}
