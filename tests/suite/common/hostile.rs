//! Hostile inputs and the measures of what they cost a running service, shared by
//! `tests/suite/bombs.rs` (which asserts bounds) and `benches/bombs.rs` (which prints figures;
//! included there by path): a zstd bomb for a centre's `/sync`, a PNG whose colour profile
//! inflates to hundreds of megabytes, the server's resident set, and a health-check poller.

#![allow(dead_code, reason = "each includer uses part of it")]

use std::io::Write as _;
use std::time::{Duration, Instant};

/// The built-in installation on port 0 with `database` and `extra` appended, written into
/// `dir`.
pub fn builtin_installation(
    dir: &std::path::Path,
    database: &str,
    extra: &str,
) -> std::path::PathBuf {
    let text = brokenray::config::DEFAULT_INSTALLATION_TOML
        .replace("127.0.0.1:7878", "127.0.0.1:0")
        .replace(
            "database = \"brokenray.db\"",
            &format!("database = \"{database}\""),
        );
    let path = dir.join("hostile.toml");
    std::fs::write(&path, format!("{text}\n{extra}\n")).unwrap();
    path
}

/// A process's (current, peak) resident set, MB (`VmRSS`, `VmHWM` of `/proc`).
pub fn rss_mb(pid: u32) -> (f64, f64) {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let field = |name: &str| {
        status
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse::<f64>().ok())
            .expect("a /proc status field")
            / 1024.0
    };
    (field("VmRSS:"), field("VmHWM:"))
}

/// What a health-check poller saw: checks asked, those not answered 200 (or not within 10 s),
/// and the slowest answer.
#[derive(Debug, Clone, Copy)]
pub struct HealthSeen {
    pub asked: u32,
    pub failed: u32,
    pub slowest: Duration,
}

/// Polls `base/healthz` every 50 ms until `stop` turns true.
pub async fn watch_health(base: String, stop: tokio::sync::watch::Receiver<bool>) -> HealthSeen {
    let client = reqwest::Client::builder()
        .timeout(Duration::from_secs(10))
        .build()
        .unwrap();
    let mut seen = HealthSeen {
        asked: 0,
        failed: 0,
        slowest: Duration::ZERO,
    };
    while !*stop.borrow() {
        seen.asked += 1;
        let asked_at = Instant::now();
        match client.get(format!("{base}/healthz")).send().await {
            Ok(r) if r.status() == 200 => seen.slowest = seen.slowest.max(asked_at.elapsed()),
            _ => seen.failed += 1,
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    seen
}

/// An upload whose samples column is `nulls` nulls: about 5 bytes each as JSON, a few
/// kilobytes as zstd.
pub fn zstd_bomb(nulls: usize) -> Vec<u8> {
    let mut encoder = zstd::stream::write::Encoder::new(Vec::new(), 3).unwrap();
    encoder
        .write_all(
            br#"{"outbox_id":"a","head_seq":2,"registry":{"links":[],"targets":[]},"batch":{"tier":"raw","after_seq":null,"upto_seq":1,"tables":[{"table":"samples","columns":[{"int":["#,
        )
        .unwrap();
    let chunk = "null,".repeat(100_000);
    for _ in 0..nulls / 100_000 {
        encoder.write_all(chunk.as_bytes()).unwrap();
    }
    encoder.write_all(b"null]}]}]}}").unwrap();
    encoder.finish().unwrap()
}

/// A `width` x `height` grey PNG whose colour profile inflates to `profile_mb` megabytes of
/// zeros.
pub fn colour_profile_bomb(width: u32, height: u32, profile_mb: usize) -> Vec<u8> {
    let mut zlib = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::best());
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..profile_mb {
        zlib.write_all(&zeros).unwrap();
    }
    let mut chunk = b"bomb\0\0".to_vec();
    chunk.extend(zlib.finish().unwrap());
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, width, height);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder.write_header().unwrap();
    writer.write_chunk(png::chunk::iCCP, &chunk).unwrap();
    writer
        .write_image_data(&vec![128u8; (width * height) as usize])
        .unwrap();
    writer.finish().unwrap();
    out
}
