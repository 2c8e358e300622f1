//! Feeding a service from the simulator: request bodies, NDJSON files, ground truth, and the
//! HTTP client behind `brokenray simulate --to` and `brokenray demo`.
//!
//! Observations go to `POST /api/v1/observations` (the service runs PnP); in `samples` mode
//! the simulator solves them itself and sends link poses with their covariance to
//! `POST /api/v1/samples`, as a pose-producing pipeline would; in `frames` mode every camera's
//! frame is rendered (8-bit PNG) and posted to `POST /api/v1/frames`, or written as
//! `DIR/<camera>/<time>.png` beside `DIR/truth.ndjson`.

use crate::clock::format_ns;
use crate::model::Observer;
use crate::sim::{SimGroup, Simulator};
use crate::wire::{ObservationIn, PoseOut};
use anyhow::{Context as _, bail};
use serde_json::{Value, json};
use std::io::Write;
use std::time::{Duration, Instant};

/// What the simulator emits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Emit {
    /// Raw marker observations (pixels), for `/observations`.
    Observations,
    /// Link poses solved here by PnP, for `/samples`.
    Samples,
    /// Rendered camera frames, for `/frames`.
    Frames,
}

impl Emit {
    /// What is sent, for messages.
    pub fn plural(self) -> &'static str {
        match self {
            Emit::Observations => "observations",
            Emit::Samples => "samples",
            Emit::Frames => "frames",
        }
    }
}

/// The observations of a group, as `/observations` items (the API's own type).
pub fn observation_items(group: &SimGroup) -> Vec<Value> {
    let time = Value::String(format_ns(group.time_ns));
    group
        .observations
        .iter()
        .filter_map(|o| {
            serde_json::to_value(ObservationIn {
                camera: o.camera.clone(),
                marker: o.marker.clone(),
                time: time.clone(),
                points_px: o.points_px.clone(),
                ids: None,
                sigma_px: None,
            })
            .ok()
        })
        .collect()
}

fn pose_json(p: &crate::geometry::Pose) -> Value {
    let out = PoseOut::from(p);
    json!({"t_mm": out.t_mm, "q_wxyz": out.q_wxyz})
}

/// The group as `/samples` items: observations solved by PnP here (an observation PnP refuses
/// is left out, as a pipeline would drop it), and the samples of links without a camera model.
pub fn sample_items(group: &SimGroup, observer: &Observer) -> Vec<Value> {
    let time = format_ns(group.time_ns);
    let mut out = Vec::new();
    for o in &group.observations {
        if let Ok((link, s)) = observer.solve(&o.camera, &o.marker, &o.points_px, None, None) {
            let cov: Vec<f64> = s.covariance.transpose().iter().copied().collect();
            out.push(json!({"link": link.name, "time": time,
                "pose": pose_json(&s.camera_from_marker), "covariance": cov,
                "quality": {"reprojection_rms_px": s.rms_px, "points": s.points}}));
        }
    }
    for s in &group.samples {
        out.push(json!({"link": s.link, "time": time, "pose": pose_json(&s.pose),
            "sigma": {"rotation_arcsec": s.sigma.rotation_arcsec, "translation_mm": s.sigma.translation_mm}}));
    }
    out
}

/// One line of the ground-truth file: every target's and measured link's true pose.
pub fn truth_line(group: &SimGroup) -> Value {
    let poses = |named: &[(String, crate::geometry::Pose)]| -> serde_json::Map<String, Value> {
        named
            .iter()
            .map(|(name, p)| {
                (
                    name.clone(),
                    serde_json::to_value(PoseOut::from(p)).unwrap_or(Value::Null),
                )
            })
            .collect()
    };
    json!({"time": format_ns(group.time_ns), "targets": poses(&group.truth), "links": poses(&group.link_truth)})
}

/// Where a run goes.
pub enum Sink {
    /// NDJSON: one item a line (observations or samples), ready to replay.
    File(std::io::BufWriter<std::fs::File>),
    /// Frames: `DIR/<camera>/<time>.png`.
    Dir(std::path::PathBuf),
    /// A running service.
    Http(Client),
}

/// A small client of a brokenray service.
pub struct Client {
    http: reqwest::Client,
    base: String,
    token: Option<String>,
}

impl Client {
    /// A client of the service at `base` (`http://host:port`).
    pub fn new(base: &str, token: Option<String>) -> anyhow::Result<Self> {
        let base = base.trim_end_matches('/').to_owned();
        if !base.starts_with("http://") && !base.starts_with("https://") {
            bail!("`{base}` is not an http:// URL of a brokenray service");
        }
        let http = reqwest::Client::builder()
            .timeout(Duration::from_secs(30))
            .build()
            .context("cannot build the HTTP client")?;
        Ok(Self { http, base, token })
    }

    /// POSTs JSON to `path` (under the base URL); an error names the status and the answer.
    pub async fn post(&self, path: &str, body: &Value) -> anyhow::Result<Value> {
        let (status, answer) = self.post_status(path, body).await?;
        if !status.is_success() {
            bail!("{path} answered {status}: {answer}");
        }
        Ok(answer)
    }

    /// DELETEs `path`; an error names the status.
    pub async fn delete(&self, path: &str) -> anyhow::Result<()> {
        let response = self
            .send(path, self.http.delete(format!("{}{path}", self.base)))
            .await?;
        let status = response.status();
        if !status.is_success() {
            bail!("{path} answered {status}");
        }
        Ok(())
    }

    /// GETs JSON from `path`; an error names the status.
    pub async fn get_json(&self, path: &str) -> anyhow::Result<Value> {
        let response = self
            .send(path, self.http.get(format!("{}{path}", self.base)))
            .await?;
        let status = response.status();
        if !status.is_success() {
            bail!("{path} answered {status}");
        }
        Ok(response.json().await?)
    }

    /// GETs `path` with `query` and returns the answer's text, waiting for it up to `timeout`;
    /// an error names the status and the service's answer.
    pub async fn get_text(
        &self,
        path: &str,
        query: &[(&str, String)],
        timeout: Duration,
    ) -> anyhow::Result<String> {
        let request = self
            .http
            .get(format!("{}{path}", self.base))
            .query(query)
            .timeout(timeout);
        let response = self.send(path, request).await?;
        let status = response.status();
        let text = response.text().await?;
        if !status.is_success() {
            bail!("{path} answered {status}: {text}");
        }
        Ok(text)
    }

    /// Sends a request for `path` with the token; an error says the service cannot be reached.
    async fn send(
        &self,
        path: &str,
        mut request: reqwest::RequestBuilder,
    ) -> anyhow::Result<reqwest::Response> {
        if let Some(t) = &self.token {
            request = request.bearer_auth(t);
        }
        request
            .send()
            .await
            .with_context(|| format!("cannot reach {}{path}", self.base))
    }

    /// POSTs a camera frame file to `/api/v1/frames`: the status and the answer.
    pub async fn post_frame(
        &self,
        camera: &str,
        time_ns: i64,
        format: crate::imagefile::FrameFormat,
        bytes: Vec<u8>,
    ) -> anyhow::Result<(reqwest::StatusCode, Value)> {
        let url = format!("{}/api/v1/frames", self.base);
        let mut request = self
            .http
            .post(&url)
            .query(&[("camera", camera), ("time", &format_ns(time_ns))])
            .header(reqwest::header::CONTENT_TYPE, format.content_type())
            .body(bytes);
        if let Some(t) = &self.token {
            request = request.bearer_auth(t);
        }
        let response = request
            .send()
            .await
            .with_context(|| format!("cannot reach {url}"))?;
        let status = response.status();
        let answer: Value = response.json().await.unwrap_or(Value::Null);
        Ok((status, answer))
    }

    /// POSTs JSON to `path`: the status and the answer; an error only when there is no answer.
    pub async fn post_status(
        &self,
        path: &str,
        body: &Value,
    ) -> anyhow::Result<(reqwest::StatusCode, Value)> {
        let mut request = self.http.post(format!("{}{path}", self.base)).json(body);
        if let Some(t) = &self.token {
            request = request.bearer_auth(t);
        }
        let response = request
            .send()
            .await
            .with_context(|| format!("cannot reach {}{path}", self.base))?;
        let status = response.status();
        let answer: Value = response.json().await.unwrap_or(Value::Null);
        Ok((status, answer))
    }
}

/// How a run is paced and packed.
#[derive(Debug, Clone)]
pub struct FeedSettings {
    /// Groups per second of the simulation (the real-time pace).
    pub rate_hz: f64,
    /// Shows progress (hidden when standard error is not a terminal).
    pub progress: indicatif::ProgressBar,
    /// Observations or samples.
    pub emit: Emit,
    /// Groups to send (`None`: until stopped).
    pub groups: Option<u64>,
    /// Send in real time (one group per period) instead of as fast as possible.
    pub real_time: bool,
    /// Groups per request when not in real time.
    pub groups_per_request: usize,
    /// Sub-pixel samples per pixel side where a disc's edge runs, for rendered frames: 32
    /// keeps the truth within about a thousandth of a pixel; the demo's 8, within a few, at a
    /// sixteenth of the work.
    pub render_samples_per_side: usize,
}

/// Counts of a run.
#[derive(Debug, Clone, Copy, Default)]
pub struct FeedSummary {
    /// Groups generated.
    pub groups: u64,
    /// Items (observations or samples) sent or written.
    pub items: u64,
    /// Items in requests the service refused as invalid (422): a refused observation (PnP
    /// finds no acceptable pose) loses its group, the run goes on.
    pub refused: u64,
}

/// Runs the simulator into a sink, with a progress bar, until `groups` are done or `stop`
/// resolves. `on_group` sees every group after it is sent (the demo sets its reference there).
pub async fn feed(
    sim: &mut Simulator,
    mut sink: Sink,
    mut truth: Option<std::io::BufWriter<std::fs::File>>,
    settings: FeedSettings,
    mut stop: impl std::future::Future<Output = ()> + Unpin,
    mut on_group: impl AsyncFnMut(&SimGroup, &Sink) -> anyhow::Result<()>,
) -> anyhow::Result<FeedSummary> {
    let started = Instant::now();
    let period = Duration::from_secs_f64(1.0 / settings.rate_hz);
    let progress = settings.progress.clone();
    let per_request = if settings.real_time {
        1
    } else {
        settings.groups_per_request.max(1)
    };
    let mut summary = FeedSummary::default();
    let mut pending: Vec<Value> = Vec::new();
    let mut last_group: Option<SimGroup> = None;
    loop {
        if settings.groups.is_some_and(|n| summary.groups >= n) {
            break;
        }
        if settings.real_time {
            let due = started + period * u32::try_from(summary.groups).unwrap_or(u32::MAX);
            tokio::select! {
                () = tokio::time::sleep_until(due.into()) => {}
                () = &mut stop => break,
            }
        }
        let group = sim.next_group();
        if let Some(t) = truth.as_mut() {
            writeln!(t, "{}", truth_line(&group)).context("cannot write the truth file")?;
        }
        let items = match settings.emit {
            Emit::Observations => observation_items(&group),
            Emit::Samples => sample_items(&group, sim.observer()),
            // Frames go one request each, never batched.
            Emit::Frames => {
                let frames = render_pngs(sim, &group, settings.render_samples_per_side).await?;
                summary.groups += 1;
                summary.items += frames.len() as u64;
                summary.refused += send_frames(&mut sink, group.time_ns, frames).await?;
                on_group(&group, &sink).await?;
                progress.inc(1);
                continue;
            }
        };
        summary.groups += 1;
        summary.items += items.len() as u64;
        pending.extend(items);
        let flush = summary.groups % per_request as u64 == 0
            || settings.groups.is_some_and(|n| summary.groups >= n);
        if flush {
            summary.refused += send(&mut sink, settings.emit, std::mem::take(&mut pending)).await?;
            on_group(&group, &sink).await?;
        }
        progress.inc(1);
        last_group = Some(group);
    }
    if !pending.is_empty() {
        summary.refused += send(&mut sink, settings.emit, std::mem::take(&mut pending)).await?;
        if let Some(g) = &last_group {
            on_group(g, &sink).await?;
        }
    }
    if let Sink::File(f) = &mut sink {
        f.flush().context("cannot write the output file")?;
    }
    if let Some(t) = truth.as_mut() {
        t.flush().context("cannot write the truth file")?;
    }
    progress.finish();
    Ok(summary)
}

/// Every camera's frame of a group, rendered and encoded as PNG on the blocking pool (a
/// frame takes tens of milliseconds: never on the async workers, which may be serving).
pub(crate) async fn render_pngs(
    sim: &Simulator,
    group: &SimGroup,
    samples_per_side: usize,
) -> anyhow::Result<Vec<(String, Vec<u8>)>> {
    let scenes = sim.frame_scenes(group);
    tokio::task::spawn_blocking(move || {
        let settings = crate::sim::render::RenderSettings {
            samples_per_side,
            ..Default::default()
        };
        // Each camera's frame on a thread of its own: a group's frames take the cores there
        // are rather than one.
        std::thread::scope(|threads| {
            let handles: Vec<_> = scenes
                .into_iter()
                .map(|scene| {
                    threads.spawn(move || {
                        let png = crate::imagefile::encode_png_fast(&scene.render(&settings))?;
                        Ok::<_, anyhow::Error>((scene.camera, png))
                    })
                })
                .collect();
            handles
                .into_iter()
                .map(|h| {
                    h.join()
                        .map_err(|_| anyhow::anyhow!("a frame's renderer panicked"))?
                })
                .collect::<anyhow::Result<Vec<_>>>()
        })
    })
    .await
    .context("the frame renderer stopped")?
}

/// Sends or writes a group's frames; answers how many the service refused as invalid.
async fn send_frames(
    sink: &mut Sink,
    time_ns: i64,
    frames: Vec<(String, Vec<u8>)>,
) -> anyhow::Result<u64> {
    let mut refused = 0;
    for (camera, png) in frames {
        match sink {
            Sink::Dir(dir) => {
                let folder = dir.join(&camera);
                std::fs::create_dir_all(&folder)
                    .with_context(|| format!("cannot create {}", folder.display()))?;
                let path = folder.join(format!("{}.png", crate::clock::format_ns_fixed(time_ns)));
                std::fs::write(&path, png)
                    .with_context(|| format!("cannot write {}", path.display()))?;
            }
            Sink::Http(client) => {
                let (status, answer) = client
                    .post_frame(&camera, time_ns, crate::imagefile::FrameFormat::Png, png)
                    .await?;
                if status == reqwest::StatusCode::UNPROCESSABLE_ENTITY {
                    tracing::warn!(%answer, camera, "the service refused a frame; going on");
                    refused += 1;
                } else if !status.is_success() {
                    bail!("/api/v1/frames answered {status}: {answer}");
                }
            }
            Sink::File(_) => bail!("frames are written to a directory, not to one file"),
        }
    }
    Ok(refused)
}

/// Sends one request's items; answers how many the service refused as invalid.
async fn send(sink: &mut Sink, emit: Emit, items: Vec<Value>) -> anyhow::Result<u64> {
    if items.is_empty() {
        return Ok(0);
    }
    match sink {
        Sink::Dir(_) => bail!("observations and samples are written to a file, not a directory"),
        Sink::File(f) => {
            for item in &items {
                writeln!(f, "{item}").context("cannot write the output file")?;
            }
            Ok(0)
        }
        Sink::Http(client) => {
            let (path, body) = match emit {
                Emit::Observations => ("/api/v1/observations", json!({"observations": items})),
                Emit::Samples => ("/api/v1/samples", json!({"samples": items})),
                Emit::Frames => bail!("frames are posted one by one, not in JSON batches"),
            };
            let (status, answer) = client.post_status(path, &body).await?;
            if status.is_success() {
                Ok(0)
            } else if status == reqwest::StatusCode::UNPROCESSABLE_ENTITY {
                tracing::warn!(%answer, "the service refused a batch; going on");
                Ok(items.len() as u64)
            } else {
                bail!("{path} answered {status}: {answer}")
            }
        }
    }
}

/// Parses a duration: `90`, `90s`, `15m`, `2h`, `1d`.
pub fn parse_duration_s(text: &str) -> Result<f64, String> {
    let t = text.trim();
    let (number, unit) = match t.find(|c: char| c.is_ascii_alphabetic()) {
        Some(i) => (&t[..i], &t[i..]),
        None => (t, "s"),
    };
    let factor = match unit {
        "s" => 1.0,
        "m" | "min" => 60.0,
        "h" => 3600.0,
        "d" => 86400.0,
        other => {
            return Err(format!(
                "unknown unit `{other}` in `{text}`: use s, m, h or d"
            ));
        }
    };
    let v: f64 = number
        .trim()
        .parse()
        .map_err(|_| format!("`{text}` is not a duration (for example 60s, 15m, 2h)"))?;
    if !(v.is_finite() && v > 0.0) {
        return Err(format!("the duration must be positive, not `{text}`"));
    }
    Ok(v * factor)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_parse_with_their_units_and_bad_ones_are_named() {
        assert_eq!(parse_duration_s("60s"), Ok(60.0));
        assert_eq!(parse_duration_s("90"), Ok(90.0));
        assert_eq!(parse_duration_s("15m"), Ok(900.0));
        assert_eq!(parse_duration_s("2h"), Ok(7200.0));
        assert!(
            parse_duration_s("3w")
                .expect_err("unit")
                .contains("unknown unit `w`")
        );
        assert!(
            parse_duration_s("-5s")
                .expect_err("negative")
                .contains("positive")
        );
        assert!(parse_duration_s("abc").is_err());
    }
}
