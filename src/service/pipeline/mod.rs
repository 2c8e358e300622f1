//! The pipeline task: the one writer (its jobs in a transaction in [`apply`], an ingest job's
//! filtering in [`filtering`], the group filtered while a commit is written in [`ahead`], the
//! cover of what is stored that spares a late request a read in [`spans`]). See
//! the module docs of [`crate::service`].

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
    NewResult, NewSample, Quality, SampleValues, Store, StoreError, StoredAlarm, WriteConn,
};
use crate::viz::Series;
use std::collections::{BTreeMap, HashMap};
use tokio::sync::mpsc;

mod ahead;
mod apply;
mod filtering;
mod spans;

use ahead::{Done, InFlight};
use apply::{Effects, Step, apply};
use filtering::{
    Ahead, Filtered, JobRows, SampleSource, VizCollect, complete_stored_groups,
    completes_within_job, filter_items, ingest, measurements_of, spans_of, stored_over_spans,
    write_rows,
};

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
    /// The store's read side: what is committed, read while a commit is in flight.
    read: Store,
    /// The commit whose rows are being written while the next group is filtered.
    in_flight: Option<InFlight>,
    /// Per link: intervals of time covering every sample stored or on its way to the store
    /// (every ingest job's samples count, whatever became of them). A job whose samples of
    /// each link lie in a gap of that link's cover cannot repeat or contradict a stored one,
    /// so it needs no read of the store.
    covered: spans::StoredSpans,
    /// Jobs taken from the queue but not yet filtered, in the order they came: those of a
    /// group taken at once behind its first request that must be read first, and one that
    /// could not join a group filtered ahead. They go before anything still on the queue, so
    /// that requests are filtered in the order they arrived.
    held: std::collections::VecDeque<Job>,
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
        read: Store,
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
            read,
            in_flight: None,
            covered: spans::StoredSpans::new(&newest_sample_ns),
            held: std::collections::VecDeque::new(),
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
    /// The group's leading ingest jobs whose samples are all new (none stored, in flight, or
    /// in an earlier job of the group over their spans) are filtered while the commit before
    /// them is still being written ([`Self::filter_ahead`]). An ingest job that may repeat
    /// stored samples has the stored samples over its span read first (the committed ones
    /// through the store's read side while that commit is written, with the commit's own from
    /// memory), and is then filtered and written the same way ([`Self::filter_after_reading`]).
    /// The jobs behind either are held, in their order, ahead of the queue: they join the
    /// group filtered behind it, or the next. A group that starts with any other job waits
    /// for that commit and runs in a transaction of the pipeline's own, as does every group
    /// while Rerun is on (its scenes read the bank after a commit).
    async fn commit_group(
        &mut self,
        mut jobs: Vec<Job>,
        rx: &mut mpsc::Receiver<Job>,
        publish: &impl Fn(Snapshot),
    ) {
        // Rerun's scenes read the bank after each commit: nothing is filtered ahead of one.
        let ahead = !self.viz.enabled();
        // How many of the group's first jobs are ingests of new samples only.
        let new = if ahead {
            self.first_not_new(&jobs).unwrap_or(jobs.len())
        } else {
            0
        };
        if new > 0 {
            self.hold(jobs.split_off(new));
            self.count_samples(&jobs);
            self.filter_ahead(jobs, &HashMap::new(), rx, publish).await;
        } else if ahead && matches!(jobs[0], Job::Ingest(_)) {
            // A request that may repeat stored samples (a retry, a late batch).
            self.hold(jobs.split_off(1));
            let Some(first) = jobs.pop() else {
                unreachable!("a group has a first job")
            };
            self.count_samples(std::slice::from_ref(&first));
            self.filter_after_reading(first, rx, publish).await;
        } else {
            self.count_samples(&jobs);
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

    /// Puts jobs taken from the queue but not filtered back ahead of it, in their order.
    fn hold(&mut self, jobs: Vec<Job>) {
        for job in jobs.into_iter().rev() {
            self.held.push_front(job);
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

    /// Covers the jobs' samples in each link's intervals.
    fn count_samples(&mut self, jobs: &[Job]) {
        for job in jobs {
            if let Job::Ingest(call) = job {
                self.covered.add_all(&call.request);
            }
        }
    }

    /// Whether the jobs can be filtered ahead: Rerun is off (its scenes read the bank after
    /// a commit), and every job is an ingest whose samples lie where their links hold
    /// nothing stored, in flight, or in an earlier job of the group, so that none can repeat
    /// or contradict a stored sample and nothing need be read from the store.
    fn all_new_samples(&self, jobs: &[Job]) -> bool {
        !self.viz.enabled() && self.first_not_new(jobs).is_none()
    }

    /// The first of the jobs that is not an ingest, or may repeat or contradict a sample
    /// stored, in flight, or of an earlier job of them (its samples of a link meet that
    /// link's cover). The cover is copied only for more than one job.
    fn first_not_new(&self, jobs: &[Job]) -> Option<usize> {
        let mut with_earlier: Option<spans::StoredSpans> = None;
        for (i, job) in jobs.iter().enumerate() {
            let Job::Ingest(call) = job else {
                return Some(i);
            };
            if with_earlier
                .as_ref()
                .unwrap_or(&self.covered)
                .may_repeat(&call.request)
            {
                return Some(i);
            }
            if i + 1 < jobs.len() {
                with_earlier
                    .get_or_insert_with(|| self.covered.clone())
                    .add_all(&call.request);
            }
        }
        None
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
            effects
                .transitions
                .extend(write_rows(&mut tx, &rows, now).await?);
            if let Some(mut f) = needs_store {
                complete_stored_groups(&mut SampleSource::Tx(&mut tx), bank, targets, &mut f)
                    .await?;
                let (report, r) = f.into_rows(bank, targets);
                effects
                    .transitions
                    .extend(write_rows(&mut tx, std::slice::from_ref(&r), now).await?);
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

/// Runs the pipeline until every sender is gone, then checkpoints and closes the write
/// connection. An error says the stop was not clean.
pub(super) async fn run(
    mut p: Pipeline,
    mut rx: mpsc::Receiver<Job>,
    publish: impl Fn(Snapshot),
) -> Result<(), String> {
    loop {
        // A job held (taken from the queue, not yet filtered) goes first. Otherwise, with a
        // commit in flight, whichever comes first: the next job (filtered while the
        // commit is written), or the commit's end (concluded at once, so that its requests
        // are answered even when nothing else arrives).
        let next = match p.in_flight.as_mut() {
            _ if !p.held.is_empty() => p.held.pop_front(),
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
        // With a commit in flight, the jobs after this one join its group one at a time,
        // each after a look at whether that commit has landed (`Pipeline::filter_ahead`), so
        // that the next commit starts as soon as the writer is free. With none, every job
        // waiting (held ones first) shares the next commit.
        while p.in_flight.is_none() && jobs.len() < MAX_JOBS_PER_COMMIT {
            let Some(job) = p.held.pop_front().or_else(|| rx.try_recv().ok()) else {
                break;
            };
            jobs.push(job);
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
