//! What the load benches that run the release binary in its own process share
//! (`frames_load`, `frames_no_prior`; included by path): the server's CPU time, the wall
//! clock, and a frame posted with its answer read.

use std::time::{SystemTime, UNIX_EPOCH};

/// CPU time (user + system) of a process so far (s).
pub fn cpu_s(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    // Fields after the command name (which may hold spaces) start after the last ')'.
    let rest = stat.rsplit(')').next().unwrap_or("");
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| {
        fields
            .get(i)
            .and_then(|v| v.parse::<f64>().ok())
            .unwrap_or(0.0)
    };
    // utime and stime are fields 14 and 15 of the line, 12 and 13 after the name.
    let hz = std::process::Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .ok()
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .and_then(|t| t.trim().parse::<f64>().ok())
        .unwrap_or(100.0);
    (ticks(11) + ticks(12)) / hz
}

/// The wall clock (ns since 1970).
pub fn wall_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_nanos() as i64)
        .unwrap_or(0)
}

/// Posts one frame of `camera` at `time` to `POST {base}/api/v1/frames`: its answer, or what
/// went wrong (the refusal's text, or the transport's error).
pub async fn post_frame(
    client: &reqwest::Client,
    base: &str,
    camera: &str,
    time: &str,
    format: brokenray::imagefile::FrameFormat,
    body: Vec<u8>,
) -> Result<serde_json::Value, String> {
    let answer = client
        .post(format!("{base}/api/v1/frames"))
        .query(&[("camera", camera), ("time", time)])
        .header("content-type", format.content_type())
        .body(body)
        .send()
        .await
        .map_err(|e| e.to_string())?;
    if answer.status().is_success() {
        Ok(answer.json().await.unwrap_or_default())
    } else {
        Err(answer.text().await.unwrap_or_default())
    }
}
