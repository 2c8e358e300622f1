//! Visualisation in Rerun: the frames, the deformation series and the alarms, live or as
//! recordings for review (`[rerun]` of the configuration).
//!
//! The pipeline never calls Rerun. It hands plain [`Record`]s to a [`VizSender`], which
//! decimates them (per series, in measurement time) and offers them to a bounded queue with
//! `try_send`: when the queue is full the record is dropped and counted, the pipeline never
//! waits. One logger thread (`logger`) owns the Rerun recording streams and is the only code
//! that calls the SDK; a stalled sink (a viewer that went away, or never came) stalls that
//! thread only.
//!
//! The same `logger::Logger` writes the recordings `brokenray replay` rebuilds from the
//! stored history (`replay`).

mod blueprint;
mod logger;
pub(crate) mod replay;

use crate::alarms::Transition;
use crate::config::{Installation, RerunSettings};
use crate::deformation::SmallMotion;
use crate::geometry::Pose;
use crate::model::TargetId;
use crate::vision::GreyImage;
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
        target: TargetId,
        /// Its time (ns).
        time_ns: i64,
        /// Filtered, or raw.
        source: crate::bank::ResultSource,
        /// `target_from_base` with its whole covariance and its systematic part.
        target_from_base: crate::deformation::MeasuredPose,
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
        target: TargetId,
        /// Time (ns).
        time_ns: i64,
        /// `G0_from_B`.
        g0_from_b: Pose,
    },
    /// An alarm transition.
    Alarm {
        /// Target index.
        target: TargetId,
        /// The transition.
        transition: Transition,
    },
    /// A camera frame and what was found in it (already decimated: [`FrameSender`]).
    Frame {
        /// Camera index (in the installation's cameras).
        camera: usize,
        /// Measurement time (ns).
        time_ns: i64,
        /// The frame.
        image: Arc<GreyImage>,
        /// Each marker of a measured link of the camera.
        marks: Vec<FrameMarks>,
        /// Counts the frame as waiting for the logger until the record is dropped.
        ticket: FrameTicket,
    },
}

/// A frame waiting for the logger: counted from [`FrameSender::offer`] until its record is
/// dropped (logged, or left in the queue at the end), so that frames, which weigh megabytes
/// where other records weigh bytes, are bounded by number in the queue.
#[derive(Debug, Default)]
pub struct FrameTicket(Option<Arc<std::sync::atomic::AtomicUsize>>);

impl FrameTicket {
    /// A ticket that counts nothing (records built outside the live queue, such as `replay`'s).
    pub fn none() -> Self {
        Self(None)
    }

    fn counting(pending: &Arc<std::sync::atomic::AtomicUsize>) -> Self {
        pending.fetch_add(1, Relaxed);
        Self(Some(Arc::clone(pending)))
    }
}

impl Clone for FrameTicket {
    fn clone(&self) -> Self {
        match &self.0 {
            Some(pending) => Self::counting(pending),
            None => Self(None),
        }
    }
}

impl PartialEq for FrameTicket {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl Drop for FrameTicket {
    fn drop(&mut self) {
        if let Some(pending) = &self.0 {
            pending.fetch_sub(1, Relaxed);
        }
    }
}

/// Frames waiting for the logger at most; more are dropped (and counted) until it catches up.
pub const MAX_PENDING_FRAMES: usize = 16;

/// What a frame showed of one marker, to draw over it.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameMarks {
    /// The marker's frame.
    pub marker: String,
    /// Detected points (px, pixel-centre convention), empty when not found.
    pub points_px: Vec<[f64; 2]>,
    /// Their ids.
    pub ids: Vec<u32>,
    /// The same points reprojected with the solved pose (px).
    pub reprojected_px: Vec<[f64; 2]>,
    /// Why it was not found; `None` when found.
    pub not_found: Option<String>,
}

impl Record {
    /// The record's measurement time (ns).
    pub fn time_ns(&self) -> i64 {
        match self {
            Record::Sample { time_ns, .. }
            | Record::Result { time_ns, .. }
            | Record::Scene { time_ns, .. }
            | Record::Reference { time_ns, .. }
            | Record::Frame { time_ns, .. } => *time_ns,
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

/// Keeps at most one record per series and interval of measurement time: the first whose time
/// falls in a new interval (`floor(t / interval)`). A record older than the newest one kept in
/// its series (a late, out-of-order sample) is left out: it is stored, and `replay` shows it.
#[derive(Debug, Clone)]
pub struct Decimator {
    scene_interval_ns: i64,
    series_interval_ns: i64,
    image_interval_ns: i64,
    /// Per series (see [`Decimator::series`]): the interval index of the last record let
    /// through, `i64::MIN` before the first.
    last_bucket: Vec<i64>,
}

/// The interval of a rate (ns); every record passes at a rate that is not a positive number.
fn interval_ns(hz: f64) -> i64 {
    if hz.is_finite() && hz > 0.0 {
        ((1e9 / hz) as i64).max(1)
    } else {
        1
    }
}

impl Decimator {
    /// At most `scene_hz` scenes and `series_hz` points per series per second (camera frames
    /// unlimited until [`Decimator::with_image_hz`]).
    pub fn new(scene_hz: f64, series_hz: f64) -> Self {
        Self {
            scene_interval_ns: interval_ns(scene_hz),
            series_interval_ns: interval_ns(series_hz),
            image_interval_ns: 1,
            last_bucket: Vec::new(),
        }
    }

    /// At most `image_hz` frames per camera per second.
    pub fn with_image_hz(self, image_hz: f64) -> Self {
        Self {
            image_interval_ns: interval_ns(image_hz),
            ..self
        }
    }

    /// The index of a series: the scene, each link's samples, each target's raw and filtered
    /// results, each camera's frames.
    fn series(kind: Series) -> usize {
        match kind {
            Series::Scene => 0,
            Series::Link(l) => 1 + 4 * l,
            Series::Raw(t) => 2 + 4 * t.0,
            Series::Filtered(t) => 3 + 4 * t.0,
            Series::Camera(c) => 4 + 4 * c,
        }
    }

    fn interval(&self, kind: Series) -> i64 {
        match kind {
            Series::Scene => self.scene_interval_ns,
            Series::Camera(_) => self.image_interval_ns,
            _ => self.series_interval_ns,
        }
    }

    /// Whether a record of `kind` at `time_ns` would be kept (nothing is recorded).
    pub fn due(&self, kind: Series, time_ns: i64) -> bool {
        let bucket = time_ns.div_euclid(self.interval(kind));
        self.last_bucket
            .get(Self::series(kind))
            .is_none_or(|&last| bucket > last)
    }

    /// Whether a record of `kind` at `time_ns` is kept, recording it if so.
    pub fn keep_series(&mut self, kind: Series, time_ns: i64) -> bool {
        if !self.due(kind, time_ns) {
            return false;
        }
        let i = Self::series(kind);
        if self.last_bucket.len() <= i {
            self.last_bucket.resize(i + 1, i64::MIN);
        }
        self.last_bucket[i] = time_ns.div_euclid(self.interval(kind));
        true
    }

    /// Whether `record` is kept; outliers, references and alarms always are.
    pub fn keep(&mut self, record: &Record) -> bool {
        let kind = match record {
            Record::Sample { outlier: true, .. }
            | Record::Reference { .. }
            | Record::Alarm { .. }
            | Record::Frame { .. } => return true,
            Record::Sample { link, .. } => Series::Link(*link),
            Record::Result { target, source, .. } => {
                if *source == crate::bank::ResultSource::Filtered {
                    Series::Filtered(*target)
                } else {
                    Series::Raw(*target)
                }
            }
            Record::Scene { .. } => Series::Scene,
        };
        self.keep_series(kind, record.time_ns())
    }
}

/// A decimated series.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Series {
    /// The frames.
    Scene,
    /// A link's samples (by link index).
    Link(usize),
    /// A target's raw results.
    Raw(TargetId),
    /// A target's filtered results.
    Filtered(TargetId),
    /// A camera's frames (by camera index).
    Camera(usize),
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
            decimator: Decimator::new(f64::INFINITY, f64::INFINITY),
            counters: Arc::default(),
        }
    }

    /// Whether anything is shown.
    pub fn enabled(&self) -> bool {
        self.tx.is_some()
    }

    /// Whether a record of `kind` at `time_ns` is kept, recording it if so: lets the pipeline
    /// build only the records that will be shown (then [`VizSender::send_kept`]). Outliers are
    /// always kept and need no asking.
    pub fn keep(&mut self, kind: Series, time_ns: i64) -> bool {
        if !self.enabled() {
            return false;
        }
        let kept = self.decimator.keep_series(kind, time_ns);
        if !kept {
            self.counters.decimated.fetch_add(1, Relaxed);
        }
        kept
    }

    /// Offers a record already decimated: queued or dropped; never waits.
    pub fn send_kept(&mut self, record: Record) {
        offer(self.tx.as_ref(), &self.counters, record);
    }

    /// The counters.
    pub fn counters(&self) -> &Arc<VizCounters> {
        &self.counters
    }

    /// A sender of camera frames into the same queue, at most `image_hz` per camera and
    /// second of measurement time.
    pub fn frame_sender(&self, image_hz: f64) -> FrameSender {
        FrameSender {
            tx: self.tx.clone(),
            pending: Arc::default(),
            decimator: std::sync::Mutex::new(
                Decimator::new(f64::INFINITY, f64::INFINITY).with_image_hz(image_hz),
            ),
            counters: Arc::clone(&self.counters),
        }
    }
}

/// The frames' end of the queue, for the HTTP handlers (shared, unlike [`VizSender`], which
/// the pipeline owns): at most `image_hz` frames per camera and second of measurement time,
/// and at most [`MAX_PENDING_FRAMES`] waiting for the logger, offered without ever waiting.
#[derive(Debug)]
pub struct FrameSender {
    tx: Option<SyncSender<Record>>,
    /// Frames sent and not yet dropped by the logger.
    pending: Arc<std::sync::atomic::AtomicUsize>,
    decimator: std::sync::Mutex<Decimator>,
    counters: Arc<VizCounters>,
}

impl FrameSender {
    /// Offers camera `camera`'s frame at `time_ns` with what to draw over it (`marks`, built
    /// only when the frame is due): queued, or decimated, or dropped because the logger is
    /// behind (counted); never waits. Returns whether it was queued.
    pub fn offer(
        &self,
        camera: usize,
        time_ns: i64,
        image: &Arc<GreyImage>,
        marks: impl FnOnce() -> Vec<FrameMarks>,
    ) -> bool {
        if self.tx.is_none() {
            return false;
        }
        let due = self
            .decimator
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .keep_series(Series::Camera(camera), time_ns);
        if !due {
            self.counters.decimated.fetch_add(1, Relaxed);
            return false;
        }
        if self.pending.load(Relaxed) >= MAX_PENDING_FRAMES {
            self.counters.dropped.fetch_add(1, Relaxed);
            return false;
        }
        offer(
            self.tx.as_ref(),
            &self.counters,
            Record::Frame {
                camera,
                time_ns,
                image: Arc::clone(image),
                marks: marks(),
                ticket: FrameTicket::counting(&self.pending),
            },
        )
    }

    /// Frames waiting for the logger now.
    pub fn pending(&self) -> usize {
        self.pending.load(Relaxed)
    }
}

/// Queues a record for the logger, or drops it when the queue is full (or the logger gone);
/// counted either way, never waits. Returns whether it was queued.
fn offer(tx: Option<&SyncSender<Record>>, counters: &VizCounters, record: Record) -> bool {
    let Some(tx) = tx else { return false };
    match tx.try_send(record) {
        Ok(()) => {
            counters.queued.fetch_add(1, Relaxed);
            true
        }
        Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => {
            counters.dropped.fetch_add(1, Relaxed);
            false
        }
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
    let (tx, rx) = std::sync::mpsc::sync_channel(settings.queue_capacity);
    let (ready_tx, ready_rx) = std::sync::mpsc::channel();
    let (inst, c) = (Arc::clone(installation), Arc::clone(&counters));
    let handle = std::thread::Builder::new()
        .name("rerun-logger".into())
        .spawn(move || {
            // Visualisation comes last: at the lowest CPU priority (nice 19), set before the
            // streams are made so that the SDK's batcher and writer threads inherit it. On a
            // saturated machine the queue then fills and records are dropped, rather than
            // ingest slowing down.
            if let Err(e) =
                thread_priority::set_current_thread_priority(thread_priority::ThreadPriority::Min)
            {
                tracing::warn!(error = ?e, "cannot lower the Rerun logger's priority");
            }
            match logger::Logger::live(&inst, c) {
                Ok(logger) => {
                    let _ = ready_tx.send(Ok(()));
                    run_logger(logger, rx);
                }
                Err(e) => {
                    let _ = ready_tx.send(Err(e));
                }
            }
        })
        .map_err(VizError::Thread)?;
    ready_rx.recv().map_err(|_| VizError::Sink {
        what: "logger",
        message: "the logger thread ended while starting".into(),
    })??;
    Ok((
        VizSender {
            tx: Some(tx),
            decimator: Decimator::new(settings.scene_hz, settings.series_hz),
            counters,
        },
        VizThread(Some(handle)),
    ))
}

/// Records written per batch at most.
const BATCH: usize = 4096;

fn run_logger(mut logger: logger::Logger, rx: Receiver<Record>) {
    let mut batch = Vec::with_capacity(BATCH);
    while let Ok(first) = rx.recv() {
        batch.push(first);
        while batch.len() < BATCH {
            match rx.try_recv() {
                Ok(r) => batch.push(r),
                Err(_) => break,
            }
        }
        logger.log_batch(&batch);
        batch.clear();
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
        // 0, 120, 200, 320, 400, ...: the first of each 100 ms interval, on each link alone.
        assert_eq!(kept, [20, 20]);
        assert!(
            d.keep(&sample(0, 1_930_000_000, true)),
            "outliers always pass"
        );
        assert!(!d.keep(&sample(0, 1_940_000_000, false)));
        // A late sample, older than the newest kept, is left out; the next interval is kept.
        assert!(!d.keep(&sample(0, 500_000_000, false)));
        assert!(d.keep(&sample(0, 2_000_000_000, false)));
    }

    #[test]
    fn frames_are_decimated_per_camera_and_bounded_while_the_logger_is_behind() {
        let (tx, rx) = std::sync::mpsc::sync_channel(1000);
        let sender = VizSender {
            tx: Some(tx),
            decimator: Decimator::new(1.0, 1.0),
            counters: Arc::default(),
        };
        let frames = sender.frame_sender(2.0);
        let image = Arc::new(GreyImage::from_u8(2, 2, &[0; 4]).expect("frame"));
        let offer = |camera: usize, time_ns: i64| frames.offer(camera, time_ns, &image, Vec::new);
        // 2 Hz per camera: 0 and 500 ms are due, 40 ms is not; each camera on its own.
        assert!(offer(0, 0));
        assert!(!offer(0, 40_000_000));
        assert!(offer(0, 500_000_000));
        assert!(offer(1, 40_000_000));
        assert_eq!(frames.pending(), 3);
        // The logger is behind: at most MAX_PENDING_FRAMES wait, the rest are dropped.
        let due = (0..40).filter(|&s| offer(2, s * 1_000_000_000)).count();
        assert_eq!(due, MAX_PENDING_FRAMES - 3);
        assert_eq!(frames.pending(), MAX_PENDING_FRAMES);
        assert_eq!(
            sender.counters().dropped.load(Relaxed),
            40 - (MAX_PENDING_FRAMES as u64 - 3)
        );
        // The logger drops what it logged: frames are taken again.
        drop(rx.try_iter().collect::<Vec<_>>());
        assert_eq!(frames.pending(), 0);
        assert!(offer(2, 100_000_000_000));
    }

    #[test]
    fn an_off_sender_counts_nothing() {
        let mut s = VizSender::off();
        assert!(!s.keep(Series::Link(0), 0));
        s.send_kept(sample(0, 0, false));
        assert!(!s.enabled());
        assert_eq!(s.counters().queued.load(Relaxed), 0);
        assert_eq!(s.counters().dropped.load(Relaxed), 0);
    }
}
