//! The binary on a real port, killed with SIGKILL mid-stream: nothing acknowledged is lost, and
//! the compensation after a restart is the one before the kill.

use serde_json::{Value, json};
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::Duration;

struct Server {
    child: Child,
    base: String,
}

impl Server {
    /// SIGKILL, and wait for the process to be gone.
    fn kill(mut self) {
        self.child.kill().expect("SIGKILL");
        self.child.wait().expect("the killed process");
    }
}

/// The time of group `k`: 2026-11-21T10:00:00Z plus `k` times 40 ms.
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
    let mut child = Command::new(env!("CARGO_BIN_EXE_brokenray"))
        .args(["serve", "--config", config.to_str().unwrap()])
        .env("RUST_LOG", "info")
        .stderr(Stdio::piped())
        .stdout(Stdio::null())
        .spawn()
        .expect("the binary starts");
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut sent = false;
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if !sent && let Some(rest) = line.split("serving on http://").nth(1) {
                let addr = rest.split('/').next().unwrap().to_owned();
                let _ = tx.send(addr);
                sent = true;
            }
        }
    });
    let addr = rx
        .recv_timeout(Duration::from_secs(30))
        .expect("the server says where it listens");
    Server {
        child,
        base: format!("http://{addr}"),
    }
}

/// A temporary directory with the built-in installation on port 0 and a database inside it.
fn site() -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("site.toml");
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML
        .replace("127.0.0.1:7878", "127.0.0.1:0")
        .replace(
            "database = \"brokenray.db\"",
            &format!("database = \"{}\"", dir.path().join("db.sqlite").display()),
        );
    std::fs::write(&config, text).unwrap();
    (dir, config)
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
        .map(|s| brokenray::api::time::parse_rfc3339_ns(s["time"].as_str().unwrap()).unwrap())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigkill_loses_nothing_acknowledged_and_the_restart_answers_the_same() {
    let (_dir, config) = site();
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
    let before = get(server.base.clone()).await;
    assert_eq!(before["status"], "ok");
    server.kill();
    let server = start(&config);
    let after = get(server.base.clone()).await;
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
    let client = reqwest::Client::new();
    let server = start(&config);
    for k in 0..50 {
        post_group(&client, &server.base, k).await;
    }
    // A writer keeps going while the backup runs.
    let (c, base) = (client.clone(), server.base.clone());
    let writer = tokio::spawn(async move {
        for k in 50..400 {
            post_group(&c, &base, k).await;
        }
    });
    let out = dir.path().join("copy.sqlite");
    let backup_args = [
        "backup",
        "--config",
        config.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    let backup = brokenray(&backup_args);
    assert!(
        backup.status.success(),
        "{}",
        String::from_utf8_lossy(&backup.stderr)
    );
    assert!(String::from_utf8_lossy(&backup.stdout).contains("a consistent copy"));
    writer.await.unwrap();
    server.kill();
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
    // A second backup to the same file is refused rather than overwriting it.
    let again = brokenray(&backup_args);
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
        brokenray::api::auth::sha256_hex("secret")
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
