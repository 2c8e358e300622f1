//! Small requests that would take a host's memory or its connections, against the real binary:
//! a zstd bomb to a centre's `/sync`, PNG frames whose colour profile inflates to hundreds of
//! megabytes, and a client that keeps every connection slot filled with idle connections.
//! Each is refused or absorbed within a bounded memory, and the health check answers
//! throughout. Memory is the server's peak resident set (`VmHWM`) from `/proc`.

use crate::common::hostile::{
    builtin_installation, colour_profile_bomb, rss_mb, watch_health, zstd_bomb,
};
use crate::common::postgres;
use crate::common::process::{self, Server};
use serde_json::json;
use std::time::Duration;

/// The most a burst of bombs may add to the server's peak memory (MB).
const MAX_GROWTH_MB: f64 = 300.0;

/// Of ten `/healthz` requests, 100 ms apart, those answered 200.
async fn health_checks_answered(client: &reqwest::Client, base: &str) -> usize {
    let mut answered = 0;
    for _ in 0..10 {
        if let Ok(r) = client.get(format!("{base}/healthz")).send().await
            && r.status() == 200
        {
            answered += 1;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    answered
}

fn start(config: &std::path::Path) -> Server {
    process::start(
        config,
        "warn,brokenray=info",
        false,
        Duration::from_secs(60),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_zstd_bombs_to_a_centre_are_refused_within_its_memory_budget() {
    if crate::common::skip_without(
        crate::common::Needs::Postgres,
        concat!(
            module_path!(),
            "::three_zstd_bombs_to_a_centre_are_refused_within_its_memory_budget"
        ),
    ) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let url = postgres::fresh_database();
    let config = builtin_installation(dir.path(), &url, "[central]\nenabled = true\n");
    let centre = start(&config);
    // 200 MB of JSON in about 20 KB.
    let bomb = zstd_bomb(40_000_000);
    assert!(bomb.len() < 64 * 1024, "{} bytes", bomb.len());
    let client = reqwest::Client::new();
    // Warm: one ordinary report of state.
    let r = client
        .post(format!("{}/api/v1/sites/s1/sync", centre.base))
        .json(&json!({"outbox_id": "a", "registry": {"links": [], "targets": []}}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let pid = centre.child.id();
    let (idle_mb, _) = rss_mb(pid);
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let health = tokio::spawn(watch_health(centre.base.clone(), stop_rx));
    let posts: Vec<_> = (0..3)
        .map(|_| {
            let client = client.clone();
            let url = format!("{}/api/v1/sites/s1/sync", centre.base);
            let body = bomb.clone();
            tokio::spawn(async move {
                let r = client
                    .post(url)
                    .header("content-type", "application/json")
                    .header("content-encoding", "zstd")
                    .body(body)
                    .send()
                    .await
                    .unwrap();
                (
                    r.status().as_u16(),
                    r.json::<serde_json::Value>().await.unwrap(),
                )
            })
        })
        .collect();
    for p in posts {
        let (status, body) = p.await.unwrap();
        assert_eq!(status, 413, "{body}");
        assert_eq!(body["error"]["code"], "payload_too_large", "{body}");
    }
    stop_tx.send(true).unwrap();
    let seen = health.await.unwrap();
    assert!(seen.asked > 0);
    assert_eq!(seen.failed, 0, "the health check answered throughout");
    let (_, peak_mb) = rss_mb(pid);
    assert!(
        peak_mb - idle_mb < MAX_GROWTH_MB,
        "peak {peak_mb:.0} MB, idle {idle_mb:.0} MB"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sixteen_colour_profile_bombs_at_once_cost_no_more_than_frames() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("site.db");
    let config = builtin_installation(dir.path(), &db.display().to_string(), "");
    let site = start(&config);
    let bomb = colour_profile_bomb(1280, 1024, 400);
    assert!(bomb.len() < 2 << 20, "{} bytes", bomb.len());
    let client = reqwest::Client::new();
    let pid = site.child.id();
    let (idle_mb, _) = rss_mb(pid);
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let health = tokio::spawn(watch_health(site.base.clone(), stop_rx));
    let time = brokenray::clock::format_ns(brokenray::clock::wall_now_ns() - 1_000_000_000);
    let posts: Vec<_> = (0..16)
        .map(|_| {
            let client = client.clone();
            let url = format!("{}/api/v1/frames?camera=C1&time={time}", site.base);
            let body = bomb.clone();
            tokio::spawn(async move {
                let r = client
                    .post(url)
                    .header("content-type", "image/png")
                    .body(body)
                    .send()
                    .await
                    .unwrap();
                (r.status().as_u16(), r.text().await.unwrap())
            })
        })
        .collect();
    for p in posts {
        let (status, body) = p.await.unwrap();
        // Decoded as the grey frame it is (nothing found in it), or told to come back.
        assert!(status == 200 || status == 503, "{status} {body}");
        if status == 503 {
            assert!(body.contains("busy"), "{body}");
        }
    }
    stop_tx.send(true).unwrap();
    let seen = health.await.unwrap();
    assert!(seen.asked > 0);
    assert_eq!(seen.failed, 0, "the health check answered throughout");
    let (_, peak_mb) = rss_mb(pid);
    assert!(
        peak_mb - idle_mb < MAX_GROWTH_MB,
        "peak {peak_mb:.0} MB, idle {idle_mb:.0} MB"
    );
}

/// A client that keeps all of a small service's connection slots filled with idle connections
/// (from 127.0.0.2, allowed every slot), opening a new one as each is closed: a newcomer from
/// another address still gets in (the greediest address's oldest idle connection makes room,
/// and the client's refills close only its own), so every health check is answered.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_connections_refilled_as_they_close_never_shut_out_a_newcomer() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("site.db");
    let config = builtin_installation(dir.path(), &db.display().to_string(), "").to_path_buf();
    let text = std::fs::read_to_string(&config).unwrap().replacen(
        "[server]\n",
        "[server]\nmax_connections = 64\nmax_connections_per_address = 64\n",
        1,
    );
    std::fs::write(&config, text).unwrap();
    let site = start(&config);
    let addr = site.base.trim_start_matches("http://").to_owned();
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    // The attacker: 64 idle connections, each reopened as soon as the server closes it.
    let opened = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let attackers: Vec<_> = (0..64)
        .map(|_| {
            let (addr, stop, opened) = (addr.clone(), stop_rx.clone(), opened.clone());
            tokio::spawn(async move {
                while !*stop.borrow() {
                    let socket = tokio::net::TcpSocket::new_v4().unwrap();
                    socket.bind("127.0.0.2:0".parse().unwrap()).unwrap();
                    let Ok(mut conn) = socket.connect(addr.parse().unwrap()).await else {
                        tokio::time::sleep(Duration::from_millis(5)).await;
                        continue;
                    };
                    opened.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    let mut buf = [0u8; 64];
                    // Idle until the server closes it.
                    let _ = tokio::io::AsyncReadExt::read(&mut conn, &mut buf).await;
                }
            })
        })
        .collect();
    tokio::time::sleep(Duration::from_millis(500)).await;
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(10))
        .pool_max_idle_per_host(0)
        .build()
        .unwrap();
    let answered = health_checks_answered(&client, &site.base).await;
    stop_tx.send(true).unwrap();
    for a in attackers {
        a.abort();
    }
    assert!(
        opened.load(std::sync::atomic::Ordering::Relaxed) >= 64,
        "the slots were filled"
    );
    assert_eq!(answered, 10, "every health check answered");
    let metrics = reqwest::get(format!("{}/metrics", site.base))
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    let evicted: f64 = metrics
        .lines()
        .find_map(|l| l.strip_prefix("brokenray_connections_evicted_total "))
        .and_then(|v| v.trim().parse().ok())
        .expect("the eviction counter");
    assert!(evicted >= 10.0, "the newcomers made room: {evicted}");
}

/// Frames of a megabyte for a camera the installation does not have, refused before their
/// bodies are read: every client reads its 422 naming `camera`, none a broken pipe.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refusal_before_the_body_is_read_still_reaches_its_client() {
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("site.db");
    let config = builtin_installation(dir.path(), &db.display().to_string(), "");
    let site = start(&config);
    let body = vec![0x5au8; 1 << 20];
    let client = reqwest::Client::new();
    let time = brokenray::clock::format_ns(brokenray::clock::wall_now_ns() - 1_000_000_000);
    for round in 0..4 {
        let posts: Vec<_> = (0..12)
            .map(|_| {
                let client = client.clone();
                let url = format!("{}/api/v1/frames?camera=C9&time={time}", site.base);
                let body = body.clone();
                tokio::spawn(async move {
                    let r = client
                        .post(url)
                        .header("content-type", "image/png")
                        .body(body)
                        .send()
                        .await
                        .map_err(|e| format!("{e:?}"))?;
                    let status = r.status().as_u16();
                    let answer: serde_json::Value = r.json().await.map_err(|e| format!("{e:?}"))?;
                    Ok::<_, String>((status, answer))
                })
            })
            .collect();
        for p in posts {
            let (status, answer) = p
                .await
                .unwrap()
                .unwrap_or_else(|e| panic!("round {round}: the refusal was lost: {e}"));
            assert_eq!(status, 422, "{answer}");
            assert_eq!(answer["error"]["details"][0]["field"], "camera", "{answer}");
        }
    }
}

/// One address holds 1100 connections busy with requests, first unread event streams, then
/// POSTs whose bodies never come: more than it may hold (a quarter of the connections), and 20
/// more that send nothing, to fill the health reserve. Its own health checks still answer 10 of
/// 10: event streams past their cap are answered 503 `busy` at once (their connections idle,
/// so closable), and when every connection the address may hold is busy, the health reserve
/// takes the check, closing a reserve connection that has sent nothing to make room.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_address_holding_every_connection_busy_still_gets_its_health_checks() {
    // 1100 connections of the test's own, beside the server's.
    let _ = rlimit::increase_nofile_limit(u64::MAX);
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("site.db");
    let config = builtin_installation(dir.path(), &db.display().to_string(), "").to_path_buf();
    let site = start(&config);
    let addr: std::net::SocketAddr = site.base.trim_start_matches("http://").parse().unwrap();
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(10))
        .pool_max_idle_per_host(0)
        .build()
        .unwrap();
    let events = format!("GET /api/v1/events HTTP/1.1\r\nHost: {addr}\r\n\r\n");
    let slow_body = format!(
        "POST /api/v1/samples HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\n\
         Content-Length: 1000000\r\n\r\n{{\"samples\": ["
    );
    for (kind, request) in [("event streams", events), ("slow bodies", slow_body)] {
        let mut held = Vec::new();
        for _ in 0..1100 {
            let Ok(mut conn) = tokio::net::TcpStream::connect(addr).await else {
                continue;
            };
            if tokio::io::AsyncWriteExt::write_all(&mut conn, request.as_bytes())
                .await
                .is_ok()
            {
                held.push(conn);
            }
        }
        assert!(held.len() > 1024, "{kind}: {} connections held", held.len());
        tokio::time::sleep(Duration::from_millis(500)).await;
        // And the health reserve filled with connections that never send a request: the
        // checks close them to get in.
        for _ in 0..20 {
            if let Ok(conn) = tokio::net::TcpStream::connect(addr).await {
                held.push(conn);
            }
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
        let answered = health_checks_answered(&client, &site.base).await;
        assert_eq!(answered, 10, "{kind}: every health check answered");
        // An event stream past the caps is told why.
        if kind == "event streams" {
            let r = client
                .get(format!("{}/api/v1/events", site.base))
                .send()
                .await
                .unwrap();
            assert_eq!(r.status(), 503);
            let body: serde_json::Value = r.json().await.unwrap();
            assert_eq!(body["error"]["code"], "busy", "{body}");
            assert!(
                body["error"]["message"]
                    .as_str()
                    .unwrap()
                    .contains("event streams"),
                "{body}"
            );
        }
        drop(held);
    }
}
