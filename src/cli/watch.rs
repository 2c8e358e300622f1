//! `brokenray watch DIR`: a folder as a frame source. Camera software writes each frame into
//! `DIR/<camera>/`; every file there is posted to `/api/v1/frames` of a running service, oldest
//! first, and removed once the service answered 2xx (it is then durably ingested).
//!
//! * The frame's time is its file name's when the stem is one (RFC 3339, such as
//!   `2026-11-21T10:00:00.040Z.png`, or integer nanoseconds), otherwise its modification time.
//! * A file is taken once it has not changed for `settle` (camera software that writes a file
//!   and renames it into place is taken at once; hidden and temporary names are skipped).
//! * A refusal (4xx other than 408 and 429: an unknown camera, a wrong size, an undecodable
//!   file, a conflicting sample) moves the file aside into `DIR/<camera>/refused/` with the
//!   service's answer beside it (`<file>.error.json`); it is never retried.
//! * When the service cannot be reached or answers 5xx, 408 or 429, nothing is removed: the file
//!   is tried again after a back-off (up to 30 s), so an outage of the service loses nothing.
//! * A file that cannot be a frame is set aside the same way, with the reason, unread and
//!   without stopping the others: a name that is not UTF-8, a time before 1970 or past 2262
//!   (in its name or its modification time), a size over what the camera can make (its width
//!   times height times 8 bytes, RGBA 16 bit, and a megabyte; the sizes come from the
//!   service's `GET /api/v1/cameras`, 64 MiB for a camera it does not list). A file that
//!   vanishes while the folder is scanned is passed over.
//!
//! The folder is scanned rather than watched with inotify: the scan works on every file system
//! (camera PCs often write to network shares, where change notifications do not arrive) and
//! costs little at camera rates; the price is up to one poll interval of latency.

use crate::feed::Client;
use crate::imagefile::FrameFormat;
use anyhow::Context as _;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

/// How a watch runs.
#[derive(Debug, Clone)]
pub(super) struct WatchSettings {
    /// Time between scans when nothing is waiting.
    pub poll: Duration,
    /// A file is taken when unchanged for this long.
    pub settle: Duration,
    /// One pass over what is there (waiting for the service while it is unreachable), then
    /// stop; otherwise watch until stopped.
    pub once: bool,
    /// Shows progress (hidden when standard error is not a terminal).
    pub progress: indicatif::ProgressBar,
}

/// What a watch did.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub(super) struct WatchSummary {
    /// Frames the service took (and that were removed).
    pub posted: u64,
    /// Frames it refused (moved aside).
    pub refused: u64,
    /// Times the service could not take a frame for now (unreachable, 5xx, 408, 429).
    pub retries: u64,
}

/// The size a frame file may have when the service's cameras are not known.
const UNKNOWN_CAMERA_MAX_BYTES: u64 = 64 << 20;

/// A file in a camera's folder that cannot be a frame, and why.
#[derive(Debug, Clone)]
struct Unfit {
    path: PathBuf,
    reason: String,
}

/// A frame file waiting.
#[derive(Debug, Clone)]
struct Waiting {
    time_ns: i64,
    camera: String,
    path: PathBuf,
    format: FrameFormat,
}

/// What the service made of one frame.
enum Outcome {
    Taken,
    /// The file went away before it was read (someone else took it): nothing to count.
    Gone,
    Refused(String),
    NotNow(String),
}

/// Watches `dir` until `stop` resolves (or, with `once`, until what was there is delivered or
/// refused).
pub(super) async fn watch(
    dir: &Path,
    client: &Client,
    settings: &WatchSettings,
    mut stop: impl std::future::Future<Output = ()> + Unpin,
) -> anyhow::Result<WatchSummary> {
    anyhow::ensure!(
        dir.is_dir(),
        "{} is not a directory (frames are written into <dir>/<camera>/)",
        dir.display()
    );
    let mut summary = WatchSummary::default();
    let mut backoff = Duration::ZERO;
    let progress = &settings.progress;
    let mut sizes = camera_sizes(client).await;
    loop {
        if sizes.is_none() {
            sizes = camera_sizes(client).await;
        }
        let (waiting, unfit) = scan(dir, settings.settle, sizes.as_ref())?;
        for u in unfit {
            summary.refused += 1;
            let answer = serde_json::to_string_pretty(&serde_json::json!({
                "refused_by": "watch",
                "reason": u.reason,
            }))
            .unwrap_or_default();
            match set_aside(&u.path, &answer) {
                Ok(aside) => progress.suspend(|| {
                    eprintln!("not a frame, moved to {}: {}", aside.display(), u.reason);
                }),
                Err(e) => progress.suspend(|| {
                    eprintln!(
                        "not a frame ({}), and it cannot be moved aside: {e:#}",
                        u.reason
                    );
                }),
            }
        }
        let mut outage = None;
        for frame in &waiting {
            match deliver(client, frame).await? {
                Outcome::Taken => {
                    summary.posted += 1;
                    backoff = Duration::ZERO;
                }
                Outcome::Gone => {}
                Outcome::Refused(answer) => {
                    summary.refused += 1;
                    match set_aside(&frame.path, &answer) {
                        Ok(aside) => progress.suspend(|| {
                            eprintln!(
                                "refused, moved to {}: {}",
                                aside.display(),
                                first_line(&answer)
                            );
                        }),
                        // Removed by someone else meanwhile: nothing is left to move aside.
                        Err(_) if !frame.path.exists() => progress.suspend(|| {
                            eprintln!(
                                "refused, and {} was removed before it could be moved aside: {}",
                                frame.path.display(),
                                first_line(&answer)
                            );
                        }),
                        Err(e) => return Err(e),
                    }
                }
                Outcome::NotNow(why) => {
                    summary.retries += 1;
                    outage = Some(why);
                    break;
                }
            }
            progress.set_message(format!(
                "{} posted, {} refused; {}",
                summary.posted,
                summary.refused,
                crate::clock::format_ns(frame.time_ns)
            ));
            progress.tick();
        }
        let pause = match &outage {
            Some(why) => {
                backoff = (backoff * 2).clamp(Duration::from_millis(250), Duration::from_secs(30));
                progress.suspend(|| {
                    eprintln!(
                        "the service cannot take frames now ({why}); {} waiting, trying again in {:.1} s",
                        waiting.len(),
                        backoff.as_secs_f64()
                    );
                });
                backoff
            }
            None if settings.once => {
                // Done when nothing is left, not even a file still settling.
                if scan(dir, Duration::ZERO, sizes.as_ref())?.0.is_empty() {
                    return Ok(summary);
                }
                if waiting.is_empty() {
                    settings.settle.max(settings.poll)
                } else {
                    Duration::ZERO
                }
            }
            None => settings.poll,
        };
        tokio::select! {
            () = tokio::time::sleep(pause) => {}
            () = &mut stop => return Ok(summary),
        }
    }
}

/// The cameras' largest possible frame files (bytes) by name, from the service; `None` when
/// it cannot say now (unreachable, or the token may not read).
async fn camera_sizes(client: &Client) -> Option<std::collections::HashMap<String, u64>> {
    let cameras = client.get_json("/api/v1/cameras").await.ok()?;
    Some(
        cameras["cameras"]
            .as_array()?
            .iter()
            .filter_map(|c| {
                let (w, h) = (c["width_px"].as_u64()?, c["height_px"].as_u64()?);
                let budget = crate::imagefile::decode_budget_bytes(
                    u32::try_from(w).ok()?,
                    u32::try_from(h).ok()?,
                );
                Some((c["name"].as_str()?.to_owned(), budget))
            })
            .collect(),
    )
}

/// The frame files under `dir/<camera>/` unchanged for `settle`, oldest first, and the files
/// there that cannot be frames. A file that vanishes meanwhile is passed over.
fn scan(
    dir: &Path,
    settle: Duration,
    sizes: Option<&std::collections::HashMap<String, u64>>,
) -> anyhow::Result<(Vec<Waiting>, Vec<Unfit>)> {
    let now = SystemTime::now();
    let mut out = Vec::new();
    let mut unfit = Vec::new();
    for camera in
        std::fs::read_dir(dir).with_context(|| format!("cannot read {}", dir.display()))?
    {
        let Ok(camera) = camera else { continue };
        let Some(name) = camera.file_name().to_str().map(str::to_owned) else {
            continue;
        };
        if name.starts_with('.') || !camera.file_type().is_ok_and(|t| t.is_dir()) {
            continue;
        }
        let Ok(files) = std::fs::read_dir(camera.path()) else {
            continue;
        };
        let max_bytes = sizes
            .and_then(|s| s.get(&name).copied())
            .unwrap_or(UNKNOWN_CAMERA_MAX_BYTES);
        for file in files {
            let Ok(file) = file else { continue };
            let path = file.path();
            let Ok(meta) = file.metadata() else {
                continue;
            };
            if !meta.is_file() {
                continue;
            }
            let Some(file_name) = file.file_name().to_str().map(str::to_owned) else {
                unfit.push(Unfit {
                    reason: format!(
                        "the name {:?} is not UTF-8: a frame's name is its time or plain text",
                        file.file_name()
                    ),
                    path,
                });
                continue;
            };
            if file_name.starts_with('.') {
                continue;
            }
            let Some(format) = FrameFormat::from_path(&path) else {
                continue;
            };
            let age = meta
                .modified()
                .ok()
                .and_then(|m| now.duration_since(m).ok())
                .unwrap_or(Duration::ZERO);
            if age < settle {
                continue;
            }
            if meta.len() > max_bytes {
                unfit.push(Unfit {
                    reason: format!(
                        "{} bytes, more than a frame of camera {name} can be ({max_bytes})",
                        meta.len()
                    ),
                    path,
                });
                continue;
            }
            match super::detect::time_of(&path) {
                Ok(time_ns) => out.push(Waiting {
                    time_ns,
                    camera: name.clone(),
                    path,
                    format,
                }),
                // Gone while we looked: someone else took it.
                Err(_) if !path.exists() => {}
                Err(e) => unfit.push(Unfit {
                    reason: format!("{e:#}"),
                    path,
                }),
            }
        }
    }
    out.sort_by(|a, b| (a.time_ns, &a.camera, &a.path).cmp(&(b.time_ns, &b.camera, &b.path)));
    Ok((out, unfit))
}

/// Posts one frame file.
async fn deliver(client: &Client, frame: &Waiting) -> anyhow::Result<Outcome> {
    let bytes = match std::fs::read(&frame.path) {
        Ok(b) => b,
        // Taken away by someone else meanwhile: nothing to do.
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Outcome::Gone),
        Err(e) => return Err(e).with_context(|| format!("cannot read {}", frame.path.display())),
    };
    let answer = client
        .post_frame(&frame.camera, frame.time_ns, frame.format, bytes)
        .await;
    let (status, body) = match answer {
        Ok(a) => a,
        Err(e) => return Ok(Outcome::NotNow(format!("{e:#}"))),
    };
    if status.is_success() {
        std::fs::remove_file(&frame.path).with_context(|| {
            format!("cannot remove {} after it was taken", frame.path.display())
        })?;
        return Ok(Outcome::Taken);
    }
    let text = serde_json::to_string_pretty(&serde_json::json!({
        "status": status.as_u16(),
        "answer": body,
    }))
    .unwrap_or_default();
    let transient = status.is_server_error()
        || status == reqwest::StatusCode::REQUEST_TIMEOUT
        || status == reqwest::StatusCode::TOO_MANY_REQUESTS;
    Ok(if transient {
        Outcome::NotNow(format!("{status}"))
    } else {
        Outcome::Refused(text)
    })
}

/// Moves a refused file into `<camera>/refused/` with the answer beside it; returns where.
fn set_aside(path: &Path, answer: &str) -> anyhow::Result<PathBuf> {
    let parent = path.parent().unwrap_or(Path::new("."));
    let aside = parent.join("refused");
    std::fs::create_dir_all(&aside)
        .with_context(|| format!("cannot create {}", aside.display()))?;
    let name = path.file_name().unwrap_or_default();
    let to = aside.join(name);
    let mut error_name = name.to_os_string();
    error_name.push(".error.json");
    std::fs::write(aside.join(error_name), answer)
        .with_context(|| format!("cannot write beside {}", to.display()))?;
    std::fs::rename(path, &to).with_context(|| format!("cannot move {} aside", path.display()))?;
    Ok(to)
}

/// The service's message, if the answer has one.
fn first_line(answer: &str) -> String {
    serde_json::from_str::<serde_json::Value>(answer)
        .ok()
        .and_then(|v| v["answer"]["error"]["message"].as_str().map(str::to_owned))
        .unwrap_or_else(|| answer.lines().next().unwrap_or_default().to_owned())
}
