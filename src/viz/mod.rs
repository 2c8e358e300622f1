//! Visualisation in Rerun: the frames, the deformation series and the alarms, live or as
//! recordings for review (`[rerun]` of the configuration).
//!
//! The pipeline never calls Rerun. It hands plain [`Record`]s to a [`VizSender`], which
//! decimates them (per series, in measurement time) and offers them to a bounded queue with
//! `try_send`: when the queue is full the record is dropped and counted, the pipeline never
//! waits. One logger thread ([`logger`]) owns the Rerun recording streams and is the only code
//! that calls the SDK; a stalled sink (a viewer that went away, or never came) stalls that
//! thread only.
//!
//! The same [`logger::Logger`] writes the recordings `brokenray replay` rebuilds from the
//! stored history ([`replay`]).

pub mod blueprint;
pub mod logger;
pub mod replay;

use crate::alarms::Transition;
use crate::config::{Installation, RerunSettings};
use crate::deformation::SmallMotion;
use crate::geometry::{Pose, PoseCov};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};

/// The name of the measurement-time timeline (timestamps of the samples, not the wall clock).
pub const TIMELINE: &str = "time";

/// One thing to show. Plain data: building one never touches Rerun.
#[derive(Debug, Clone, PartialEq)]
#[allow(
    clippy::large_enum_variant,
    reason = "moved once into a preallocated queue slot; boxing would allocate per record"
)]
pub enum Record {
    /// A measured link's sample as the filter judged it.
    Sample {
        /// Link index.
        link: usize,
        /// Measurement time (ns).
        time_ns: i64,
        /// Normalised innovation squared, where the filter computed one.
        nis: Option<f64>,
        /// Rejected as an outlier.
        outlier: bool,
    },
    /// A raw (from one sample group) or filtered result of a target.
    Result {
        /// Target index.
        target: usize,
        /// Its time (ns).
        time_ns: i64,
        /// Filtered, or raw.
        filtered: bool,
        /// `target_from_base`.
        target_from_base: PoseCov,
        /// `G0_from_G` against the reference in force, with sigmas.
        deformation: Option<SmallMotion>,
    },
    /// The frames placed by the links' filtered poses at a time.
    Scene {
        /// Time (ns).
        time_ns: i64,
        /// Per link index: `parent_from_child`, where known.
        link_poses: Vec<Option<Pose>>,
    },
    /// A target's reference (from when it is in force).
    Reference {
        /// Target index.
        target: usize,
        /// Time (ns).
        time_ns: i64,
        /// `G0_from_B`.
        g0_from_b: Pose,
    },
    /// An alarm transition.
    Alarm {
        /// Target index.
        target: usize,
        /// The transition.
        transition: Transition,
    },
}

impl Record {
    /// The record's measurement time (ns).
    pub fn time_ns(&self) -> i64 {
        match self {
            Record::Sample { time_ns, .. }
            | Record::Result { time_ns, .. }
            | Record::Scene { time_ns, .. }
            | Record::Reference { time_ns, .. } => *time_ns,
            Record::Alarm { transition, .. } => transition.time_ns,
        }
    }
}

/// Counters of what went to Rerun, for `/metrics`.
#[derive(Debug, Default)]
pub struct VizCounters {
    /// Records queued for the logger.
    pub queued: AtomicU64,
    /// Records dropped because the queue was full.
    pub dropped: AtomicU64,
    /// Records the logger wrote.
    pub logged: AtomicU64,
    /// Records left out by decimation.
    pub decimated: AtomicU64,
    /// Errors of the Rerun SDK (logged, then ignored).
    pub errors: AtomicU64,
    /// Recording files started.
    pub files: AtomicU64,
}

/// Keeps at most one record per series and interval of measurement time.
#[derive(Debug, Clone)]
pub struct Decimator {
    scene_interval_ns: i64,
    series_interval_ns: i64,
    /// Per series key: the time of the last record let through.
    last_ns: std::collections::HashMap<(u8, usize), i64>,
}

impl Decimator {
    /// At most `scene_hz` scenes and `series_hz` points per series per second.
    pub fn new(scene_hz: f64, series_hz: f64) -> Self {
        let interval = |hz: f64| {
            if hz.is_finite() && hz > 0.0 {
                (1e9 / hz) as i64
            } else {
                0
            }
        };
        Self {
            scene_interval_ns: interval(scene_hz),
            series_interval_ns: interval(series_hz),
            last_ns: Default::default(),
        }
    }

    /// Lets everything through.
    pub fn everything() -> Self {
        Self::new(f64::INFINITY, f64::INFINITY)
    }

    /// Whether a scene at `time_ns` is due.
    pub fn scene_due(&self, time_ns: i64) -> bool {
        self.due((0, 0), self.scene_interval_ns, time_ns)
    }

    fn due(&self, key: (u8, usize), interval: i64, time_ns: i64) -> bool {
        self.last_ns
            .get(&key)
            .is_none_or(|&last| time_ns < last || time_ns >= last.saturating_add(interval))
    }

    /// Whether `record` is kept; outliers, references and alarms always are.
    pub fn keep(&mut self, record: &Record) -> bool {
        let (key, interval) = match record {
            Record::Sample { outlier: true, .. }
            | Record::Reference { .. }
            | Record::Alarm { .. } => return true,
            Record::Sample { link, .. } => ((1, *link), self.series_interval_ns),
            Record::Result {
                target, filtered, ..
            } => ((2 + u8::from(*filtered), *target), self.series_interval_ns),
            Record::Scene { .. } => ((0, 0), self.scene_interval_ns),
        };
        let t = record.time_ns();
        if self.due(key, interval, t) {
            self.last_ns.insert(key, t);
            true
        } else {
            false
        }
    }
}

/// The pipeline's end of the queue: decimates, then offers without ever waiting.
#[derive(Debug)]
pub struct VizSender {
    tx: Option<SyncSender<Record>>,
    decimator: Decimator,
    counters: Arc<VizCounters>,
}

impl VizSender {
    /// A sender that shows nothing (`mode = "off"`).
    pub fn off() -> Self {
        Self {
            tx: None,
            decimator: Decimator::everything(),
            counters: Arc::default(),
        }
    }

    /// Whether anything is shown.
    pub fn enabled(&self) -> bool {
        self.tx.is_some()
    }

    /// Whether a scene at `time_ns` would be kept (to skip computing it otherwise).
    pub fn scene_due(&self, time_ns: i64) -> bool {
        self.enabled() && self.decimator.scene_due(time_ns)
    }

    /// Offers a record: kept or decimated away, queued or dropped; never waits.
    pub fn send(&mut self, record: Record) {
        let Some(tx) = &self.tx else { return };
        if !self.decimator.keep(&record) {
            self.counters.decimated.fetch_add(1, Relaxed);
            return;
        }
        match tx.try_send(record) {
            Ok(()) => {
                self.counters.queued.fetch_add(1, Relaxed);
            }
            Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => {
                self.counters.dropped.fetch_add(1, Relaxed);
            }
        }
    }

    /// The counters.
    pub fn counters(&self) -> &Arc<VizCounters> {
        &self.counters
    }
}

/// Errors of starting the visualisation.
#[derive(Debug, thiserror::Error)]
pub enum VizError {
    /// The recordings directory could not be made.
    #[error("cannot create the recordings directory {path}: {source}")]
    RecordingsDir {
        /// The directory.
        path: std::path::PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The Rerun SDK refused a sink.
    #[error("cannot start Rerun's {what}: {message}")]
    Sink {
        /// `save`, `connect` or `serve`.
        what: &'static str,
        /// The SDK's message.
        message: String,
    },
    /// The logger thread could not start.
    #[error("cannot start the Rerun logger thread: {0}")]
    Thread(std::io::Error),
}

/// The logger thread, to wait for at shutdown.
#[derive(Debug)]
pub struct VizThread(Option<std::thread::JoinHandle<()>>);

impl VizThread {
    /// No thread (visualisation off).
    pub fn none() -> Self {
        Self(None)
    }

    /// Waits (up to `timeout`) for the logger to write out what it has and close its
    /// recordings; returns whether it finished. Call after the last [`VizSender`] is dropped.
    pub fn finish(self, timeout: std::time::Duration) -> bool {
        let Some(handle) = self.0 else { return true };
        let deadline = std::time::Instant::now() + timeout;
        while !handle.is_finished() {
            if std::time::Instant::now() >= deadline {
                tracing::warn!("the Rerun logger did not finish in time; leaving it");
                return false;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        handle.join().is_ok()
    }
}

/// Starts the logger thread for `installation.rerun`: a disabled sender and no thread when
/// nothing is configured.
pub fn start(installation: &Arc<Installation>) -> Result<(VizSender, VizThread), VizError> {
    let settings: &RerunSettings = &installation.rerun;
    if !settings.enabled() {
        return Ok((VizSender::off(), VizThread::none()));
    }
    let counters = Arc::new(VizCounters::default());
    let logger = logger::Logger::live(installation, Arc::clone(&counters))?;
    let (tx, rx) = std::sync::mpsc::sync_channel(settings.queue_capacity);
    let handle = std::thread::Builder::new()
        .name("rerun-logger".into())
        .spawn(move || run_logger(logger, rx))
        .map_err(VizError::Thread)?;
    Ok((
        VizSender {
            tx: Some(tx),
            decimator: Decimator::new(settings.scene_hz, settings.series_hz),
            counters,
        },
        VizThread(Some(handle)),
    ))
}

fn run_logger(mut logger: logger::Logger, rx: Receiver<Record>) {
    while let Ok(record) = rx.recv() {
        logger.log(&record);
    }
    logger.close();
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(link: usize, time_ns: i64, outlier: bool) -> Record {
        Record::Sample {
            link,
            time_ns,
            nis: Some(1.0),
            outlier,
        }
    }

    #[test]
    fn decimation_keeps_one_point_per_series_and_interval_and_every_outlier() {
        // 10 points a second per series; samples every 40 ms on two links for 2 s.
        let mut d = Decimator::new(1.0, 10.0);
        let mut kept = [0usize; 2];
        for k in 0..50 {
            for (link, n) in kept.iter_mut().enumerate() {
                if d.keep(&sample(link, k * 40_000_000, false)) {
                    *n += 1;
                }
            }
        }
        // 0, 120, 240, ... 1920 ms: one per 100 ms interval started, on each link alone.
        assert_eq!(kept, [17, 17]);
        assert!(
            d.keep(&sample(0, 1_930_000_000, true)),
            "outliers always pass"
        );
        assert!(!d.keep(&sample(0, 1_940_000_000, false)));
        // A time going backwards (a replay, a restarted pipeline) starts the series afresh.
        assert!(d.keep(&sample(0, 0, false)));
    }

    #[test]
    fn an_off_sender_counts_nothing() {
        let mut s = VizSender::off();
        s.send(sample(0, 0, false));
        assert!(!s.enabled());
        assert_eq!(s.counters().queued.load(Relaxed), 0);
        assert_eq!(s.counters().dropped.load(Relaxed), 0);
    }
}
