//! Orchestration: ingest -> filter -> store, references, calibrations, and what readers see.
//!
//! The only place that sequences IO. One pipeline task (`pipeline`) owns the database's write
//! connection and the filter bank. Requests reach it as jobs on a queue; it takes every job
//! waiting, applies them in order inside one transaction (conflict checks against the store,
//! filtering, results), persists the bank's state in the same transaction, commits, and only
//! then answers each job. Many requests therefore share one commit (group commit), and an
//! answer always means "on disk". If a commit fails, the bank is restored to the state of the
//! last commit and the jobs are answered with an error.
//!
//! While one commit's rows are written (by a task of its own, on the write connection it
//! takes along), the pipeline filters the next group when that group is ingest alone, takes
//! into that group the ingest requests that arrive until the commit lands (one `fsync` for
//! all that waited), then sends its own. The pipeline keeps, per link, a few intervals of
//! time that cover every sample stored or on its way (`pipeline::spans`). A request whose
//! samples of each link lie outside that link's intervals (new samples, or a late batch that
//! fills a gap) needs no read of the store. A late batch of whole groups older than the
//! filters' memory completes those groups from its own samples and is filtered ahead too;
//! one that needs other links' stored samples waits for the commit. A request that may
//! repeat stored samples (a retry, a late batch over stored times) is filtered once what is
//! stored before it is known: the committed
//! samples of its links over its span, read through the store's read side while the commit
//! is written, with the samples of the commit in flight and of the group's earlier requests
//! from memory. Only the pipeline writes samples, so that is all there is; when that read
//! fails, the request waits for the commit and is read on the write connection
//! (`pipeline::ahead`). Requests are filtered in the order they arrived: those taken from
//! the queue together behind one that must be read first are held, in order, ahead of the
//! queue, and join the next group before anything newer. An ingest job's checks, filtering
//! and rows are `pipeline::filtering`, the other jobs' work in a transaction
//! `pipeline::apply`. Readers and requesters never see
//! the bank run ahead: a commit's snapshot is the one taken when its group was filtered,
//! published once it has committed, and if it fails the group filtered behind it is refused
//! too.
//!
//! After each commit the pipeline publishes a [`Snapshot`] (latest filtered result, deformation
//! and reference per target, link counters, and a view of the filters for predictions), which
//! readers use without touching the pipeline.

mod acceptance;
mod compensation;
mod health;
mod job;
mod metrics;
use crate::deformation::ReferenceVersion;
use crate::model::TargetId;
use job::Job;
mod pipeline;
mod report;
mod tasks;

pub use acceptance::{
    AcceptanceOut, AcceptanceRecord, AcceptanceSummary, AcceptedTarget, PlannedStepOut, RunOut,
    StepOut, StillOut, WindowOut,
};
pub use compensation::{CompensationSource, Evaluated};
pub use metrics::{ConnectionCounters, Metrics, REJECTION_STATUSES};
pub use report::{
    LISTED_GAPS, REPORT_BUCKETS, ReportWindow, last_complete_period, report_file_name,
};
pub use tasks::TaskWatch;

pub use pipeline::{IngestItem, IngestReport};

use crate::bank::{FilterBank, TargetEstimate, TargetStatus};
use crate::config::Installation;
use crate::deformation::Deformation;
use crate::geometry::{Pose, PoseCov};
use crate::store::{self, Store, StoreError};
use std::sync::{Arc, RwLock};
use tokio::sync::{mpsc, oneshot};

/// A problem with one item of a request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ItemProblem {
    /// Index of the item in the request.
    pub index: Option<usize>,
    /// The field concerned (`time`, `pose.q_wxyz`, ...).
    pub field: Option<String>,
    /// What is wrong.
    pub message: String,
}

/// Errors of the service layer.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// The request is invalid; nothing was stored.
    #[error("{message}")]
    Invalid {
        /// Summary.
        message: String,
        /// The items concerned.
        problems: Vec<ItemProblem>,
    },
    /// The request conflicts with stored data; nothing was stored.
    #[error("{message}")]
    Conflict {
        /// Summary.
        message: String,
        /// The items concerned.
        problems: Vec<ItemProblem>,
    },
    /// Something asked for does not exist.
    #[error("{0}")]
    NotFound(String),
    /// The store failed; nothing of the request was stored.
    #[error(transparent)]
    Storage(#[from] StoreError),
    /// The transaction holding the request did not commit; nothing of it was stored.
    #[error("{0}")]
    CommitFailed(String),
    /// The writer stopped before it answered (a defect): the request's fate is unknown.
    #[error("the writer stopped before answering")]
    WriterStopped,
    /// The pipeline is not running (the service is shutting down).
    #[error("the service is shutting down")]
    ShuttingDown,
    /// The visualisation could not start.
    #[error(transparent)]
    Viz(#[from] crate::viz::VizError),
}

/// Result alias of the service.
pub type ServiceResult<T> = Result<T, ServiceError>;

/// What readers see of one target.
#[derive(Debug, Clone, PartialEq)]
pub struct TargetView {
    /// The newest filtered result.
    pub latest: Option<TargetEstimate>,
    /// The current reference.
    pub reference: Option<ReferenceVersion>,
    /// The alarm state, fed with every filtered result.
    pub alarms: crate::alarms::AlarmMonitor,
}

impl TargetView {
    /// The deformation of the newest result against the current reference.
    pub fn deformation(&self) -> Option<Deformation> {
        let estimate = self.latest.as_ref()?.target_from_base.as_ref()?;
        Some(Deformation::new(&self.reference?.reference, estimate))
    }
}

/// An event for live subscribers.
#[derive(Debug, Clone)]
#[allow(
    clippy::large_enum_variant,
    reason = "a few per second, cloned into each subscriber's slot; boxing buys nothing"
)]
pub enum LiveEvent {
    /// A new filtered result of a target (rate-limited per target).
    Result {
        /// Target index.
        target: TargetId,
        /// The result.
        estimate: TargetEstimate,
        /// The reference in force.
        reference: Option<ReferenceVersion>,
    },
    /// An alarm transition, as stored (with its id).
    Alarm(crate::store::StoredAlarm),
    /// An alarm transition acknowledged, with its acknowledgement.
    Acknowledged(crate::store::StoredAlarm),
}

/// How many stored alarm transitions may wait for the notifier (see
/// [`Service::take_alarm_feed`]) before new ones are dropped, counted.
pub const ALARM_FEED_CAPACITY: usize = 10_000;

/// How many events a live subscriber may fall behind before it is dropped.
pub const EVENT_BUFFER: usize = 256;

/// What readers see, as of the last commit.
#[derive(Debug, Clone)]
pub struct Snapshot {
    /// Per target (installation order).
    pub targets: Vec<TargetView>,
    /// The filters' current states, for predictions and link counters.
    pub bank: FilterBank,
}

/// A target as it stands at a time of the server's clock.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TargetNow {
    /// The newest result's status, or `stale` when a link on the target's paths has delivered
    /// nothing for longer than its limit; `initializing` before any result.
    pub status: TargetStatus,
    /// Seconds from the newest result's time to now (never negative); `None` before any
    /// result.
    pub age_s: Option<f64>,
    /// The link furthest behind its limit.
    pub liveness: crate::bank::TargetLiveness,
}

crate::words! {
    /// A link's state at a time of the server's clock.
    pub enum LinkState("link status") {
        /// A calibrated link: no samples to wait for.
        Calibrated = "calibrated",
        /// A measured link without a sample yet (or since a reset).
        NoData = "no_data",
        /// A measured link whose newest sample is older than its staleness limit on the server's
        /// clock (plus `[server] clock_tolerance_s`), or behind the newest link's sample by more
        /// than the limit in measurement time.
        Stale = "stale",
        /// A measured link that delivers.
        Ok = "ok",
    }
}

impl Snapshot {
    /// Target `ti` at `now_ns` on the server's clock, with `tolerance_s` of skew allowed: its
    /// newest result judged by [`Self::judge`].
    pub fn target_now(&self, ti: TargetId, now_ns: i64, tolerance_s: f64) -> TargetNow {
        let latest = self.targets.get(ti.0).and_then(|t| t.latest.as_ref());
        self.judge(ti, latest, now_ns, tolerance_s)
    }

    /// A live result of target `ti` judged at `now_ns` on the server's clock: `stale` when a
    /// link on the target's paths has delivered nothing for longer than its limit (plus
    /// `tolerance_s`), and its age from the result's time to now.
    pub fn judge(
        &self,
        ti: TargetId,
        result: Option<&TargetEstimate>,
        now_ns: i64,
        tolerance_s: f64,
    ) -> TargetNow {
        let liveness = self.bank.target_liveness(ti, now_ns, tolerance_s);
        let status = match result {
            None => TargetStatus::Initializing,
            Some(_) if liveness.stale => TargetStatus::Stale,
            Some(r) => r.status,
        };
        TargetNow {
            status,
            age_s: result.map(|r| ((now_ns - r.time_ns) as f64 / 1e9).max(0.0)),
            liveness,
        }
    }

    /// A link's state at `now_ns` on the server's clock, with `tolerance_s` of skew allowed.
    pub fn link_state(
        &self,
        link: crate::chain::LinkId,
        now_ns: i64,
        tolerance_s: f64,
    ) -> LinkState {
        let bank = &self.bank;
        if !matches!(
            bank.model().links[link.0].kind,
            crate::model::LinkKind::Measured(_)
        ) {
            return LinkState::Calibrated;
        }
        let by_clock = bank.link_lag_with(link, now_ns, tolerance_s);
        let behind_newest = bank.newest_sample_ns().and_then(|n| bank.link_lag(link, n));
        match (by_clock, behind_newest) {
            (None, _) => LinkState::NoData,
            (Some(c), l) if c.stale || l.is_some_and(|l| l.stale) => LinkState::Stale,
            _ => LinkState::Ok,
        }
    }
}

/// How a reference is set.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ReferenceRequest {
    /// An explicit `G0_from_B`.
    Explicit(Pose),
    /// The mean of the filtered results in `[from_ns, to_ns]`.
    Window {
        /// Start (ns).
        from_ns: i64,
        /// End (ns).
        to_ns: i64,
    },
}

struct Inner {
    installation: Arc<Installation>,
    store: Store,
    /// The queue's only sender: when the last handle is dropped the pipeline drains and stops.
    jobs: mpsc::Sender<Job>,
    /// Shared with the pipeline, which publishes into it (it must not hold `Inner`, or the
    /// queue would never close).
    snapshot: Arc<RwLock<Arc<Snapshot>>>,
    /// Counters, shared with the pipeline.
    metrics: Arc<Metrics>,
    /// Live events; sending never waits, a subscriber that lags is dropped.
    events: tokio::sync::broadcast::Sender<LiveEvent>,
    /// What went to Rerun.
    viz_counters: Arc<crate::viz::VizCounters>,
    /// Camera frames to Rerun (dropped with the last handle, like the job queue, so the logger
    /// can finish).
    frame_viz: crate::viz::FrameSender,
    /// Solves marker observations into link samples.
    observer: Arc<crate::model::Observer>,
    /// Turns true when shutdown begins: live event streams end on it.
    stopping: tokio::sync::watch::Sender<bool>,
    /// The server's clock.
    clock: crate::clock::SharedClock,
    /// Every stored alarm transition, in commit order, for the notifier (when webhooks are
    /// configured): taken once.
    alarm_feed: std::sync::Mutex<Option<mpsc::Receiver<crate::store::StoredAlarm>>>,
    /// Bounds the reads that stream over many rows (statistics, fine history), so that they
    /// cannot take every read connection.
    heavy_reads: Arc<tokio::sync::Semaphore>,
    /// The last removal the disk budget forced (see [`Service::storage_problem`]).
    storage_problem: std::sync::Mutex<Option<String>>,
    /// Why the last scheduled report could not be filed (see [`Service::report_problem`]).
    report_problem: std::sync::Mutex<Option<String>>,
    /// The background tasks, watched.
    tasks: TaskWatch,
    /// The acceptance run, while one is running or until the next starts.
    acceptance: tokio::sync::Mutex<Option<acceptance::Run>>,
}

/// What one pass of retention removed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Pruned {
    /// Samples older than their retention.
    pub samples: u64,
    /// Results older than theirs.
    pub results: u64,
    /// With a disk budget: what it made go beyond the ages (and the bytes in use).
    pub budget: Option<crate::store::BudgetCut>,
}

/// The running service: a handle that request handlers clone.
#[derive(Clone)]
pub struct Service {
    inner: Arc<Inner>,
}

/// The pipeline task, to await at shutdown (it finishes the jobs already queued), and the
/// Rerun logger behind it.
pub struct PipelineHandle(
    tokio::task::JoinHandle<Result<(), String>>,
    crate::viz::VizThread,
);

impl PipelineHandle {
    /// Waits until every queued job is committed and answered and the database is checkpointed
    /// and closed, then (for a bounded time) until the Rerun logger has written out what it was
    /// given and closed its recordings. An error says what kept the stop from being clean.
    pub async fn finished(self) -> Result<(), String> {
        let outcome = match self.0.await {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) => Err(e),
            Err(e) => {
                tracing::error!(error = %e, "the pipeline task panicked");
                Err(format!("the pipeline task panicked: {e}"))
            }
        };
        let viz = self.1;
        let finish =
            tokio::task::spawn_blocking(move || viz.finish(std::time::Duration::from_secs(10)));
        if let Err(e) = finish.await {
            tracing::error!(error = %e, "the Rerun logger panicked");
        }
        outcome
    }
}

/// How often staleness is judged on the server's clock.
pub const LIVENESS_CHECK_S: f64 = 1.0;

/// A short fingerprint of the parts of an installation that the filter state depends on.
fn installation_digest(inst: &Installation) -> String {
    let mut parts: Vec<String> = inst
        .model
        .links
        .iter()
        .map(|l| match &l.kind {
            crate::model::LinkKind::Measured(m) => format!("{}:{}", l.name, m.tuning.model.name()),
            crate::model::LinkKind::Calibrated { .. } => format!("{}:calibrated", l.name),
        })
        .collect();
    parts.sort();
    parts.join(",")
}

impl Service {
    /// Opens the store, restores the filters, references and calibrations, and starts the
    /// pipeline. The handle must be awaited after the last request, at shutdown.
    pub async fn start(installation: Installation) -> ServiceResult<(Service, PipelineHandle)> {
        Self::start_with_clock(installation, crate::clock::system()).await
    }

    /// Starts the service with the given clock as the server's (a test sets it instead of
    /// sleeping). Measurement times are unaffected: the clock judges liveness and the future
    /// limit of ingest, and stamps what the server records.
    pub async fn start_with_clock(
        installation: Installation,
        clock: crate::clock::SharedClock,
    ) -> ServiceResult<(Service, PipelineHandle)> {
        let installation = Arc::new(installation);
        let (store, write) = store::open(&installation, clock.now_ns()).await?;

        let mut bank = FilterBank::shared(Arc::clone(&installation.model));
        for spec in &installation.model.links {
            if matches!(spec.kind, crate::model::LinkKind::Calibrated { .. }) {
                for c in store.calibrations(spec.id).await? {
                    bank.add_calibration(spec.id, c.valid_from_ns, c.parent_from_child);
                }
            }
        }
        let digest = installation_digest(&installation);
        if let Some((stored_digest, state)) = store.filter_state().await? {
            if stored_digest != digest {
                tracing::warn!(
                    stored = %stored_digest,
                    now = %digest,
                    "the installation's links changed since the filter state was saved; restoring what still fits"
                );
            }
            match serde_json::from_str::<crate::bank::BankRecord>(&state) {
                Ok(record) => {
                    for skipped in bank.restore(&record) {
                        tracing::warn!(%skipped, "filter state not restored");
                    }
                }
                Err(e) => {
                    tracing::warn!(error = %e, "the stored filter state is unreadable; filters start afresh")
                }
            }
        }
        let mut targets = Vec::with_capacity(installation.model.targets.len());
        for (ti, _) in installation.model.target_ids() {
            let reference = store.references(ti).await?.pop();
            let latest = store
                .latest_result(ti, crate::bank::ResultSource::Filtered)
                .await?
                .map(|r| TargetEstimate {
                    target: ti,
                    time_ns: r.time_ns,
                    status: r.status,
                    target_from_base: Some(r.estimate),
                    age_s: r.age_s,
                    consistency: None,
                    paths_used: 0,
                });
            let [deformation, rate, stale] = store.alarm_levels(ti).await?;
            let alarms = crate::alarms::AlarmMonitor::new(
                installation.model.targets[ti.0].alarms,
                deformation,
                rate,
                stale,
            );
            targets.push(TargetView {
                latest,
                reference,
                alarms,
            });
        }
        let mut newest_sample_ns = Vec::with_capacity(installation.model.links.len());
        for l in 0..installation.model.links.len() {
            newest_sample_ns.push(store.newest_sample_ns(crate::chain::LinkId(l)).await?);
        }
        let snapshot = Arc::new(Snapshot {
            targets: targets.clone(),
            bank: bank.current_view(),
        });
        let (viz, viz_thread) = crate::viz::start(&installation)?;
        let viz_counters = Arc::clone(viz.counters());
        let frame_viz = viz.frame_sender(installation.rerun.image_hz);
        let (jobs, rx) = mpsc::channel(1024);
        let slot = Arc::new(RwLock::new(snapshot));
        let metrics = Arc::new(Metrics::default());
        let (events, _) = tokio::sync::broadcast::channel(EVENT_BUFFER);
        let (alarm_tx, alarm_rx) = if installation.notify.webhooks.is_empty() {
            (None, None)
        } else {
            let (tx, rx) = mpsc::channel(ALARM_FEED_CAPACITY);
            (Some(tx), Some(rx))
        };
        let inner = Arc::new(Inner {
            events: events.clone(),
            installation: Arc::clone(&installation),
            store: store.clone(),
            jobs,
            snapshot: Arc::clone(&slot),
            metrics: Arc::clone(&metrics),
            viz_counters,
            frame_viz,
            observer: Arc::new(crate::model::Observer::new(&installation.model)),
            stopping: tokio::sync::watch::channel(false).0,
            clock: Arc::clone(&clock),
            alarm_feed: std::sync::Mutex::new(alarm_rx),
            storage_problem: std::sync::Mutex::new(None),
            report_problem: std::sync::Mutex::new(None),
            tasks: TaskWatch::default(),
            acceptance: tokio::sync::Mutex::new(None),
            heavy_reads: Arc::new(tokio::sync::Semaphore::new(
                installation.server.max_heavy_reads,
            )),
        });
        let task = tokio::spawn(pipeline::run(
            pipeline::Pipeline::new(
                write,
                store,
                bank,
                targets,
                digest,
                newest_sample_ns,
                pipeline::Outlets {
                    metrics,
                    events,
                    viz,
                    clock,
                    alarm_feed: alarm_tx,
                    events_max_hz: installation.server.events_max_hz,
                    clock_tolerance_s: installation.server.clock_tolerance_s,
                },
            ),
            rx,
            move |s: Snapshot| match slot.write() {
                Ok(mut guard) => *guard = Arc::new(s),
                Err(poisoned) => *poisoned.into_inner() = Arc::new(s),
            },
        ));
        let service = Service { inner };
        // Retention runs every ten minutes through the pipeline; the task ends with the service.
        let weak = Arc::downgrade(&service.inner);
        service.spawn_watched("retention", async move {
            let mut every = tokio::time::interval(std::time::Duration::from_secs(600));
            every.tick().await;
            loop {
                every.tick().await;
                let Some(inner) = weak.upgrade() else { return };
                match (Service { inner }).prune().await {
                    Ok((0, 0)) => {}
                    Ok((samples, results)) => {
                        tracing::info!(samples, results, "retention pruned old rows")
                    }
                    Err(e) => tracing::warn!(error = %e, "retention failed"),
                }
            }
        });
        // The scheduled report is looked for every ten minutes (and at once): the last period
        // that has ended is filed when its file is not there.
        if let Some(settings) = service.installation().reports.clone() {
            let weak = Arc::downgrade(&service.inner);
            service.spawn_watched("reports", async move {
                let mut every = tokio::time::interval(std::time::Duration::from_secs(600));
                loop {
                    every.tick().await;
                    let Some(inner) = weak.upgrade() else { return };
                    match (Service { inner }).file_due_report(&settings).await {
                        Ok(None) => {}
                        Ok(Some(path)) => {
                            tracing::info!(path = %path.display(), "filed the period's report")
                        }
                        Err(e) => tracing::error!(error = %e, "the period's report was not filed"),
                    }
                }
            });
        }
        // Staleness is judged every second on the server's clock, whether data comes or not.
        let weak = Arc::downgrade(&service.inner);
        service.spawn_watched("liveness", async move {
            let mut every =
                tokio::time::interval(std::time::Duration::from_secs_f64(LIVENESS_CHECK_S));
            every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                every.tick().await;
                let Some(inner) = weak.upgrade() else { return };
                if *inner.stopping.borrow() {
                    return;
                }
                if let Err(e) = (Service { inner }).check_liveness().await {
                    tracing::warn!(error = %e, "the liveness check failed");
                }
            }
        });
        Ok((service, PipelineHandle(task, viz_thread)))
    }

    /// Every alarm transition stored from now on, in commit order, for the notifier: `Some` to
    /// the first caller when webhooks are configured. Sending into it never waits; when the
    /// notifier falls [`ALARM_FEED_CAPACITY`] behind, transitions are dropped and counted.
    pub fn take_alarm_feed(&self) -> Option<mpsc::Receiver<crate::store::StoredAlarm>> {
        match self.inner.alarm_feed.lock() {
            Ok(mut g) => g.take(),
            Err(poisoned) => poisoned.into_inner().take(),
        }
    }

    /// The server's clock.
    pub fn clock(&self) -> crate::clock::SharedClock {
        Arc::clone(&self.inner.clock)
    }

    /// The server's clock now (ns since the Unix epoch).
    pub fn now_ns(&self) -> i64 {
        self.inner.clock.now_ns()
    }

    /// Judges every target's staleness now (the service does so every second by itself);
    /// returns how many stale alarms changed level, each stored and sent live.
    pub async fn check_liveness(&self) -> ServiceResult<usize> {
        self.submit((), Job::CheckLiveness).await
    }

    /// The installation.
    pub fn installation(&self) -> &Installation {
        &self.inner.installation
    }

    /// The installation's camera-marker links, for solving observations.
    pub fn observer(&self) -> Arc<crate::model::Observer> {
        Arc::clone(&self.inner.observer)
    }

    /// The store's read side.
    pub fn store(&self) -> &Store {
        &self.inner.store
    }

    /// The state as of the last commit.
    pub fn snapshot(&self) -> Arc<Snapshot> {
        match self.inner.snapshot.read() {
            Ok(g) => Arc::clone(&g),
            Err(poisoned) => Arc::clone(&poisoned.into_inner()),
        }
    }

    /// Waits for a turn at a heavy read (`[server] max_heavy_reads` run at once); the turn
    /// lasts as long as the permit is held.
    pub async fn heavy_read(&self) -> Option<tokio::sync::OwnedSemaphorePermit> {
        Arc::clone(&self.inner.heavy_reads)
            .acquire_owned()
            .await
            .ok()
    }

    /// Where the HTTP handlers offer camera frames for Rerun (`[rerun] image_hz`).
    pub fn frame_viz(&self) -> &crate::viz::FrameSender {
        &self.inner.frame_viz
    }

    /// Marks the start of shutdown: live event streams end.
    pub fn begin_shutdown(&self) {
        self.inner.stopping.send_replace(true);
    }

    /// Spawns a background task that lives as long as the service: one that ends before
    /// shutdown begins is reported by [`Service::tasks_problem`].
    pub fn spawn_watched<F>(&self, name: &'static str, task: F) -> tokio::task::JoinHandle<()>
    where
        F: std::future::Future<Output = ()> + Send + 'static,
    {
        self.inner.tasks.spawn(name, self.stopping(), task)
    }

    /// The background tasks that stopped while the service runs, and why.
    pub fn tasks_problem(&self) -> Option<String> {
        self.inner.tasks.problem()
    }

    /// Turns true when shutdown begins.
    pub fn stopping(&self) -> tokio::sync::watch::Receiver<bool> {
        self.inner.stopping.subscribe()
    }

    /// Subscribes to live events.
    pub fn subscribe(&self) -> tokio::sync::broadcast::Receiver<LiveEvent> {
        self.inner.events.subscribe()
    }

    /// What went to Rerun (all zero when it is off).
    pub fn viz_counters(&self) -> &crate::viz::VizCounters {
        &self.inner.viz_counters
    }

    /// The pipeline's counters.
    pub fn metrics(&self) -> &Metrics {
        &self.inner.metrics
    }

    /// The counters, shared (for the server loop, which counts the refusals it writes itself).
    pub fn metrics_handle(&self) -> Arc<Metrics> {
        Arc::clone(&self.inner.metrics)
    }

    /// Jobs waiting for the pipeline.
    pub fn queue_depth(&self) -> usize {
        self.inner.jobs.max_capacity() - self.inner.jobs.capacity()
    }

    /// True while the pipeline accepts jobs.
    pub fn pipeline_alive(&self) -> bool {
        !self.inner.jobs.is_closed()
    }

    /// Queues a job for the writer and waits for its answer.
    async fn submit<R, A>(&self, request: R, job: fn(job::Call<R, A>) -> Job) -> ServiceResult<A> {
        let (reply, answer) = oneshot::channel();
        self.inner
            .jobs
            .send(job(job::Call::new(request, reply)))
            .await
            .map_err(|_| ServiceError::ShuttingDown)?;
        answer.await.map_err(|_| ServiceError::WriterStopped)?
    }

    /// Ingests validated samples atomically: all are durably stored (or were already, as
    /// identical retries) when this returns `Ok`; none is when it returns an error.
    pub async fn ingest(&self, items: Vec<IngestItem>) -> ServiceResult<IngestReport> {
        self.submit(items, Job::Ingest).await
    }

    /// Sets a target's reference (a new version).
    pub async fn set_reference(
        &self,
        target: TargetId,
        request: ReferenceRequest,
    ) -> ServiceResult<ReferenceVersion> {
        self.submit(job::SetReference { target, request }, Job::SetReference)
            .await
    }

    /// Deletes samples and results older than the retention ages (counted back from the newest
    /// result, or from the server's clock when that is earlier); rollups stay. Returns how many `(samples, results)` were deleted.
    pub async fn prune(&self) -> ServiceResult<(u64, u64)> {
        let p = self.prune_report().await?;
        Ok((p.samples, p.results))
    }

    /// One pass of retention, as [`Service::prune`], with what the disk budget made it remove
    /// beyond the ages. When the budget removed rows, that is kept as the storage problem
    /// ([`Service::storage_problem`]), logged as an error and counted in the metrics.
    pub async fn prune_report(&self) -> ServiceResult<Pruned> {
        let retention = self.inner.installation.retention;
        let upstream_raw =
            (self.inner.installation.fleet.upstream.as_ref()).map(|u| u.raw_kbit_s > 0.0);
        let pruned = self
            .submit(
                job::Prune {
                    retention,
                    upstream_raw,
                },
                Job::Prune,
            )
            .await?;
        if let (Some(cut), Some(budget)) = (pruned.budget, retention.disk_budget_bytes)
            && cut.rows() > 0
        {
            let m = self.metrics();
            m.budget_rows_removed
                .fetch_add(cut.rows(), std::sync::atomic::Ordering::Relaxed);
            m.budget_unsent_removed
                .fetch_add(cut.unsent, std::sync::atomic::Ordering::Relaxed);
            let when =
                |t: Option<i64>| t.map_or_else(|| "none".to_owned(), crate::clock::format_ns);
            let problem = format!(
                "the disk budget ({:.0} MB) forced removing {} rows younger than their retention \
                 ({} samples, {} raw results before {}, {} filtered results before {}), {} of \
                 them not yet acknowledged by the centre, at {}",
                budget as f64 / 1e6,
                cut.rows(),
                cut.samples,
                cut.raw_results,
                when(cut.raw_before_ns),
                cut.results,
                when(cut.results_before_ns),
                cut.unsent,
                crate::clock::format_ns(self.now_ns()),
            );
            tracing::error!(problem = %problem, "storage budget reached");
            *self
                .inner
                .storage_problem
                .lock()
                .unwrap_or_else(|p| p.into_inner()) = Some(problem);
        }
        if let Some(cut) = pruned.budget {
            self.metrics()
                .database_used_bytes
                .store(cut.used_bytes_after, std::sync::atomic::Ordering::Relaxed);
        }
        Ok(pruned)
    }

    /// The last time the disk budget removed rows younger than their retention, and what: the
    /// service works on (`/healthz` stays 200), but history was lost, and on a fleet's site
    /// possibly rows the centre never received.
    pub fn storage_problem(&self) -> Option<String> {
        self.inner
            .storage_problem
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Records that the centre acknowledged `tier` up to the commit `seq` (in a commit of its
    /// own, like every write).
    pub async fn record_upstream_ack(
        &self,
        tier: crate::store::outbox::Tier,
        seq: i64,
    ) -> ServiceResult<()> {
        self.submit(job::RecordAck { tier, seq }, Job::RecordAck)
            .await
    }

    /// Restarts a measured link's filter from its next sample (see
    /// [`crate::bank::FilterBank::reset_link`]), recorded with who asked and why; returns when
    /// (ns, wall clock).
    pub async fn reset_link(
        &self,
        link: crate::chain::LinkId,
        by: Option<String>,
        note: Option<String>,
    ) -> ServiceResult<i64> {
        self.submit(job::ResetLink { link, by, note }, Job::ResetLink)
            .await
    }

    /// Acknowledges alarm transition `id`: who, and an optional note, recorded with the server's
    /// time. The same acknowledgement again is accepted (a retry); a different one of an
    /// acknowledged alarm is a conflict; a transition back to `none` has nothing to acknowledge.
    pub async fn acknowledge_alarm(
        &self,
        id: i64,
        by: String,
        note: Option<String>,
    ) -> ServiceResult<crate::store::StoredAlarm> {
        self.submit(
            job::AcknowledgeAlarm { id, by, note },
            Job::AcknowledgeAlarm,
        )
        .await?;
        let alarm = self
            .inner
            .store
            .alarm(id)
            .await?
            .ok_or_else(|| ServiceError::NotFound(format!("no alarm {id}")))?;
        // Live subscribers (the event stream, the plant's outputs) hear of it; none may be
        // listening.
        let _ = self
            .inner
            .events
            .send(LiveEvent::Acknowledged(alarm.clone()));
        Ok(alarm)
    }

    /// Stores a new calibration of a calibrated link, valid from `valid_from_ns`; returns its
    /// version.
    pub async fn add_calibration(
        &self,
        link: crate::chain::LinkId,
        valid_from_ns: i64,
        parent_from_child: PoseCov,
    ) -> ServiceResult<i64> {
        self.submit(
            job::AddCalibration {
                link,
                valid_from_ns,
                parent_from_child,
            },
            Job::AddCalibration,
        )
        .await
    }
}
