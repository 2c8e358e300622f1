//! `brokenray replay`: a recording rebuilt from the stored history, so that any past period can
//! be reviewed in Rerun even when nothing was recorded live.
//!
//! Every stored result of the period becomes a point (raw and filtered, no decimation); every
//! stored sample of the targets' measured links its NIS (and outlier mark); every alarm
//! transition its lane change and log line; each reference version its frame; every frame the
//! archive kept of the period (`[frames] archive_dir`) its image under its camera. The filtered
//! link poses are not stored, so the frame tree is placed by the links' raw samples (and the
//! calibrations), at most `scene_hz` times a second.

use super::logger::Logger;
use super::{Decimator, Record, VizCounters};
use crate::bank::ResultSource;
use crate::config::Installation;
use crate::deformation::Deformation;
use crate::model::LinkKind;
use crate::model::TargetId;
use crate::store::Store;
use std::path::Path;
use std::sync::Arc;

/// Rows read from the database at a time.
const PAGE: i64 = 20_000;

/// What was written.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct ReplaySummary {
    /// Filtered results.
    pub filtered: u64,
    /// Raw results.
    pub raw: u64,
    /// Samples.
    pub samples: u64,
    /// Alarm transitions.
    pub alarms: u64,
    /// Archived camera frames.
    pub frames: u64,
}

/// Errors of a replay.
#[derive(Debug, thiserror::Error)]
pub(crate) enum ReplayError {
    /// The database could not be read.
    #[error(transparent)]
    Store(#[from] crate::store::StoreError),
    /// The recording could not be written.
    #[error(transparent)]
    Viz(#[from] super::VizError),
    /// The frame archive could not be read.
    #[error("the frame archive cannot be read: {0}")]
    Archive(std::io::Error),
}

/// Writes the period `[from_ns, to_ns]` of `targets` (indices; all when empty) to `out`.
/// `progress` is told the number of rows done and the total.
pub(crate) async fn replay(
    inst: &Arc<Installation>,
    store: &Store,
    targets: &[TargetId],
    from_ns: i64,
    to_ns: i64,
    out: &Path,
    progress: &mut dyn FnMut(u64, u64),
) -> Result<ReplaySummary, ReplayError> {
    let targets: Vec<TargetId> = if targets.is_empty() {
        inst.model.target_ids().map(|(t, _)| t).collect()
    } else {
        targets.to_vec()
    };
    let mut links: Vec<usize> = targets
        .iter()
        .flat_map(|&t| inst.model.targets[t.0].resolution.paths.iter())
        .flat_map(|p| p.links())
        .map(|l| l.0)
        .filter(|&l| matches!(inst.model.links[l].kind, LinkKind::Measured(_)))
        .collect();
    links.sort_unstable();
    links.dedup();
    let mut total = 0u64;
    for &t in &targets {
        for &source in ResultSource::ALL {
            total += store.count_results(t, source, from_ns, to_ns).await?;
        }
    }
    for &l in &links {
        total += store
            .count_samples(crate::chain::LinkId(l), from_ns, to_ns)
            .await?;
    }
    let name = format!(
        "brokenray replay {} .. {}",
        crate::clock::format_ns(from_ns),
        crate::clock::format_ns(to_ns)
    );
    let mut logger = Logger::to_file(inst, out, &name, Arc::new(VizCounters::default()))?;
    let mut summary = ReplaySummary::default();
    let mut done = 0u64;
    progress(0, total);

    for &t in &targets {
        let references = store.references(t).await?;
        for r in &references {
            logger.log(&Record::Reference {
                target: t,
                time_ns: r.created_ns.clamp(from_ns, to_ns),
                g0_from_b: r.reference.g0_from_b.whole.pose,
            });
        }
        for &source in ResultSource::ALL {
            let mut cursor = from_ns;
            loop {
                let page = store.results(t, source, cursor, to_ns, PAGE).await?;
                let Some(last) = page.last().map(|r| r.time_ns) else {
                    break;
                };
                let mut batch = Vec::with_capacity(page.len());
                for r in &page {
                    let deformation = r.deformation.and_then(|(version, _, _)| {
                        references
                            .iter()
                            .find(|x| x.version == version)
                            .map(|x| Deformation::new(&x.reference, &r.estimate).deformation())
                    });
                    batch.push(Record::Result {
                        target: t,
                        time_ns: r.time_ns,
                        source,
                        target_from_base: r.estimate,
                        deformation,
                    });
                }
                logger.log_batch(&batch);
                let n = page.len() as u64;
                match source {
                    ResultSource::Filtered => summary.filtered += n,
                    ResultSource::Raw => summary.raw += n,
                }
                done += n;
                progress(done, total);
                if (page.len() as i64) < PAGE || last == i64::MAX {
                    break;
                }
                cursor = last + 1;
            }
        }
    }

    // The links' samples, and the frame tree from them.
    // Links are read one after the other, so each has its own scene decimation.
    let mut scenes: Vec<Decimator> = inst
        .model
        .links
        .iter()
        .map(|_| Decimator::new(inst.rerun.scene_hz, f64::INFINITY))
        .collect();
    let mut poses: Vec<Option<crate::geometry::Pose>> = inst
        .model
        .links
        .iter()
        .map(|l| match &l.kind {
            LinkKind::Calibrated { parent_from_child } => Some(parent_from_child.pose),
            LinkKind::Measured(_) => None,
        })
        .collect();
    for &l in &links {
        let mut cursor = from_ns;
        loop {
            let page = store
                .samples(crate::chain::LinkId(l), cursor, to_ns, PAGE)
                .await?;
            let Some(last) = page.last().map(|s| s.time_ns) else {
                break;
            };
            let mut batch = Vec::with_capacity(page.len());
            for s in &page {
                batch.push(Record::Sample {
                    link: l,
                    time_ns: s.time_ns,
                    nis: s.nis,
                    outlier: s.outlier,
                });
                if !s.outlier {
                    poses[l] = Some(s.values.pose);
                    let record = Record::Scene {
                        time_ns: s.time_ns,
                        link_poses: poses.clone(),
                    };
                    if scenes[l].keep(&record) {
                        batch.push(record);
                    }
                }
            }
            logger.log_batch(&batch);
            summary.samples += page.len() as u64;
            done += page.len() as u64;
            progress(done, total);
            if (page.len() as i64) < PAGE || last == i64::MAX {
                break;
            }
            cursor = last + 1;
        }
    }

    for &t in &targets {
        for a in store
            .alarms(Some(t), from_ns, to_ns, i64::MAX, false)
            .await?
        {
            logger.log(&Record::Alarm {
                target: a.target,
                transition: a.transition,
            });
            summary.alarms += 1;
        }
    }
    // The archived frames of the period, when there is an archive: each under its camera, with
    // why it was kept in the camera's log when it is evidence.
    if let Some(dir) = &inst.frames.archive_dir
        && dir.is_dir()
    {
        let archived =
            crate::archive::archived_in(dir, from_ns, to_ns).map_err(ReplayError::Archive)?;
        for frame in archived {
            let Some(camera) = inst
                .model
                .cameras
                .iter()
                .position(|c| c.frame == frame.camera)
            else {
                continue;
            };
            let image = std::fs::read(&frame.path)
                .map_err(ReplayError::Archive)
                .and_then(|bytes| {
                    crate::imagefile::decode(&bytes, crate::imagefile::FrameFormat::Png, None)
                        .map_err(|e| ReplayError::Archive(std::io::Error::other(e)))
                });
            let image = match image {
                Ok(image) => image,
                Err(e) => {
                    // A file removed or damaged since: the rest of the replay still goes.
                    tracing::warn!(path = %frame.path.display(), error = %e, "an archived frame is left out of the replay");
                    continue;
                }
            };
            let evidence = match frame.reason {
                crate::archive::ArchiveReason::Periodic => None,
                reason => Some(format!("frame archived as evidence: {}", reason.name())),
            };
            logger.log(&Record::Frame {
                camera,
                time_ns: frame.time_ns,
                image: Arc::new(image),
                marks: evidence
                    .into_iter()
                    .map(|why| super::FrameMarks {
                        marker: String::new(),
                        points_px: Vec::new(),
                        ids: Vec::new(),
                        reprojected_px: Vec::new(),
                        not_found: Some(why),
                    })
                    .collect(),
                ticket: super::FrameTicket::none(),
            });
            summary.frames += 1;
        }
    }
    logger.close();
    Ok(summary)
}
