//! A period's report gathered from the store and the filters: what [`crate::report::period`]
//! draws. Each figure is read the way the API reads it for the same period (the statistics
//! of `GET .../stats`, the buckets of `GET .../history`, the budget of `GET .../budget`), so
//! the page and the API agree.

use super::Service;
use crate::bank::ResultSource;
use crate::chain::LinkId;
use crate::config::ReportSettings;
use crate::model::{LinkKind, TargetId};
use crate::report::period::{
    BudgetSnapshot, CalibrationLine, CameraLine, Gap, Gaps, LinkInGap, PeriodReport, SourceWindow,
    TargetReport,
};
use crate::store::{StoreError, StoreResult};
use std::path::PathBuf;

/// The buckets of each picture: enough for a page's width.
pub const REPORT_BUCKETS: usize = 600;

/// The gaps listed per target, the longest first (all are counted).
pub const LISTED_GAPS: usize = 50;

/// The gaps read per target: past it the count and total are "at least".
const MOST_GAPS: i64 = 100_000;

/// The alarm transitions read per target.
const MOST_ALARMS: i64 = 10_000;

/// What a report covers: `[from_ns, to_ns]`, and the silence that counts as a gap.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReportWindow {
    /// Start (ns).
    pub from_ns: i64,
    /// End (ns).
    pub to_ns: i64,
    /// A silence between raw results longer than this is a gap (ns).
    pub min_gap_ns: i64,
}

/// The last period of `every_ns` that has ended by `now_ns`: `(from, to)`, the periods counted
/// from 1970-01-01T00:00:00Z so that a restart does not move them.
pub fn last_complete_period(now_ns: i64, every_ns: i64) -> (i64, i64) {
    let to = now_ns.div_euclid(every_ns) * every_ns;
    (to.saturating_sub(every_ns), to)
}

/// The file of a period's report: `brokenray-report-FROM--TO.html`, the times in RFC 3339 with
/// `-` for `:` (which some file systems refuse).
pub fn report_file_name(from_ns: i64, to_ns: i64) -> String {
    let stamp = |ns: i64| crate::clock::format_ns(ns).replace(':', "-");
    format!("brokenray-report-{}--{}.html", stamp(from_ns), stamp(to_ns))
}

impl Service {
    /// Files the report of the last period of `settings` that has ended, in its folder, when
    /// it is not there yet: the file written, or `None` when it was there. The page is written
    /// beside its name and renamed into place once on disk, so a crash leaves no half report
    /// under a report's name. A failure is kept as [`Service::report_problem`] until a later
    /// report is filed.
    pub async fn file_due_report(
        &self,
        settings: &ReportSettings,
    ) -> Result<Option<PathBuf>, String> {
        let result = self.try_file_due_report(settings).await;
        let problem = result.as_ref().err().cloned();
        *self
            .inner
            .report_problem
            .lock()
            .unwrap_or_else(|p| p.into_inner()) = problem;
        result
    }

    async fn try_file_due_report(
        &self,
        settings: &ReportSettings,
    ) -> Result<Option<PathBuf>, String> {
        let (from_ns, to_ns) = last_complete_period(self.now_ns(), settings.every_ns);
        let path = settings.folder.join(report_file_name(from_ns, to_ns));
        if tokio::fs::try_exists(&path).await.unwrap_or(false) {
            return Ok(None);
        }
        let report = self
            .period_report(ReportWindow {
                from_ns,
                to_ns,
                min_gap_ns: settings.min_gap_ns,
            })
            .await
            .map_err(|e| format!("the report of {} could not be read: {e}", path.display()))?;
        let page = crate::report::period::render(&report);
        let target = path.clone();
        tokio::task::spawn_blocking(move || write_new(&target, page.as_bytes()))
            .await
            .map_err(|e| format!("the report's writer stopped: {e}"))?
            .map_err(|e| format!("{} could not be written: {e}", path.display()))?;
        Ok(Some(path))
    }

    /// Why the last scheduled report could not be filed, until one is.
    pub fn report_problem(&self) -> Option<String> {
        self.inner
            .report_problem
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// The report of `window`: read under one heavy-read permit, as a long history is.
    pub async fn period_report(&self, window: ReportWindow) -> Result<PeriodReport, StoreError> {
        let _permit = self.heavy_read().await;
        let inst = self.installation();
        let model = &inst.model;
        let store = self.store();
        let cameras = model
            .cameras
            .iter()
            .map(|c| CameraLine {
                frame: c.frame.clone(),
                intrinsics: c.intrinsics,
                pixel_sigma_px: c.pixel_sigma_px,
                intrinsics_sigma_px: c
                    .intrinsics_covariance
                    .map(|cov| std::array::from_fn(|i| cov[(i, i)].max(0.0).sqrt())),
                has_report: inst.calibration_reports.iter().any(|r| r.camera == c.frame),
            })
            .collect();
        let mut calibrations = Vec::new();
        for link in &model.links {
            let LinkKind::Calibrated { parent_from_child } = &link.kind else {
                continue;
            };
            let stored = store.calibrations(link.id).await?;
            // The version in force when the period starts, and every one made during it.
            let in_force_at_start = stored
                .iter()
                .rposition(|c| c.valid_from_ns <= window.from_ns);
            let shown: Vec<CalibrationLine> = stored
                .iter()
                .enumerate()
                .filter(|(i, c)| {
                    Some(*i) == in_force_at_start
                        || (c.valid_from_ns > window.from_ns && c.valid_from_ns <= window.to_ns)
                })
                .map(|(_, c)| CalibrationLine {
                    link: link.name.clone(),
                    version: Some(c.version),
                    valid_from_ns: Some(c.valid_from_ns),
                    sigma: c.parent_from_child.reported_sigmas().axes(),
                })
                .collect();
            if in_force_at_start.is_none() {
                calibrations.push(CalibrationLine {
                    link: link.name.clone(),
                    version: None,
                    valid_from_ns: None,
                    sigma: parent_from_child.reported_sigmas().axes(),
                });
            }
            calibrations.extend(shown);
        }
        let mut targets = Vec::new();
        for (i, spec) in model.targets.iter().enumerate() {
            targets.push(self.target_report(TargetId(i), &spec.name, window).await?);
        }
        Ok(PeriodReport {
            installation: inst.source.clone(),
            generated_ns: self.now_ns(),
            from_ns: window.from_ns,
            to_ns: window.to_ns,
            min_gap_ns: window.min_gap_ns,
            cameras,
            calibrations,
            targets,
            acceptance: self.acceptance_section(window.to_ns).await?,
        })
    }

    async fn target_report(
        &self,
        ti: TargetId,
        name: &str,
        window: ReportWindow,
    ) -> Result<TargetReport, StoreError> {
        let store = self.store();
        let (from, to) = (window.from_ns, window.to_ns);
        // The long reads at once, each on a connection of its own (on PostgreSQL the server
        // folds one while this process decodes another).
        let ((raw_stats, raw_span), (filtered_stats, _), raw_history, filtered_history, inner_gaps) =
            tokio::try_join!(
                store.pose_stats(ti, ResultSource::Raw, from, to),
                store.pose_stats(ti, ResultSource::Filtered, from, to),
                store.history(ti, ResultSource::Raw, from, to, REPORT_BUCKETS),
                store.history(ti, ResultSource::Filtered, from, to, REPORT_BUCKETS),
                store.result_gaps(
                    ti,
                    ResultSource::Raw,
                    (from, to),
                    window.min_gap_ns,
                    MOST_GAPS
                ),
            )?;
        let raw = SourceWindow {
            stats: raw_stats,
            history: raw_history,
        };
        let filtered = SourceWindow {
            stats: filtered_stats,
            history: filtered_history,
        };
        let reference = store
            .references(ti)
            .await?
            .into_iter()
            .filter(|r| r.created_ns <= to)
            .max_by_key(|r| r.version)
            .map(|r| (r.version, r.created_ns));
        let alarms = store.alarms(Some(ti), from, to, MOST_ALARMS, false).await?;
        let gaps = self.gaps(ti, window, raw_span, inner_gaps).await?;
        let snapshot = self.snapshot();
        let model = snapshot.bank.model();
        let budget = snapshot
            .bank
            .budget(ti, ResultSource::Filtered)
            .map(|(time_ns, budget)| BudgetSnapshot {
                time_ns,
                names: budget
                    .lines
                    .iter()
                    .map(|l| {
                        (
                            l.contributor,
                            model.contributor_name(l.contributor).to_owned(),
                        )
                    })
                    .collect(),
                budget,
            });
        Ok(TargetReport {
            name: name.to_owned(),
            raw,
            filtered,
            reference,
            alarms,
            gaps,
            budget,
        })
    }

    /// The silences of a target's raw results in the window: `inner` between results (as
    /// [`crate::store::Store::result_gaps`] gives them), and from the window's start to its
    /// first result and from its last to the end (`raw_span`), with what its measured links
    /// stored in the longest.
    async fn gaps(
        &self,
        ti: TargetId,
        window: ReportWindow,
        raw_span: Option<(i64, i64)>,
        inner: Vec<(i64, i64)>,
    ) -> StoreResult<Gaps> {
        let store = self.store();
        // The period's end, or now when it lies ahead: the future is not a gap.
        let end = window.to_ns.min(self.now_ns()).max(window.from_ns);
        let mut truncated = false;
        let mut spans: Vec<(i64, i64)> = match raw_span {
            None => vec![(window.from_ns, end)],
            Some((first, last)) => {
                truncated = i64::try_from(inner.len()).unwrap_or(i64::MAX) >= MOST_GAPS;
                let mut spans = Vec::with_capacity(inner.len() + 2);
                spans.push((window.from_ns, first));
                spans.extend(inner);
                spans.push((last, end));
                spans
            }
        };
        spans.retain(|(a, b)| b - a > window.min_gap_ns);
        let count = spans.len();
        let total_ns = spans.iter().map(|(a, b)| b - a).sum();
        spans.sort_by_key(|(a, b)| std::cmp::Reverse(b - a));
        spans.truncate(LISTED_GAPS);
        let model = &self.installation().model;
        let measured: Vec<LinkId> = {
            let mut links: Vec<LinkId> = model.targets[ti.0]
                .resolution
                .paths
                .iter()
                .flat_map(|p| p.links())
                .filter(|l| matches!(model.link(*l).kind, LinkKind::Measured(_)))
                .collect();
            links.sort_by_key(|l| l.0);
            links.dedup();
            links
        };
        let mut listed = Vec::with_capacity(spans.len());
        for (from_ns, to_ns) in spans {
            let mut links = Vec::with_capacity(measured.len());
            for &link in &measured {
                // Strictly inside: the results at the ends are not the gap's.
                let count = store
                    .count_samples_and_outliers(link, from_ns + 1, to_ns - 1)
                    .await?;
                links.push(LinkInGap {
                    link: model.link(link).name.clone(),
                    samples: count.stored,
                    outliers: count.outliers,
                });
            }
            listed.push(Gap {
                from_ns,
                to_ns,
                links,
            });
        }
        Ok(Gaps {
            listed,
            count,
            total_ns,
            truncated,
        })
    }
}

/// Writes `bytes` to `path` through a temporary file beside it, synced before it is renamed
/// into place (the folder made when missing, and synced after the rename).
fn write_new(path: &std::path::Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write as _;
    let folder = path.parent().unwrap_or(std::path::Path::new("."));
    std::fs::create_dir_all(folder)?;
    let mut part = path.as_os_str().to_owned();
    part.push(".part");
    let part = PathBuf::from(part);
    let mut file = std::fs::File::create(&part)?;
    file.write_all(bytes)?;
    file.sync_all()?;
    std::fs::rename(&part, path)?;
    std::fs::File::open(folder)?.sync_all()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn periods_are_counted_from_the_epoch_and_named_by_their_ends() {
        let day = 86_400 * 1_000_000_000_i64;
        // 2026-11-27T15:00:00Z: the last whole day is the 26th.
        let now = 1_795_777_200_000_000_000;
        let (from, to) = last_complete_period(now, day);
        assert_eq!((to - from, to % day), (day, 0));
        assert!(to <= now && now - to < day);
        assert_eq!(
            report_file_name(from, to),
            "brokenray-report-2026-11-26T00-00-00Z--2026-11-27T00-00-00Z.html"
        );
        // At a period's very end it is complete.
        assert_eq!(last_complete_period(to, day), (from, to));
    }
}
