//! `brokenray detect`: frame files of one camera turned into observations (NDJSON lines ready
//! for `POST /api/v1/observations`), for pipelines that detect next to the camera.
//!
//! Each file's time is `--time` (one file only), else its name's stem when that is a time
//! (`2026-11-21T10:00:00.040Z.png`, `1763719200040000000.pgm`), else its modification time.
//! A marker's points are predicted from its pose in the previous file where it was found, else
//! from its link's nominal pose; files are taken in the order given.

use crate::clock::{format_ns, parse_query_time};
use crate::config::Installation;
use crate::geometry::Pose;
use crate::imagefile::{FrameFormat, decode};
use crate::model::{Observer, observe_frame};
use crate::wire::ObservationIn;
use anyhow::{Context, bail};
use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};

/// What a run did.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct DetectSummary {
    /// Frames read.
    pub frames: usize,
    /// Observations printed.
    pub observations: usize,
    /// Markers not found (each reported on `log`).
    pub not_found: usize,
}

/// Detects `camera`'s markers in `files`, writing observations to `out` and what was not
/// found to `log`.
pub fn detect_files(
    installation: &Installation,
    camera: &str,
    time: Option<&str>,
    files: &[PathBuf],
    out: &mut impl Write,
    log: &mut impl Write,
) -> anyhow::Result<DetectSummary> {
    if time.is_some() && files.len() != 1 {
        bail!(
            "--time stamps one frame, not {}: name the files by their time instead",
            files.len()
        );
    }
    let observer = Observer::new(&installation.model);
    let size = observer
        .camera(camera)
        .map(|c| (c.width_px, c.height_px))
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut last: HashMap<usize, Pose> = HashMap::new();
    let mut summary = DetectSummary::default();
    for path in files {
        let time_ns = match time {
            Some(t) => parse_query_time(t).map_err(|m| anyhow::anyhow!("--time: {m}"))?,
            None => time_of(path)?,
        };
        let format = FrameFormat::from_path(path).ok_or_else(|| {
            anyhow::anyhow!(
                "{}: not a frame file (.png, .jpg, .jpeg, .tif, .tiff or .pgm)",
                path.display()
            )
        })?;
        let bytes =
            std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
        let image = decode(&bytes, format, Some(size))
            .map_err(|e| anyhow::anyhow!("{}: {e} (camera {camera})", path.display()))?;
        // The pose in the previous frame (the nominal one follows by itself).
        let predictions = |link: &crate::model::ObservedLink| -> Vec<Pose> {
            last.get(&link.link.0).copied().into_iter().collect()
        };
        let seen = observe_frame(&observer, camera, &image, predictions)
            .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        summary.frames += 1;
        for m in &seen.markers {
            match &m.result {
                Ok(found) => {
                    last.insert(m.link.link.0, found.solution.camera_from_marker);
                    let observation = ObservationIn {
                        camera: camera.to_owned(),
                        marker: m.link.marker_frame.clone(),
                        time: serde_json::Value::String(format_ns(time_ns)),
                        points_px: found.points_px.clone(),
                        ids: Some(found.ids.clone()),
                        sigma_px: Some(found.sigma_px.clone()),
                    };
                    writeln!(out, "{}", serde_json::to_string(&observation)?)?;
                    summary.observations += 1;
                }
                Err(why) => {
                    writeln!(
                        log,
                        "{}: marker {} not found: {why}",
                        path.display(),
                        m.link.marker_frame
                    )?;
                    summary.not_found += 1;
                }
            }
        }
    }
    Ok(summary)
}

/// A file's time: its name's stem when that is one, else its modification time.
pub(super) fn time_of(path: &Path) -> anyhow::Result<i64> {
    if let Some(stem) = path.file_stem().and_then(|s| s.to_str())
        && let Ok(t) = parse_query_time(stem)
    {
        return Ok(t);
    }
    let modified = std::fs::metadata(path)
        .and_then(|m| m.modified())
        .with_context(|| {
            format!(
                "{}: no time in its name and no modification time",
                path.display()
            )
        })?;
    let since = modified
        .duration_since(std::time::UNIX_EPOCH)
        .with_context(|| format!("{}: modified before 1970", path.display()))?;
    i64::try_from(since.as_nanos())
        .with_context(|| format!("{}: modification time out of range", path.display()))
}
