//! The pipeline task: the one writer. See the module docs of [`crate::service`].

use super::job::{self, Job};
use super::{
    ItemProblem, Pruned, ReferenceRequest, ServiceError, ServiceResult, Snapshot, TargetView,
};
use crate::bank::{BankRecord, FilterBank, ResultSource, Sample, TargetEstimate};
use crate::chain::LinkId;
use crate::deformation::ReferenceVersion;
use crate::deformation::{Deformation, MeasuredPose, Reference};
use crate::filter::Disposition;
use crate::model::TargetId;
use crate::store::WriteTx;
use crate::store::outbox::KeepUnsent;
use crate::store::{
    NewResult, NewSample, Quality, SampleValues, StoreError, StoredAlarm, WriteConn,
};
use crate::viz::Series;
use std::collections::{BTreeMap, HashMap};
use tokio::sync::mpsc;

/// At most this many queued jobs share one commit (bounds the latency of the first).
const MAX_JOBS_PER_COMMIT: usize = 256;

/// One validated sample of an ingest request.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IngestItem {
    /// Its index in the request.
    pub index: usize,
    /// The sample.
    pub sample: Sample,
    /// Pose-estimation quality, as given.
    pub quality: Quality,
}

/// What an ingest request did.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct IngestReport {
    /// Samples in the request: all now durably stored.
    pub accepted: usize,
    /// Of those, newly stored.
    pub stored: usize,
    /// Of those, identical to samples already stored (retries).
    pub duplicates: usize,
    /// New samples flagged as outliers.
    pub outliers: usize,
    /// New samples older than their link's filter (stored, not fused).
    pub out_of_order: usize,
    /// Filter restarts after a run of consistent outliers.
    pub reinitialized: usize,
    /// Raw results completed.
    pub raw_results: usize,
    /// Filtered results produced.
    pub filtered_results: usize,
    /// Targets some of whose results were not finite numbers, with what was not: those
    /// results were not stored (the target's configuration gives numbers out of range); the
    /// samples and every other target's results were.
    pub unusable: Vec<(String, &'static str)>,
}

pub(super) struct Pipeline {
    /// The write connection; with the commit in flight while one is (see [`InFlight`]).
    write: Option<WriteConn>,
    /// The commit whose rows are being written while the next group is filtered.
    in_flight: Option<InFlight>,
    /// Per link: at least the newest time of any sample stored or on its way to the store
    /// (every ingest job's samples count, whatever became of them). A job whose samples are
    /// all newer cannot repeat or contradict a stored one, so it needs no read of the store.
    newest_sample_ns: Vec<Option<i64>>,
    /// A job taken from the queue while a group was filtered ahead that could not join it:
    /// the first of the next group.
    held: Option<Job>,
    bank: FilterBank,
    targets: Vec<TargetView>,
    digest: String,
    committed_state: BankRecord,
    metrics: std::sync::Arc<super::Metrics>,
    events: tokio::sync::broadcast::Sender<super::LiveEvent>,
    /// Per target: the measurement time of the last result sent live.
    last_event_ns: Vec<Option<i64>>,
    /// What goes to Rerun (never waits).
    viz: crate::viz::VizSender,
    /// The server's clock: receipt stamps, retention, liveness.
    clock: crate::clock::SharedClock,
    /// Stored alarm transitions for the notifier (never waits).
    alarm_feed: Option<mpsc::Sender<StoredAlarm>>,
    /// `[server] events_max_hz`: most live results per target and second of measurement time.
    events_max_hz: f64,
    /// `[server] clock_tolerance_s`: skew allowed when judging staleness (s).
    clock_tolerance_s: f64,
}

/// What a commit group's jobs changed besides their answers, acted on after the commit (or
/// undone when it fails).
#[derive(Default)]
struct Effects {
    /// Alarm transitions stored, for the notifier and live events.
    transitions: Vec<StoredAlarm>,
    /// What goes to the visualisation.
    viz_records: Vec<crate::viz::Record>,
    /// Calibrations added to the bank, removed again if the commit fails.
    added_calibrations: Vec<(LinkId, i64)>,
}

/// What a job may touch inside the transaction.
struct Step<'a, 'c> {
    tx: &'a mut WriteTx<'c>,
    bank: &'a mut FilterBank,
    targets: &'a mut [TargetView],
    /// The visualisation, when it records.
    viz: Option<&'a mut crate::viz::VizSender>,
    now: i64,
    /// `[server] clock_tolerance_s`.
    clock_tolerance_s: f64,
    effects: &'a mut Effects,
}

/// Does one job in the transaction, setting its answer. An `Err` fails the whole transaction.
async fn apply(job: &mut Job, step: &mut Step<'_, '_>) -> Result<(), StoreError> {
    match job {
        Job::Ingest(call) => {
            call.answer = apply_ingest(step, std::mem::take(&mut call.request)).await?;
        }
        Job::SetReference(call) => call.answer = apply_reference(step, &call.request).await?,
        Job::Prune(call) => call.answer = Ok(apply_prune(step, &call.request).await?),
        Job::RecordAck(call) => {
            let r = &call.request;
            step.tx.record_ack(r.tier, r.seq, step.now).await?;
            call.answer = Ok(());
        }
        Job::AddCalibration(call) => call.answer = apply_calibration(step, &call.request).await?,
        Job::ResetLink(call) => call.answer = apply_reset(step, &call.request).await?,
        Job::RecordAcceptance(call) => {
            let id = step
                .tx
                .insert_acceptance(&call.request.row(), step.now)
                .await?;
            call.answer = Ok((id, step.now));
        }
        Job::CheckLiveness(call) => {
            let raised = judge_liveness(step.bank, step.targets, step.now, step.clock_tolerance_s);
            let t = store_alarms(step.tx, &raised, step.now).await?;
            call.answer = Ok(t.len());
            step.effects.transitions.extend(t);
        }
        Job::AcknowledgeAlarm(call) => call.answer = apply_acknowledge(step, &call.request).await?,
    }
    Ok(())
}

async fn apply_ingest(
    step: &mut Step<'_, '_>,
    items: Vec<IngestItem>,
) -> Result<ServiceResult<IngestReport>, StoreError> {
    let mut t = Vec::new();
    let collect = step.viz.as_deref_mut().map(|sender| VizCollect {
        sender,
        records: &mut step.effects.viz_records,
    });
    let answer = ingest(
        step.tx,
        step.bank,
        step.targets,
        items,
        step.now,
        &mut t,
        collect,
    )
    .await?;
    step.effects.transitions.extend(t);
    Ok(answer)
}

async fn apply_reference(
    step: &mut Step<'_, '_>,
    r: &job::SetReference,
) -> Result<ServiceResult<ReferenceVersion>, StoreError> {
    let answer = set_reference(step.tx, step.targets, r.target, r.request, step.now).await?;
    if step.viz.is_some()
        && let Ok(current) = &answer
    {
        step.effects
            .viz_records
            .push(crate::viz::Record::Reference {
                target: r.target,
                time_ns: step.targets[r.target.0]
                    .latest
                    .as_ref()
                    .map_or(step.now, |l| l.time_ns),
                g0_from_b: current.reference.g0_from_b.whole.pose,
            });
    }
    Ok(answer)
}

/// One pass of retention: the ages, then the disk budget; a site keeps what the centre has
/// not acknowledged (unless the budget forces otherwise).
async fn apply_prune(step: &mut Step<'_, '_>, r: &job::Prune) -> Result<Pruned, StoreError> {
    let keep = match r.upstream_raw {
        None => KeepUnsent::default(),
        Some(raw) => KeepUnsent::from_acks(&step.tx.upstream_acks().await?, raw),
    };
    let newest = step
        .targets
        .iter()
        .filter_map(|t| t.latest.as_ref().map(|l| l.time_ns))
        .max();
    let (samples, results) = match r.retention.cutoffs_ns(newest, step.now) {
        Some((samples_before, results_before)) => {
            step.tx.prune(samples_before, results_before, keep).await?
        }
        None => (0, 0),
    };
    let budget = match r.retention.disk_budget_bytes {
        Some(b) => Some(step.tx.shrink_to_budget(b, keep).await?),
        None => None,
    };
    Ok(Pruned {
        samples,
        results,
        budget,
    })
}

async fn apply_calibration(
    step: &mut Step<'_, '_>,
    r: &job::AddCalibration,
) -> Result<ServiceResult<i64>, StoreError> {
    let version = step
        .tx
        .insert_calibration(r.link, r.valid_from_ns, &r.parent_from_child, step.now)
        .await?;
    Ok(
        if step
            .bank
            .add_calibration(r.link, r.valid_from_ns, r.parent_from_child)
        {
            step.effects
                .added_calibrations
                .push((r.link, r.valid_from_ns));
            Ok(version)
        } else {
            Err(ServiceError::Invalid {
                message: "only calibrated links take calibrations".into(),
                problems: Vec::new(),
            })
        },
    )
}

async fn apply_reset(
    step: &mut Step<'_, '_>,
    r: &job::ResetLink,
) -> Result<ServiceResult<i64>, StoreError> {
    if !step.bank.reset_link(r.link) {
        return Ok(Err(ServiceError::Invalid {
            message: "only measured links have a filter to reset".into(),
            problems: Vec::new(),
        }));
    }
    step.tx
        .insert_link_reset(r.link, r.by.as_deref(), r.note.as_deref(), step.now)
        .await?;
    Ok(Ok(step.now))
}

async fn apply_acknowledge(
    step: &mut Step<'_, '_>,
    r: &job::AcknowledgeAlarm,
) -> Result<ServiceResult<()>, StoreError> {
    use crate::alarms::{AckRefusal, Acknowledging, Level, acknowledging};
    let id = r.id;
    let Some((to, prev_by, prev_note)) = step.tx.alarm_ack_state(id).await? else {
        return Ok(Err(ServiceError::NotFound(format!("no alarm {id}"))));
    };
    let Some(to) = Level::parse(&to) else {
        // A damaged row refuses this request alone, not the group's transaction.
        return Ok(Err(ServiceError::Storage(StoreError::Malformed(format!(
            "alarm {id} has the unknown level `{to}`"
        )))));
    };
    let previous = prev_by.as_deref().map(|b| (b, prev_note.as_deref()));
    Ok(
        match acknowledging(to, previous, &r.by, r.note.as_deref()) {
            Ok(Acknowledging::AlreadyRecorded) => Ok(()),
            Ok(Acknowledging::Record) => {
                step.tx
                    .acknowledge_alarm(id, &r.by, r.note.as_deref(), step.now)
                    .await?;
                Ok(())
            }
            Err(AckRefusal::ReturnToNone) => Err(ServiceError::Invalid {
                message: format!(
                    "alarm {id} is a return to `none`: there is nothing to acknowledge"
                ),
                problems: vec![ItemProblem {
                    index: None,
                    field: Some("id".into()),
                    message: "a transition back to `none`".into(),
                }],
            }),
            Err(AckRefusal::AlreadyAcknowledged { by }) => Err(ServiceError::Conflict {
                message: format!("alarm {id} was already acknowledged by `{by}`"),
                problems: Vec::new(),
            }),
        },
    )
}

/// Where the pipeline's work goes besides the database, and the clock it reads.
pub(super) struct Outlets {
    pub metrics: std::sync::Arc<super::Metrics>,
    pub events: tokio::sync::broadcast::Sender<super::LiveEvent>,
    pub viz: crate::viz::VizSender,
    pub clock: crate::clock::SharedClock,
    pub alarm_feed: Option<mpsc::Sender<StoredAlarm>>,
    /// `[server] events_max_hz`.
    pub events_max_hz: f64,
    /// `[server] clock_tolerance_s`.
    pub clock_tolerance_s: f64,
}

impl Pipeline {
    /// `newest_sample_ns`: per link, the time of its newest stored sample.
    pub(super) fn new(
        write: WriteConn,
        bank: FilterBank,
        targets: Vec<TargetView>,
        digest: String,
        newest_sample_ns: Vec<Option<i64>>,
        outlets: Outlets,
    ) -> Self {
        let Outlets {
            metrics,
            events,
            viz,
            clock,
            alarm_feed,
            events_max_hz,
            clock_tolerance_s,
        } = outlets;
        let committed_state = bank.record();
        let last_event_ns = vec![None; targets.len()];
        Self {
            alarm_feed,
            clock,
            viz,
            events,
            last_event_ns,
            write: Some(write),
            in_flight: None,
            newest_sample_ns,
            held: None,
            bank,
            targets,
            digest,
            committed_state,
            metrics,
            events_max_hz,
            clock_tolerance_s,
        }
    }

    /// Sends each target's newest result in `targets` (a commit's snapshot) to live
    /// subscribers, at most `events_max_hz` per target in measurement time. Never waits: with
    /// no subscriber the send just fails.
    fn publish_events(&mut self, targets: &[TargetView]) {
        let min_interval_ns = (1e9 / self.events_max_hz) as i64;
        for (ti, view) in targets.iter().enumerate() {
            let ti = TargetId(ti);
            let Some(latest) = &view.latest else { continue };
            if self.last_event_ns[ti.0].is_some_and(|t| latest.time_ns < t + min_interval_ns) {
                continue;
            }
            self.last_event_ns[ti.0] = Some(latest.time_ns);
            let _ = self.events.send(super::LiveEvent::Result {
                target: ti,
                estimate: latest.clone(),
                reference: view.reference,
            });
        }
    }

    /// Hands a committed group's records to the visualisation, with the frames placed by the
    /// links' filtered poses at the newest result's time when a scene is due.
    fn publish_viz(&mut self, records: Vec<crate::viz::Record>) {
        if !self.viz.enabled() {
            return;
        }
        let newest = records
            .iter()
            .filter(|r| {
                matches!(
                    r,
                    crate::viz::Record::Result {
                        source: ResultSource::Filtered,
                        ..
                    }
                )
            })
            .map(crate::viz::Record::time_ns)
            .max();
        for r in records {
            self.viz.send_kept(r);
        }
        if let Some(t) = newest
            && self.viz.keep(Series::Scene, t)
        {
            let link_poses = (0..self.bank.model().links.len())
                .map(|l| {
                    self.bank
                        .link_estimate(LinkId(l), t)
                        .ok()
                        .flatten()
                        .map(|p| p.pose)
                })
                .collect();
            self.viz.send_kept(crate::viz::Record::Scene {
                time_ns: t,
                link_poses,
            });
        }
    }

    fn snapshot(&self) -> Snapshot {
        Snapshot {
            targets: self.targets.clone(),
            bank: self.bank.current_view(),
        }
    }

    /// The write connection. It is away only while a commit is in flight, and every caller
    /// settles that commit first.
    fn writer(&mut self) -> &mut WriteConn {
        let Some(write) = self.write.as_mut() else {
            unreachable!("the write connection is back whenever no commit is in flight")
        };
        write
    }

    /// Applies a group of jobs in one transaction and, after the commit, publishes the snapshot
    /// readers see (`publish`), then answers them.
    ///
    /// A group of ingest jobs whose samples are all newer than their links' stored ones is
    /// filtered while the commit before it is still being written ([`Self::filter_ahead`]).
    /// An ingest job that may repeat stored samples waits for that commit, has the stored
    /// samples over its span read, and is then written the same way
    /// ([`Self::filter_after_reading`]). Any other group waits for that commit and runs in a
    /// transaction of the pipeline's own.
    async fn commit_group(
        &mut self,
        mut jobs: Vec<Job>,
        rx: &mut mpsc::Receiver<Job>,
        publish: &impl Fn(Snapshot),
    ) {
        // A request that may repeat stored samples (a retry, a late batch) has its links'
        // stored samples read first, once the commit before it has landed; it is then filtered
        // and written as one filtered ahead is, and the requests after it go on meanwhile.
        let read_first: Vec<Job> = jobs.drain(..self.read_first_count(&jobs)).collect();
        for job in read_first {
            self.count_samples(std::slice::from_ref(&job));
            self.filter_after_reading(job, rx, publish).await;
        }
        if jobs.is_empty() {
            return;
        }
        let ahead = self.all_new_samples(&jobs);
        self.count_samples(&jobs);
        if ahead {
            self.filter_ahead(jobs, &HashMap::new(), rx, publish).await;
        } else {
            let Err(jobs) = self.answer_unchanged_liveness(jobs) else {
                return;
            };
            // A failure of the commit in flight was concluded there: the bank and targets
            // are back at the last committed state, on which this group now runs.
            let _ = self.settle(publish).await;
            let targets_before = self.targets.clone();
            self.commit_in_turn(Vec::new(), None, jobs, targets_before, publish)
                .await;
        }
    }

    /// Liveness checks alone write only when a stale alarm changes: judged first on a copy
    /// (while a commit may be in flight: a failure of it returns the targets to before it,
    /// and the next check judges again), and answered without a transaction when nothing
    /// changes, the usual case every second. Gives the jobs back when they need one.
    fn answer_unchanged_liveness(&mut self, mut jobs: Vec<Job>) -> Result<(), Vec<Job>> {
        if !jobs.iter().all(|j| matches!(j, Job::CheckLiveness(_))) {
            return Err(jobs);
        }
        let now = self.clock.now_ns();
        let mut probe = self.targets.clone();
        if !judge_liveness(&self.bank, &mut probe, now, self.clock_tolerance_s).is_empty() {
            return Err(jobs);
        }
        self.targets = probe;
        for job in &mut jobs {
            if let Job::CheckLiveness(call) = job {
                call.answer = Ok(0);
            }
        }
        for job in jobs {
            job.answer();
        }
        Ok(())
    }

    /// Counts the jobs' samples in each link's newest time.
    fn count_samples(&mut self, jobs: &[Job]) {
        for job in jobs {
            if let Job::Ingest(call) = job {
                raise_all(&mut self.newest_sample_ns, &call.request);
            }
        }
    }

    /// Whether the jobs can be filtered ahead: Rerun is off (its scenes read the bank after
    /// a commit), and every job is an ingest whose samples are all newer than anything of
    /// their links stored, in flight, or in an earlier job of the group, so that none can
    /// repeat or contradict a stored sample and nothing need be read from the store.
    fn all_new_samples(&self, jobs: &[Job]) -> bool {
        if self.viz.enabled() {
            return false;
        }
        let mut newest = self.newest_sample_ns.clone();
        for job in jobs {
            let Job::Ingest(call) = job else {
                return false;
            };
            if may_repeat(&newest, &call.request) {
                return false;
            }
            raise_all(&mut newest, &call.request);
        }
        true
    }

    /// How many of the group's first jobs are filtered one by one after a read of the stored
    /// samples, rather than inside a transaction of their own: with Rerun off, the ingest
    /// jobs up to the last that may repeat stored samples (one not newer than everything of
    /// its links before it) or is not an ingest, so that the jobs after them are all new.
    /// One pass over the group.
    fn read_first_count(&self, jobs: &[Job]) -> usize {
        if self.viz.enabled() {
            return 0;
        }
        let mut newest = self.newest_sample_ns.clone();
        let mut through_last_not_new = 0;
        for (i, job) in jobs.iter().enumerate() {
            let Job::Ingest(call) = job else {
                through_last_not_new = i + 1;
                continue;
            };
            if may_repeat(&newest, &call.request) {
                through_last_not_new = i + 1;
            }
            raise_all(&mut newest, &call.request);
        }
        let ingest_first = jobs
            .iter()
            .take_while(|j| matches!(j, Job::Ingest(_)))
            .count();
        through_last_not_new.min(ingest_first)
    }

    /// Filters one ingest request after reading the stored samples of its links over its
    /// span (once the commit before it has landed, so that what is read is all there is),
    /// then sends its rows to be written while the next requests are filtered. When the read
    /// fails, the request goes through a transaction of its own, which meets the same
    /// failure and answers it.
    async fn filter_after_reading(
        &mut self,
        job: Job,
        rx: &mut mpsc::Receiver<Job>,
        publish: &impl Fn(Snapshot),
    ) {
        // A failure of the commit in flight was concluded there: the bank and targets are
        // back at the last committed state, on which this request now runs.
        let _ = self.settle(publish).await;
        let Job::Ingest(call) = &job else {
            unreachable!("only ingest requests are read for first")
        };
        let Some(write) = self.write.as_mut() else {
            unreachable!("the write connection is back once the commit before has settled")
        };
        match stored_over_spans(&mut SampleSource::Committed(write), &call.request).await {
            Ok(stored) => self.filter_ahead(vec![job], &stored, rx, publish).await,
            Err(e) => {
                tracing::warn!(error = %e, "reading the stored samples before filtering");
                let targets_before = self.targets.clone();
                self.commit_in_turn(Vec::new(), None, vec![job], targets_before, publish)
                    .await;
            }
        }
    }

    /// Filters a group of new samples while the commit before it is written, taking into it
    /// the requests of new samples that arrive until that commit lands, then sends this
    /// group's rows to be written in turn. When that commit fails,
    /// the bank and the targets return to its state before it and this group is refused too
    /// (nothing of it was written). A job whose samples complete groups older than memory
    /// needs the store: the group then goes on in the pipeline's own transaction once the
    /// commit before it has landed.
    async fn filter_ahead(
        &mut self,
        jobs: Vec<Job>,
        stored: &HashMap<(LinkId, i64), SampleValues>,
        rx: &mut mpsc::Receiver<Job>,
        publish: &impl Fn(Snapshot),
    ) {
        let started = std::time::Instant::now();
        if self.in_flight.is_some() {
            self.metrics
                .groups_filtered_ahead
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
        let now = self.clock.now_ns();
        let targets_before = self.targets.clone();
        let mut filtered: Vec<(Job, JobRows)> = Vec::with_capacity(jobs.len());
        let mut stop = Ahead::Next;
        let mut rest = jobs.into_iter();
        for job in rest.by_ref() {
            stop = self.filter_job_ahead(job, now, stored, &mut filtered);
            if !matches!(stop, Ahead::Next) {
                break;
            }
        }
        let rest: Vec<Job> = rest.collect();
        // While the commit before is written, later requests of new samples join this group
        // (one commit, one `fsync`, for as many requests as waited), until it lands.
        let mut landed: Option<Result<(), String>> = None;
        while matches!(stop, Ahead::Next) && filtered.len() < MAX_JOBS_PER_COMMIT {
            let Some(flight) = self.in_flight.as_mut() else {
                break;
            };
            let job = tokio::select! {
                biased;
                joined = &mut flight.handle => {
                    landed = Some(self.land(joined, publish));
                    break;
                }
                job = rx.recv() => job,
            };
            let Some(job) = job else { break };
            if !self.all_new_samples(std::slice::from_ref(&job)) {
                self.held = Some(job);
                break;
            }
            self.count_samples(std::slice::from_ref(&job));
            stop = self.filter_job_ahead(job, now, &HashMap::new(), &mut filtered);
        }
        let settled = match landed {
            Some(result) => result,
            None => self.settle(publish).await,
        };
        if let Err(message) = settled {
            let needs_store = match stop {
                Ahead::NeedsStore(pending) => Some(pending.0),
                _ => None,
            };
            // The failure returned the bank and the targets to before that commit, which
            // undid these jobs too.
            let jobs = filtered.into_iter().map(|(j, _)| j);
            for job in jobs.chain(needs_store).chain(rest) {
                job.fail(&message);
            }
            return;
        }
        match stop {
            Ahead::Next => {}
            Ahead::Defect(e) => {
                let jobs = filtered.into_iter().map(|(j, _)| j).chain(rest).collect();
                self.refuse_group(jobs, targets_before, e, publish);
                return;
            }
            // Alone in its group, with nothing in flight: the stored samples it needs are
            // all committed, and are read before its rows go to be written like any other.
            Ahead::NeedsStore(pending) if filtered.is_empty() && rest.is_empty() => {
                let (mut job, mut f) = *pending;
                let Some(write) = self.write.as_mut() else {
                    unreachable!("the write connection is back once the commit before has settled")
                };
                let read = complete_stored_groups(
                    &mut SampleSource::Committed(write),
                    &self.bank,
                    &self.targets,
                    &mut f,
                )
                .await;
                if let Err(e) = read {
                    self.refuse_group(vec![job], targets_before, e, publish);
                    return;
                }
                let (report, rows) = f.into_rows(&self.bank, &mut self.targets);
                if let Job::Ingest(call) = &mut job {
                    call.answer = Ok(report);
                }
                filtered.push((job, rows));
            }
            Ahead::NeedsStore(pending) => {
                self.commit_in_turn(filtered, Some(*pending), rest, targets_before, publish)
                    .await;
                return;
            }
        }
        let record = self.bank.record();
        let state_json = match serde_json::to_string(&record) {
            Ok(json) => json,
            Err(e) => {
                let jobs = filtered.into_iter().map(|(j, _)| j).collect();
                let e = StoreError::Defect(format!("cannot encode the filter state: {e}"));
                self.refuse_group(jobs, targets_before, e, publish);
                return;
            }
        };
        let snapshot = self.snapshot();
        let (jobs, rows): (Vec<Job>, Vec<JobRows>) = filtered.into_iter().unzip();
        let Some(write) = self.write.take() else {
            unreachable!("the write connection is back once the commit before has settled")
        };
        let handle = tokio::spawn(write_in_flight(
            write,
            rows,
            self.digest.clone(),
            state_json,
            now,
        ));
        self.in_flight = Some(InFlight {
            handle,
            done: Done {
                jobs,
                effects: Effects::default(),
                record,
                snapshot,
                targets_before,
                started,
            },
        });
        // A task spawned from this one waits in this worker's next slot until this one
        // yields, and the filtering of the next group does not: let the commit start now.
        tokio::task::yield_now().await;
    }

    /// Waits for the commit in flight, if any, and concludes it (answers, or rolls back). An
    /// error says it failed, with the message its requests were refused with.
    async fn settle(&mut self, publish: &impl Fn(Snapshot)) -> Result<(), String> {
        let Some(flight) = self.in_flight.as_mut() else {
            return Ok(());
        };
        let joined = (&mut flight.handle).await;
        self.land(joined, publish)
    }

    /// Concludes the commit in flight with what its task returned. A panic in the task goes on
    /// here, as it would have in the pipeline's own task.
    fn land(
        &mut self,
        joined: Result<InFlightOutcome, tokio::task::JoinError>,
        publish: &impl Fn(Snapshot),
    ) -> Result<(), String> {
        let Some(flight) = self.in_flight.take() else {
            return Ok(());
        };
        let (write, outcome) = match joined {
            Ok(landed) => landed,
            Err(e) if e.is_panic() => std::panic::resume_unwind(e.into_panic()),
            Err(e) => panic!("the commit in flight was cancelled: {e}"),
        };
        self.write = Some(write);
        let failure = outcome.as_ref().err().map(ToString::to_string);
        self.conclude(flight.done, outcome, publish);
        match failure {
            None => Ok(()),
            Some(e) => Err(format!(
                "the database did not accept an earlier write, so this request was not applied: {e}"
            )),
        }
    }

    /// Refuses a group filtered ahead that failed before its transaction began (`error`, a
    /// defect), once the commit before it has settled: what the group did to the bank and
    /// the targets is undone and its requests are refused.
    fn refuse_group(
        &mut self,
        jobs: Vec<Job>,
        targets_before: Vec<TargetView>,
        error: StoreError,
        publish: &impl Fn(Snapshot),
    ) {
        let done = Done {
            jobs,
            effects: Effects::default(),
            record: self.committed_state.clone(),
            snapshot: self.snapshot(),
            targets_before,
            started: std::time::Instant::now(),
        };
        self.conclude(done, Err(error), publish);
    }

    /// Filters one ingest job ahead into `filtered`, and says whether the group can go on.
    fn filter_job_ahead(
        &mut self,
        mut job: Job,
        now: i64,
        stored: &HashMap<(LinkId, i64), SampleValues>,
        filtered: &mut Vec<(Job, JobRows)>,
    ) -> Ahead {
        let Job::Ingest(call) = &mut job else {
            unreachable!("only ingest jobs are filtered ahead")
        };
        let items = std::mem::take(&mut call.request);
        let result = match measurements_of(&self.bank, &items) {
            Err(refusal) => Ok(Err(refusal)),
            Ok(z) => filter_items(
                &mut self.bank,
                &mut self.targets,
                items,
                z,
                stored,
                now,
                None,
            ),
        };
        match result {
            Err(e) => {
                filtered.push((job, JobRows::default()));
                Ahead::Defect(e)
            }
            Ok(Err(refusal)) => {
                call.answer = Err(refusal);
                filtered.push((job, JobRows::default()));
                Ahead::Next
            }
            Ok(Ok(f)) if f.stored_groups.is_empty() => {
                let (report, rows) = f.into_rows(&self.bank, &mut self.targets);
                call.answer = Ok(report);
                filtered.push((job, rows));
                Ahead::Next
            }
            Ok(Ok(f)) => Ahead::NeedsStore(Box::new((job, f))),
        }
    }

    /// Applies jobs in one transaction of the pipeline's own, with nothing in flight: first
    /// the rows of jobs already filtered ahead (`filtered`), then the one that needs the
    /// store to complete its groups (`needs_store`), then `rest` job by job; commits, then
    /// concludes.
    async fn commit_in_turn(
        &mut self,
        filtered: Vec<(Job, JobRows)>,
        needs_store: Option<(Job, Filtered)>,
        rest: Vec<Job>,
        targets_before: Vec<TargetView>,
        publish: &impl Fn(Snapshot),
    ) {
        let now = self.clock.now_ns();
        let started = std::time::Instant::now();
        let mut effects = Effects::default();
        // Every job stays in `jobs`, to be answered or refused whatever happens.
        let (mut jobs, rows): (Vec<Job>, Vec<JobRows>) = filtered.into_iter().unzip();
        let mut in_turn = rows.len();
        let needs_store = needs_store.map(|(job, f)| {
            jobs.push(job);
            in_turn += 1;
            f
        });
        jobs.extend(rest);
        let Pipeline {
            viz,
            write,
            bank,
            targets,
            digest,
            clock_tolerance_s,
            ..
        } = self;
        let Some(write) = write.as_mut() else {
            unreachable!("the write connection is back whenever no commit is in flight")
        };
        let outcome: Result<BankRecord, StoreError> = async {
            let mut tx = write.begin(now).await?;
            for r in &rows {
                effects
                    .transitions
                    .extend(write_rows(&mut tx, r, now).await?);
            }
            if let Some(mut f) = needs_store {
                complete_stored_groups(&mut SampleSource::Tx(&mut tx), bank, targets, &mut f)
                    .await?;
                let (report, r) = f.into_rows(bank, targets);
                effects
                    .transitions
                    .extend(write_rows(&mut tx, &r, now).await?);
                if let Some(Job::Ingest(call)) = jobs.get_mut(in_turn - 1) {
                    call.answer = Ok(report);
                }
            }
            let mut step = Step {
                tx: &mut tx,
                bank,
                targets,
                viz: viz.enabled().then_some(viz),
                now,
                clock_tolerance_s: *clock_tolerance_s,
                effects: &mut effects,
            };
            for job in &mut jobs[in_turn..] {
                apply(job, &mut step).await?;
            }
            let record = bank.record();
            let json = serde_json::to_string(&record)
                .map_err(|e| StoreError::Defect(format!("cannot encode the filter state: {e}")))?;
            tx.save_filter_state(digest, &json, now).await?;
            tx.commit().await?;
            Ok(record)
        }
        .await;
        let (record, outcome) = match outcome {
            Ok(record) => (record, Ok(Vec::new())),
            Err(e) => (self.committed_state.clone(), Err(e)),
        };
        let done = Done {
            jobs,
            effects,
            record,
            snapshot: self.snapshot(),
            targets_before,
            started,
        };
        self.conclude(done, outcome, publish);
    }

    /// Ends a group's commit. On success: the state it committed becomes the one a failure
    /// returns to, readers see its snapshot before its requests are answered, and its alarm
    /// transitions (`alarms`, with those it stored itself) go out. On failure: the bank
    /// returns to the last committed state, the targets to theirs before the group, and its
    /// requests are refused.
    fn conclude(
        &mut self,
        done: Done,
        outcome: Result<Vec<StoredAlarm>, StoreError>,
        publish: &impl Fn(Snapshot),
    ) {
        let Done {
            jobs,
            effects,
            record,
            snapshot,
            targets_before,
            started,
        } = done;
        let Effects {
            mut transitions,
            mut viz_records,
            added_calibrations,
        } = effects;
        match outcome {
            Ok(alarms) => {
                transitions.extend(alarms);
                self.writer().health().record_ok();
                self.committed_state = record;
                use std::sync::atomic::Ordering::Relaxed;
                let m = &self.metrics;
                m.commit(u64::try_from(started.elapsed().as_micros()).unwrap_or(u64::MAX));
                for job in &jobs {
                    if let Job::Ingest(call) = job
                        && let Ok(r) = &call.answer
                    {
                        m.ingest_requests.fetch_add(1, Relaxed);
                        m.samples_stored.fetch_add(r.stored as u64, Relaxed);
                        m.samples_duplicate.fetch_add(r.duplicates as u64, Relaxed);
                        m.samples_outlier.fetch_add(r.outliers as u64, Relaxed);
                        m.filter_restarts.fetch_add(r.reinitialized as u64, Relaxed);
                    }
                }
                // Readers see the commit before its requests are answered: a client that
                // reads right after its write gets what it wrote.
                let live = snapshot.targets.clone();
                publish(snapshot);
                for job in jobs {
                    job.answer();
                }
                self.publish_events(&live);
                for a in &transitions {
                    viz_records.push(crate::viz::Record::Alarm {
                        target: a.target,
                        transition: a.transition.clone(),
                    });
                }
                for a in transitions {
                    if let Some(feed) = &self.alarm_feed
                        && let Err(e) = feed.try_send(a.clone())
                    {
                        self.metrics
                            .alarm_feed_dropped
                            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        tracing::error!(alarm = a.id, error = %e, "an alarm transition cannot be queued for the webhooks; it will not be sent");
                    }
                    let _ = self.events.send(super::LiveEvent::Alarm(a));
                }
                self.publish_viz(viz_records);
            }
            Err(e) => {
                tracing::error!(error = %e, "a commit failed; its requests are refused and the filters roll back");
                self.writer().health().record_failure(&e);
                self.metrics
                    .commits_failed
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                for skipped in self.bank.rollback(&self.committed_state) {
                    tracing::warn!(%skipped, "rollback could not restore a filter");
                }
                for (link, valid_from) in added_calibrations {
                    self.bank.remove_calibration(link, valid_from);
                }
                self.targets = targets_before;
                let message = format!("the database did not accept the write: {e}");
                for job in jobs {
                    job.fail(&message);
                }
            }
        }
    }
}

/// A group's jobs and what concluding its commit needs.
struct Done {
    jobs: Vec<Job>,
    effects: Effects,
    /// The bank's state the commit saves.
    record: BankRecord,
    /// What readers see once it has committed.
    snapshot: Snapshot,
    /// The targets before the group, restored when it fails.
    targets_before: Vec<TargetView>,
    started: std::time::Instant,
}

/// What the task writing a commit gives back: the connection, and the alarm transitions it
/// stored or why it failed.
type InFlightOutcome = (WriteConn, Result<Vec<StoredAlarm>, StoreError>);

/// A commit being written by a task of its own while the pipeline filters the next group.
struct InFlight {
    handle: tokio::task::JoinHandle<InFlightOutcome>,
    done: Done,
}

/// Writes a group's rows and the filters' state in one transaction and commits, on the
/// connection it hands back.
async fn write_in_flight(
    mut write: WriteConn,
    rows: Vec<JobRows>,
    digest: String,
    state_json: String,
    now: i64,
) -> InFlightOutcome {
    let outcome = async {
        let mut tx = write.begin(now).await?;
        let mut alarms = Vec::new();
        for job in &rows {
            alarms.extend(write_rows(&mut tx, job, now).await?);
        }
        tx.save_filter_state(&digest, &state_json, now).await?;
        tx.commit().await?;
        Ok(alarms)
    }
    .await;
    (write, outcome)
}

/// Runs the pipeline until every sender is gone, then checkpoints and closes the write
/// connection. An error says the stop was not clean.
pub(super) async fn run(
    mut p: Pipeline,
    mut rx: mpsc::Receiver<Job>,
    publish: impl Fn(Snapshot),
) -> Result<(), String> {
    loop {
        // With a commit in flight, whichever comes first: the next job (filtered while the
        // commit is written), or the commit's end (concluded at once, so that its requests
        // are answered even when nothing else arrives).
        let next = match p.in_flight.as_mut() {
            _ if p.held.is_some() => p.held.take(),
            Some(flight) => tokio::select! {
                job = rx.recv() => job,
                landed = &mut flight.handle => {
                    // A failure was logged and its requests refused there.
                    let _ = p.land(landed, &publish);
                    continue;
                }
            },
            None => rx.recv().await,
        };
        let Some(first) = next else { break };
        let mut jobs = vec![first];
        while jobs.len() < MAX_JOBS_PER_COMMIT {
            match rx.try_recv() {
                Ok(j) => jobs.push(j),
                Err(_) => break,
            }
        }
        p.commit_group(jobs, &mut rx, &publish).await;
    }
    let _ = p.settle(&publish).await;
    let last = p.writer().health().problem();
    let Some(write) = p.write.take() else {
        unreachable!("the write connection is back once the last commit has settled")
    };
    if let Err(e) = write.close().await {
        tracing::error!(error = %e, "closing the database failed");
        return Err(format!("closing the database failed: {e}"));
    }
    match last {
        Some(problem) => Err(problem),
        None => Ok(()),
    }
}

/// Raises a newest time to `t` when `t` is newer.
fn raise_to(newest: &mut Option<i64>, t: i64) {
    *newest = Some(newest.map_or(t, |n| n.max(t)));
}

/// Whether a batch holds a sample not newer than its link's newest time (`newest`, by link):
/// one that may repeat or contradict a stored sample.
fn may_repeat(newest: &[Option<i64>], items: &[IngestItem]) -> bool {
    items
        .iter()
        .any(|item| newest[item.sample.link.0].is_some_and(|t| item.sample.time_ns <= t))
}

/// Raises each link's newest time (`newest`, by link) to a batch's samples.
fn raise_all(newest: &mut [Option<i64>], items: &[IngestItem]) {
    for item in items {
        raise_to(&mut newest[item.sample.link.0], item.sample.time_ns);
    }
}

/// Stores alarm transitions `(target, transition)`; returns them with their ids.
async fn store_alarms(
    tx: &mut WriteTx<'_>,
    raised: &[(TargetId, crate::alarms::Transition)],
    now: i64,
) -> Result<Vec<StoredAlarm>, StoreError> {
    let mut out = Vec::with_capacity(raised.len());
    for (target, transition) in raised {
        out.push(StoredAlarm {
            id: tx.insert_alarm(*target, transition, now).await?,
            target: *target,
            transition: transition.clone(),
            ack: None,
        });
    }
    Ok(out)
}

/// Steps every target's stale track at `now_ns` (the server's clock) with the link furthest
/// behind its staleness limit (plus `[server] clock_tolerance_s`); returns the transitions.
fn judge_liveness(
    bank: &FilterBank,
    targets: &mut [TargetView],
    now_ns: i64,
    tolerance_s: f64,
) -> Vec<(TargetId, crate::alarms::Transition)> {
    let model = bank.model();
    let mut out = Vec::new();
    for (ti, view) in targets.iter_mut().enumerate() {
        let ti = TargetId(ti);
        let Some((link, lag)) = bank.target_liveness(ti, now_ns, tolerance_s).worst else {
            continue;
        };
        if let Some(t) = view.alarms.liveness(
            now_ns,
            &model.links[link.0].name,
            lag.behind_s.max(0.0),
            lag.limit_s,
        ) {
            out.push((ti, t));
        }
    }
    out
}

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
struct VizCollect<'a> {
    sender: &'a mut crate::viz::VizSender,
    records: &'a mut Vec<crate::viz::Record>,
}

/// One ingest job in the transaction: conflict checks against the store, filtering, groups
/// completed from the store, rows. `Ok(Err(..))` refuses the job alone (no effect on the bank
/// or the transaction); `Err` aborts the whole transaction.
async fn ingest(
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
    let stored = stored_over_spans(&mut SampleSource::Tx(tx), &items).await?;
    let mut filtered = match filter_items(bank, targets, items, measurements, &stored, now, viz)? {
        Ok(f) => f,
        Err(refusal) => return Ok(Err(refusal)),
    };
    complete_stored_groups(&mut SampleSource::Tx(tx), bank, targets, &mut filtered).await?;
    let (report, rows) = filtered.into_rows(bank, targets);
    *new_transitions = write_rows(tx, &rows, now).await?;
    Ok(Ok(report))
}

/// The stored samples a batch may repeat: each link's over the batch's span of its times.
async fn stored_over_spans(
    source: &mut SampleSource<'_, '_>,
    items: &[IngestItem],
) -> Result<HashMap<(LinkId, i64), SampleValues>, StoreError> {
    let mut spans: HashMap<LinkId, (i64, i64)> = HashMap::new();
    for item in items {
        let e = spans
            .entry(item.sample.link)
            .or_insert((item.sample.time_ns, item.sample.time_ns));
        e.0 = e.0.min(item.sample.time_ns);
        e.1 = e.1.max(item.sample.time_ns);
    }
    let mut stored = HashMap::new();
    for (link, (from, to)) in spans {
        for (t, v) in source.samples(link, from, to).await? {
            stored.insert((link, t), v);
        }
    }
    Ok(stored)
}

/// Every item's measurement, checked before the bank sees any of them; the refusal names the
/// items whose uncertainties cannot be used.
fn measurements_of(
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
struct Filtered {
    report: IngestReport,
    sample_rows: Vec<NewSample>,
    result_rows: BTreeMap<(TargetId, ResultSource, i64), NewResult>,
    latest: HashMap<TargetId, TargetEstimate>,
    transitions: Vec<(TargetId, crate::alarms::Transition)>,
    /// Samples too old for the groups kept in memory (a backfill): their groups are
    /// completed from this job's samples and the store's ([`complete_stored_groups`]).
    stored_groups: Vec<(LinkId, i64, crate::geometry::PoseCov)>,
}

/// Whether a group filtered ahead can take its next job.
enum Ahead {
    /// Yes.
    Next,
    /// No: this job's samples complete groups older than memory, which needs the store.
    NeedsStore(Box<(Job, Filtered)>),
    /// No: a defect (the job is among those filtered).
    Defect(StoreError),
}

/// What one ingest job writes: its samples, its results and its alarm transitions (nothing,
/// by default: a refused job).
#[derive(Default)]
struct JobRows {
    samples: Vec<NewSample>,
    results: Vec<NewResult>,
    transitions: Vec<(TargetId, crate::alarms::Transition)>,
}

/// Sorts out retries and conflicts against `stored` (the stored samples over the job's
/// span), then feeds the new samples to the bank in time order. `Ok(Err(..))` refuses the
/// job before the bank sees any sample; `Err` is a defect.
fn filter_items(
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
            if let Some(v) = viz.as_mut()
                && v.sender.keep(Series::Raw(raw.target), raw.time_ns)
            {
                v.records.push(crate::viz::Record::Result {
                    target: raw.target,
                    time_ns: raw.time_ns,
                    source: ResultSource::Raw,
                    target_from_base: raw.target_from_base,
                    deformation: deformation.map(|(_, d)| d),
                });
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
            if let Some(v) = viz.as_mut()
                && v.sender.keep(Series::Filtered(est.target), est.time_ns)
            {
                v.records.push(crate::viz::Record::Result {
                    target: est.target,
                    time_ns: est.time_ns,
                    source: ResultSource::Filtered,
                    target_from_base: pose,
                    deformation: deformation.map(|(_, d)| d),
                });
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
enum SampleSource<'a, 'c> {
    Tx(&'a mut WriteTx<'c>),
    Committed(&'a mut WriteConn),
}

impl SampleSource<'_, '_> {
    /// The stored samples of `link` with times in `[from_ns, to_ns]`, with their values.
    async fn samples(
        &mut self,
        link: LinkId,
        from_ns: i64,
        to_ns: i64,
    ) -> Result<Vec<(i64, SampleValues)>, StoreError> {
        match self {
            Self::Tx(tx) => tx.existing_samples(link, from_ns, to_ns).await,
            Self::Committed(write) => write.stored_samples(link, from_ns, to_ns).await,
        }
    }
}

/// Completes the groups of a job's backfilled samples: the other links' samples of the same
/// instant (within the group tolerance) come from this job or the store (earlier jobs of this
/// transaction included). A group completes once, when its last sample arrives: from this
/// job's latest sample of it (ties: the highest link id), at its earliest sample's time.
async fn complete_stored_groups(
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
            let in_job = stored_groups
                .iter()
                .filter(|(other, t, _)| *other == l && (t - time_ns).abs() <= tolerance)
                .min_by_key(|(_, t, _)| (t - time_ns).unsigned_abs())
                .map(|&(_, t, z)| (t, z));
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

impl Filtered {
    /// The job's report and rows: a result that is not finite is left out (its target's
    /// problem, never a storage failure of all), and each target's newest result becomes its
    /// latest.
    fn into_rows(self, bank: &FilterBank, targets: &mut [TargetView]) -> (IngestReport, JobRows) {
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

/// Writes a job's rows in the transaction; returns its alarm transitions with their ids.
async fn write_rows(
    tx: &mut WriteTx<'_>,
    rows: &JobRows,
    now: i64,
) -> Result<Vec<StoredAlarm>, StoreError> {
    tx.insert_samples(&rows.samples).await?;
    tx.insert_results(&rows.results).await?;
    store_alarms(tx, &rows.transitions, now).await
}

async fn set_reference(
    tx: &mut WriteTx<'_>,
    targets: &mut [TargetView],
    target: TargetId,
    request: ReferenceRequest,
    now: i64,
) -> Result<ServiceResult<ReferenceVersion>, StoreError> {
    let reference = match request {
        ReferenceRequest::Explicit(pose) => Reference::explicit(pose),
        ReferenceRequest::Window { from_ns, to_ns } => {
            let rows = tx.filtered_poses(target, from_ns, to_ns).await?;
            let poses: Vec<_> = rows.iter().map(|r| r.estimate).collect();
            match Reference::from_window(&poses, from_ns, to_ns) {
                Ok(r) => r,
                Err(_) => {
                    return Ok(Err(ServiceError::Invalid {
                        message: "there are no filtered results in the window".into(),
                        problems: vec![ItemProblem {
                            index: None,
                            field: Some("from".into()),
                            message: "no filtered result lies between `from` and `to`".into(),
                        }],
                    }));
                }
            }
        }
    };
    let version = tx.insert_reference(target, &reference, now).await?;
    let current = ReferenceVersion {
        version,
        reference,
        created_ns: now,
    };
    targets[target.0].reference = Some(current);
    Ok(Ok(current))
}
