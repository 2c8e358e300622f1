//! An ingest job's filtering: its samples checked against what is stored (retries and
//! conflicts), fed to the bank, the groups it completes from the store, and the rows it writes.

use super::*;

fn nis_of(d: &Disposition) -> Option<f64> {
    match d {
        Disposition::Fused { nis }
        | Disposition::Outlier { nis, .. }
        | Disposition::Reinitialized { nis, .. } => Some(*nis).filter(|n| n.is_finite()),
        _ => None,
    }
}

fn deformation_of(
    targets: &[TargetView],
    target: TargetId,
    measured: &MeasuredPose,
) -> Option<(i64, crate::deformation::SmallMotion)> {
    let r = targets[target.0].reference?;
    Some((
        r.version,
        Deformation::new(&r.reference, measured).deformation(),
    ))
}

/// The row of a raw result.
fn raw_row(
    raw: &crate::bank::RawResult,
    deformation: Option<(i64, crate::deformation::SmallMotion)>,
) -> NewResult {
    NewResult {
        target: raw.target,
        source: ResultSource::Raw,
        time_ns: raw.time_ns,
        estimate: raw.target_from_base,
        status: raw.status(),
        age_s: 0.0,
        chi2: raw.consistency.map(|c| c.chi2),
        deformation,
    }
}

/// Where an ingest job puts what it shows in Rerun: the sender decides (decimation) before a
/// record is built; the records go out after the commit.
pub(super) struct VizCollect<'a> {
    pub(super) sender: &'a mut crate::viz::VizSender,
    pub(super) records: &'a mut Vec<crate::viz::Record>,
}

impl VizCollect<'_> {
    /// Shows a raw or filtered result, when the sender keeps its series at this time.
    fn result(
        &mut self,
        target: TargetId,
        source: ResultSource,
        time_ns: i64,
        target_from_base: MeasuredPose,
        deformation: Option<(i64, crate::deformation::SmallMotion)>,
    ) {
        let series = match source {
            ResultSource::Raw => Series::Raw(target),
            ResultSource::Filtered => Series::Filtered(target),
        };
        if self.sender.keep(series, time_ns) {
            self.records.push(crate::viz::Record::Result {
                target,
                time_ns,
                source,
                target_from_base,
                deformation: deformation.map(|(_, d)| d),
            });
        }
    }
}

/// One ingest job in the transaction: conflict checks against the store, filtering, groups
/// completed from the store, rows. `Ok(Err(..))` refuses the job alone (no effect on the bank
/// or the transaction); `Err` aborts the whole transaction.
pub(super) async fn ingest(
    tx: &mut WriteTx<'_>,
    bank: &mut FilterBank,
    targets: &mut [TargetView],
    items: Vec<IngestItem>,
    now: i64,
    new_transitions: &mut Vec<StoredAlarm>,
    viz: Option<VizCollect<'_>>,
) -> Result<ServiceResult<IngestReport>, StoreError> {
    let measurements = match measurements_of(bank, &items) {
        Ok(m) => m,
        Err(refusal) => return Ok(Err(refusal)),
    };
    // Retries and conflicts: compare with what is stored (earlier jobs of this transaction
    // included), link by link over the batch's time span.
    let stored = stored_over_spans(&mut SampleSource::Tx(tx), &spans_of(&items)).await?;
    let mut filtered = match filter_items(bank, targets, items, measurements, &stored, now, viz)? {
        Ok(f) => f,
        Err(refusal) => return Ok(Err(refusal)),
    };
    complete_stored_groups(&mut SampleSource::Tx(tx), bank, targets, &mut filtered).await?;
    let (report, rows) = filtered.into_rows(bank, targets);
    *new_transitions = write_rows(tx, std::slice::from_ref(&rows), now).await?;
    Ok(Ok(report))
}

/// The stored samples a batch may repeat: each link's over the batch's span of its times
/// (`spans`, from [`spans_of`]).
pub(super) async fn stored_over_spans(
    source: &mut SampleSource<'_, '_>,
    spans: &HashMap<LinkId, (i64, i64)>,
) -> Result<HashMap<(LinkId, i64), SampleValues>, StoreError> {
    let mut stored = HashMap::new();
    for (&link, &(from, to)) in spans {
        for (t, v) in source.samples(link, from, to).await? {
            stored.insert((link, t), v);
        }
    }
    Ok(stored)
}

/// Each link's span of a batch's times, `(first, last)`.
pub(super) fn spans_of(items: &[IngestItem]) -> HashMap<LinkId, (i64, i64)> {
    let mut spans: HashMap<LinkId, (i64, i64)> = HashMap::new();
    for item in items {
        let e = spans
            .entry(item.sample.link)
            .or_insert((item.sample.time_ns, item.sample.time_ns));
        e.0 = e.0.min(item.sample.time_ns);
        e.1 = e.1.max(item.sample.time_ns);
    }
    spans
}

/// Every item's measurement, checked before the bank sees any of them; the refusal names the
/// items whose uncertainties cannot be used.
pub(super) fn measurements_of(
    bank: &FilterBank,
    items: &[IngestItem],
) -> Result<Vec<crate::geometry::PoseCov>, ServiceError> {
    let mut problems = Vec::new();
    let mut measurements = Vec::with_capacity(items.len());
    for item in items {
        match bank.measurement(&item.sample) {
            Ok(z) => measurements.push(z),
            Err(e) => problems.push(ItemProblem {
                index: Some(item.index),
                field: Some("covariance".into()),
                message: e.to_string(),
            }),
        }
    }
    if problems.is_empty() {
        Ok(measurements)
    } else {
        Err(ServiceError::Invalid {
            message: format!(
                "{} sample(s) have unusable uncertainties; nothing was stored",
                problems.len()
            ),
            problems,
        })
    }
}

/// An ingest job checked and filtered, its rows not yet written.
pub(super) struct Filtered {
    pub(super) report: IngestReport,
    pub(super) sample_rows: Vec<NewSample>,
    pub(super) result_rows: BTreeMap<(TargetId, ResultSource, i64), NewResult>,
    pub(super) latest: HashMap<TargetId, TargetEstimate>,
    pub(super) transitions: Vec<(TargetId, crate::alarms::Transition)>,
    /// Samples too old for the groups kept in memory (a backfill): their groups are
    /// completed from this job's samples and the store's ([`complete_stored_groups`]).
    pub(super) stored_groups: Vec<(LinkId, i64, crate::geometry::PoseCov)>,
}

/// Whether a group filtered ahead can take its next job.
pub(super) enum Ahead {
    /// Yes.
    Next,
    /// No: this job's samples complete groups older than memory from other links' stored
    /// samples, which needs the store.
    NeedsStore(Box<(Job, Filtered)>),
    /// No: a defect (the job is among those filtered).
    Defect(StoreError),
}

/// What one ingest job writes: its samples, its results and its alarm transitions (nothing,
/// by default: a refused job).
#[derive(Default)]
pub(super) struct JobRows {
    pub(super) samples: Vec<NewSample>,
    pub(super) results: Vec<NewResult>,
    pub(super) transitions: Vec<(TargetId, crate::alarms::Transition)>,
}

/// Sorts out retries and conflicts against `stored` (the stored samples over the job's
/// span), then feeds the new samples to the bank in time order. `Ok(Err(..))` refuses the
/// job before the bank sees any sample; `Err` is a defect.
pub(super) fn filter_items(
    bank: &mut FilterBank,
    targets: &mut [TargetView],
    items: Vec<IngestItem>,
    measurements: Vec<crate::geometry::PoseCov>,
    stored: &HashMap<(LinkId, i64), SampleValues>,
    now: i64,
    mut viz: Option<VizCollect<'_>>,
) -> Result<ServiceResult<Filtered>, StoreError> {
    let mut report = IngestReport {
        accepted: items.len(),
        ..IngestReport::default()
    };
    let mut fresh = Vec::with_capacity(items.len());
    let mut conflicts = Vec::new();
    for (item, z) in items.into_iter().zip(measurements) {
        let values = SampleValues {
            pose: item.sample.parent_from_child,
            uncertainty: item.sample.uncertainty,
            quality: item.quality,
        };
        match stored.get(&(item.sample.link, item.sample.time_ns)) {
            Some(existing) if existing.same_as(&values) => report.duplicates += 1,
            Some(_) => conflicts.push(ItemProblem {
                index: Some(item.index),
                field: Some("time".into()),
                message: format!(
                    "a different sample of `{}` at this time is already stored",
                    bank.model().links[item.sample.link.0].name
                ),
            }),
            None => fresh.push((item, values, z)),
        }
    }
    if !conflicts.is_empty() {
        return Ok(Err(ServiceError::Conflict {
            message: format!(
                "{} sample(s) conflict with stored samples (same link and time, other values); nothing was stored",
                conflicts.len()
            ),
            problems: conflicts,
        }));
    }
    // Filter in time order, links in a fixed order within one time.
    fresh.sort_by_key(|(item, _, _)| (item.sample.time_ns, item.sample.link));
    let mut sample_rows = Vec::with_capacity(fresh.len());
    let mut result_rows: BTreeMap<(TargetId, ResultSource, i64), NewResult> = BTreeMap::new();
    let mut latest: HashMap<TargetId, TargetEstimate> = HashMap::new();
    let mut transitions: Vec<(TargetId, crate::alarms::Transition)> = Vec::new();
    let mut stored_groups: Vec<(LinkId, i64, crate::geometry::PoseCov)> = Vec::new();
    for (item, values, z) in fresh {
        let outcome = match bank.ingest_measurement(&item.sample, z) {
            Ok(o) => o,
            // Checked above; a failure here would be a defect, not bad input.
            Err(e) => {
                return Err(StoreError::Defect(format!(
                    "the filter refused a checked sample: {e}"
                )));
            }
        };
        let d = outcome.disposition;
        if outcome.needs_stored_group {
            stored_groups.push((item.sample.link, item.sample.time_ns, z));
        }
        report.stored += 1;
        match d {
            Disposition::Outlier { .. } => report.outliers += 1,
            Disposition::Reinitialized { .. } => {
                report.outliers += 1;
                report.reinitialized += 1;
            }
            Disposition::OutOfOrder { .. } => report.out_of_order += 1,
            _ => {}
        }
        if let Some(v) = viz.as_mut()
            && (d.is_outlier()
                || v.sender
                    .keep(Series::Link(item.sample.link.0), item.sample.time_ns))
        {
            v.records.push(crate::viz::Record::Sample {
                link: item.sample.link.0,
                time_ns: item.sample.time_ns,
                nis: nis_of(&d),
                outlier: d.is_outlier(),
            });
        }
        sample_rows.push(NewSample {
            link: item.sample.link,
            time_ns: item.sample.time_ns,
            values,
            disposition: d.kind(),
            outlier: d.is_outlier(),
            nis: nis_of(&d),
            received_ns: now,
        });
        for raw in &outcome.raw_results {
            report.raw_results += 1;
            let deformation = deformation_of(targets, raw.target, &raw.target_from_base);
            if let Some(v) = viz.as_mut() {
                v.result(
                    raw.target,
                    ResultSource::Raw,
                    raw.time_ns,
                    raw.target_from_base,
                    deformation,
                );
            }
            result_rows.insert(
                (raw.target, ResultSource::Raw, raw.time_ns),
                raw_row(raw, deformation),
            );
        }
        for est in outcome.filtered_results {
            let Some(pose) = est.target_from_base else {
                continue;
            };
            report.filtered_results += 1;
            let deformation = deformation_of(targets, est.target, &pose);
            if let Some(v) = viz.as_mut() {
                v.result(
                    est.target,
                    ResultSource::Filtered,
                    est.time_ns,
                    pose,
                    deformation,
                );
            }
            result_rows.insert(
                (est.target, ResultSource::Filtered, est.time_ns),
                NewResult {
                    target: est.target,
                    source: ResultSource::Filtered,
                    time_ns: est.time_ns,
                    estimate: pose,
                    status: est.status,
                    age_s: est.age_s,
                    chi2: est.consistency.map(|c| c.chi2),
                    deformation,
                },
            );
            let magnitudes = deformation
                .map(|(_, d)| (d.rotation_magnitude_arcsec(), d.translation_magnitude_mm()));
            for t in targets[est.target.0]
                .alarms
                .update(est.time_ns, pose.pose(), magnitudes)
            {
                transitions.push((est.target, t));
            }
            latest.insert(est.target, est);
        }
    }
    Ok(Ok(Filtered {
        report,
        sample_rows,
        result_rows,
        latest,
        transitions,
        stored_groups,
    }))
}

/// Where stored samples are read from: a transaction (its own writes included), or the
/// write connection outside one (what is committed, while nothing is in flight).
pub(super) enum SampleSource<'a, 'c> {
    Tx(&'a mut WriteTx<'c>),
    Committed(&'a mut WriteConn),
    /// What is committed, through the store's read side (while a commit is in flight).
    Reader(&'a Store),
    /// No store: the job holds every sample its stored groups need
    /// ([`completes_within_job`]), so none is read.
    JobAlone,
}

impl SampleSource<'_, '_> {
    /// The stored samples of `link` with times in `[from_ns, to_ns]`, with their values.
    pub(super) async fn samples(
        &mut self,
        link: LinkId,
        from_ns: i64,
        to_ns: i64,
    ) -> Result<Vec<(i64, SampleValues)>, StoreError> {
        match self {
            Self::Tx(tx) => tx.existing_samples(link, from_ns, to_ns).await,
            Self::Committed(write) => write.stored_samples(link, from_ns, to_ns).await,
            Self::Reader(store) => store.sample_values(link, from_ns, to_ns).await,
            Self::JobAlone => Err(StoreError::Defect(format!(
                "a group completed from its job alone needed a stored sample of link {}",
                link.0
            ))),
        }
    }
}

/// Completes the groups of a job's backfilled samples: the other links' samples of the same
/// instant (within the group tolerance) come from this job or the store (earlier jobs of this
/// transaction included). A group completes once, when its last sample arrives: from this
/// job's latest sample of it (ties: the highest link id), at its earliest sample's time.
pub(super) async fn complete_stored_groups(
    tx: &mut SampleSource<'_, '_>,
    bank: &FilterBank,
    targets: &[TargetView],
    f: &mut Filtered,
) -> Result<(), StoreError> {
    let tolerance = bank.group_tolerance_ns();
    let stored_groups = &f.stored_groups;
    let report = &mut f.report;
    let result_rows = &mut f.result_rows;
    for &(link, time_ns, z) in stored_groups {
        let mut group: HashMap<LinkId, (i64, crate::geometry::PoseCov)> = HashMap::new();
        group.insert(link, (time_ns, z));
        let mut latest_of_job = (time_ns, link);
        for (l, spec) in bank.model().links.iter().enumerate() {
            let l = LinkId(l);
            if l == link || !matches!(spec.kind, crate::model::LinkKind::Measured(_)) {
                continue;
            }
            // This job's sample of that instant, else the store's: the nearest in time.
            let in_job = job_sample_near(stored_groups, l, time_ns, tolerance);
            if let Some((t, _)) = in_job {
                latest_of_job = latest_of_job.max((t, l));
            }
            let found = match in_job {
                Some(found) => Some(found),
                None => tx
                    .samples(l, time_ns - tolerance, time_ns + tolerance)
                    .await?
                    .into_iter()
                    .min_by_key(|(t, _)| (t - time_ns).unsigned_abs())
                    .and_then(|(t, v)| {
                        let sample = crate::bank::Sample {
                            link: l,
                            time_ns: t,
                            parent_from_child: v.pose,
                            uncertainty: v.uncertainty,
                        };
                        bank.measurement(&sample).ok().map(|z| (t, z))
                    }),
            };
            if let Some(found) = found {
                group.insert(l, found);
            }
        }
        if latest_of_job != (time_ns, link) {
            continue;
        }
        let Some(group_ns) = group.values().map(|(t, _)| *t).min() else {
            continue;
        };
        for raw in bank.raw_results_of_group(link, group_ns, &group) {
            report.raw_results += 1;
            let deformation = deformation_of(targets, raw.target, &raw.target_from_base);
            result_rows.insert(
                (raw.target, ResultSource::Raw, raw.time_ns),
                raw_row(&raw, deformation),
            );
        }
    }
    Ok(())
}

/// The job's sample of `link` nearest to `time_ns` within `tolerance`, among its samples
/// whose groups are older than memory.
fn job_sample_near(
    stored_groups: &[(LinkId, i64, crate::geometry::PoseCov)],
    link: LinkId,
    time_ns: i64,
    tolerance: i64,
) -> Option<(i64, crate::geometry::PoseCov)> {
    stored_groups
        .iter()
        .filter(|(other, t, _)| *other == link && (t - time_ns).abs() <= tolerance)
        .min_by_key(|(_, t, _)| (t - time_ns).unsigned_abs())
        .map(|&(_, t, z)| (t, z))
}

/// Whether [`complete_stored_groups`] completes every group of the job's samples older than
/// memory from the job itself (true when it has none): each holds a sample of every other
/// measured link at that instant (a late batch of whole groups), so that nothing stored is
/// read, and the job can be filtered ahead like any other.
pub(super) fn completes_within_job(bank: &FilterBank, f: &Filtered) -> bool {
    let tolerance = bank.group_tolerance_ns();
    f.stored_groups.iter().all(|&(link, time_ns, _)| {
        bank.model()
            .links
            .iter()
            .enumerate()
            .filter(|(l, spec)| {
                *l != link.0 && matches!(spec.kind, crate::model::LinkKind::Measured(_))
            })
            .all(|(l, _)| {
                job_sample_near(&f.stored_groups, LinkId(l), time_ns, tolerance).is_some()
            })
    })
}

impl Filtered {
    /// The job's report and rows: a result that is not finite is left out (its target's
    /// problem, never a storage failure of all), and each target's newest result becomes its
    /// latest.
    pub(super) fn into_rows(
        self,
        bank: &FilterBank,
        targets: &mut [TargetView],
    ) -> (IngestReport, JobRows) {
        let Filtered {
            mut report,
            sample_rows,
            result_rows,
            mut latest,
            transitions,
            ..
        } = self;
        let mut rows: Vec<NewResult> = Vec::with_capacity(result_rows.len());
        for row in result_rows.into_values() {
            match row.non_finite() {
                None => rows.push(row),
                Some(what) => {
                    let name = &bank.model().targets[row.target.0].name;
                    if !report.unusable.iter().any(|(n, _)| n == name) {
                        tracing::error!(
                            target = %name,
                            what,
                            "a result of this target is not a finite number and is not stored: \
                             its filter tuning, sigmas or calibrations give numbers out of range"
                        );
                        report.unusable.push((name.clone(), what));
                    }
                    latest.remove(&row.target);
                    match row.source {
                        ResultSource::Raw => {
                            report.raw_results = report.raw_results.saturating_sub(1)
                        }
                        ResultSource::Filtered => {
                            report.filtered_results = report.filtered_results.saturating_sub(1)
                        }
                    }
                }
            }
        }
        for (t, est) in latest {
            targets[t.0].latest = Some(est);
        }
        (
            report,
            JobRows {
                samples: sample_rows,
                results: rows,
                transitions,
            },
        )
    }
}

/// Writes jobs' rows in the transaction, every job's samples in one call and results in one
/// (so that the rollups are read and written once); returns their alarm transitions with
/// their ids, in the jobs' order.
pub(super) async fn write_rows(
    tx: &mut WriteTx<'_>,
    rows: &[JobRows],
    now: i64,
) -> Result<Vec<StoredAlarm>, StoreError> {
    let samples: Vec<&[NewSample]> = rows.iter().map(|r| r.samples.as_slice()).collect();
    tx.insert_samples(&samples).await?;
    let results: Vec<&[NewResult]> = rows.iter().map(|r| r.results.as_slice()).collect();
    tx.insert_results(&results).await?;
    let mut alarms = Vec::new();
    for r in rows {
        alarms.extend(store_alarms(tx, &r.transitions, now).await?);
    }
    Ok(alarms)
}
