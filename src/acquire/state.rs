//! What each camera source is doing, shared between its acquisition thread and the readers
//! (`GET /api/v1/cameras`, `/metrics`, `acquire`'s log), and the queue through which its frames
//! leave: [`QUEUED_FRAMES`] frames in time order, the oldest dropped (and counted) when a new one
//! finds it full, so a camera never waits and a hiccup of ingest (a commit, a checkpoint) costs
//! nothing.

use super::timing::FitReport;
use crate::config::{CameraSource, TimestampMode, TriggerMode};
use crate::vision::GreyImage;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

crate::words! {
    /// Where a camera source stands.
    pub enum SourceStatus("camera source status") {
        /// Opening and configuring the camera.
        Connecting = "connecting",
        /// Frames arrive.
        Streaming = "streaming",
        /// The camera was lost or could not be reached; tried again with back-off.
        Disconnected = "disconnected",
        /// The camera refused a setting of `[cameras.source]` (named in the error); tried again
        /// with back-off.
        Refused = "refused",
        /// This build cannot take frames from cameras (built without the `genicam` feature).
        Unsupported = "unsupported",
        /// Acquisition has stopped (the service is shutting down).
        Stopped = "stopped",
    }
}

/// A frame taken from a camera, its time settled.
#[derive(Debug)]
pub struct AcquiredFrame {
    /// The measurement time: UTC ns, the middle of the exposure.
    pub time_ns: i64,
    /// The frame.
    pub image: GreyImage,
    /// The host's clock when it arrived (ns).
    pub arrival_ns: i64,
}

/// The last error and what the connection knows.
#[derive(Debug, Clone)]
pub struct SourceDetail {
    /// Where it stands.
    pub status: SourceStatus,
    /// The last error, and when (host clock, ns).
    pub last_error: Option<(String, i64)>,
    /// The camera's PTP status as last read (`ptp` mode).
    pub ptp_status: Option<String>,
    /// The device clock's fit (`host_fit` mode).
    pub clock_fit: Option<FitReport>,
    /// The camera's vendor and model, once connected.
    pub device: Option<String>,
    /// The exposure in force (µs), once connected.
    pub exposure_us: Option<f64>,
}

/// Counters of one source.
#[derive(Debug, Default)]
pub struct SourceCounters {
    /// Complete frames received.
    pub received: AtomicU64,
    /// Frames handed on and taken by ingest.
    pub ingested: AtomicU64,
    /// Frames dropped from a full queue for a newer one before ingest took them.
    pub dropped: AtomicU64,
    /// Buffers that arrived incomplete (lost packets, timeouts), not used.
    pub incomplete: AtomicU64,
    /// Frames refused for their time (PTP not synchronised, a time far from the host's clock).
    pub refused_time: AtomicU64,
    /// Frames taken before `host_fit`'s clock fit settled (its first three seconds), not used.
    pub settling: AtomicU64,
    /// Frames ingest refused or failed on.
    pub failed: AtomicU64,
    /// Connections made again after a loss.
    pub reconnects: AtomicU64,
}

/// One camera source's state.
#[derive(Debug)]
pub struct SourceState {
    /// Its settings.
    pub source: CameraSource,
    /// Counters.
    pub counters: SourceCounters,
    detail: Mutex<SourceDetail>,
    queue: Mutex<std::collections::VecDeque<AcquiredFrame>>,
    ready: tokio::sync::Notify,
    closed: AtomicBool,
    /// The newest frames' delays from the middle of the exposure to the result committed (s).
    delays_s: Mutex<std::collections::VecDeque<f64>>,
}

/// Frames a source's queue holds: 160 ms at 25 Hz.
pub const QUEUED_FRAMES: usize = 4;

/// How many frames' delays a source keeps.
const DELAYS_KEPT: usize = 1000;

/// What a reader sees of a source.
#[derive(Debug, Clone)]
pub struct SourceReport {
    /// The camera.
    pub camera: String,
    /// Its address.
    pub address: String,
    /// Its trigger.
    pub trigger: TriggerMode,
    /// Its timestamp mode.
    pub timestamp: TimestampMode,
    /// Status, errors, PTP and the clock fit.
    pub detail: SourceDetail,
    /// Complete frames received.
    pub received: u64,
    /// Frames taken by ingest.
    pub ingested: u64,
    /// Frames replaced by newer ones before ingest took them.
    pub dropped: u64,
    /// Incomplete buffers.
    pub incomplete: u64,
    /// Frames refused for their time.
    pub refused_time: u64,
    /// Frames taken before the clock fit settled.
    pub settling: u64,
    /// Frames ingest refused or failed on.
    pub failed: u64,
    /// Connections made again.
    pub reconnects: u64,
    /// The median and 99th percentile of the newest frames' delays from the middle of the
    /// exposure to the result committed (s).
    pub delay_s: Option<(f64, f64)>,
}

impl SourceState {
    /// A source not yet started.
    pub fn new(source: CameraSource) -> Self {
        Self {
            source,
            counters: SourceCounters::default(),
            detail: Mutex::new(SourceDetail {
                status: SourceStatus::Connecting,
                last_error: None,
                ptp_status: None,
                clock_fit: None,
                device: None,
                exposure_us: None,
            }),
            queue: Mutex::new(std::collections::VecDeque::with_capacity(QUEUED_FRAMES + 1)),
            ready: tokio::sync::Notify::new(),
            closed: AtomicBool::new(false),
            delays_s: Mutex::new(std::collections::VecDeque::new()),
        }
    }

    fn detail(&self) -> std::sync::MutexGuard<'_, SourceDetail> {
        self.detail.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Updates what the connection knows.
    pub fn update(&self, f: impl FnOnce(&mut SourceDetail)) {
        f(&mut self.detail());
    }

    /// Records an error; it is logged (with the camera's name) when it differs from the last
    /// one, so a camera refusing every frame for the same reason does not fill the log.
    pub fn error(&self, status: SourceStatus, message: String, now_ns: i64) {
        let mut d = self.detail();
        if d.last_error
            .as_ref()
            .is_none_or(|(last, _)| *last != message)
        {
            tracing::warn!(camera = %self.source.camera, address = %self.source.address, "{message}");
        }
        d.status = status;
        d.last_error = Some((message, now_ns));
    }

    /// Records a frame ingested `delay_s` after the middle of its exposure.
    pub fn ingested(&self, delay_s: f64) {
        self.counters.ingested.fetch_add(1, Ordering::Relaxed);
        let mut d = self.delays_s.lock().unwrap_or_else(|p| p.into_inner());
        if d.len() == DELAYS_KEPT {
            d.pop_front();
        }
        d.push_back(delay_s);
    }

    /// Records a frame ingest refused or failed on, keeping the status.
    pub fn failed(&self, message: String, now_ns: i64) {
        self.counters.failed.fetch_add(1, Ordering::Relaxed);
        let mut d = self.detail();
        if d.last_error
            .as_ref()
            .is_none_or(|(last, _)| *last != message)
        {
            tracing::warn!(camera = %self.source.camera, "a frame was not taken: {message}");
        }
        d.last_error = Some((message, now_ns));
    }

    /// Hands a frame on; a full queue drops its oldest, counted.
    pub fn offer(&self, frame: AcquiredFrame) {
        let dropped = {
            let mut queue = self.queue.lock().unwrap_or_else(|p| p.into_inner());
            queue.push_back(frame);
            queue.len() > QUEUED_FRAMES && queue.pop_front().is_some()
        };
        if dropped {
            self.counters.dropped.fetch_add(1, Ordering::Relaxed);
        }
        self.ready.notify_one();
    }

    /// The oldest frame waiting, waiting for one; `None` once the source is closed and empty.
    pub async fn next(&self) -> Option<AcquiredFrame> {
        loop {
            if let Some(f) = self.take() {
                return Some(f);
            }
            if self.closed.load(Ordering::Acquire) {
                return None;
            }
            self.ready.notified().await;
        }
    }

    /// The oldest frame waiting, if any (for a caller outside the async runtime).
    pub fn take(&self) -> Option<AcquiredFrame> {
        self.queue
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .pop_front()
    }

    /// Ends [`SourceState::next`] for its readers once the queue is empty.
    pub fn close(&self) {
        self.closed.store(true, Ordering::Release);
        self.update(|d| d.status = SourceStatus::Stopped);
        self.ready.notify_one();
    }

    /// A copy for readers.
    pub fn report(&self) -> SourceReport {
        let c = &self.counters;
        let get = |a: &AtomicU64| a.load(Ordering::Relaxed);
        SourceReport {
            camera: self.source.camera.clone(),
            address: self.source.address.to_string(),
            trigger: self.source.trigger,
            timestamp: self.source.timestamp,
            detail: self.detail().clone(),
            received: get(&c.received),
            ingested: get(&c.ingested),
            dropped: get(&c.dropped),
            incomplete: get(&c.incomplete),
            refused_time: get(&c.refused_time),
            settling: get(&c.settling),
            failed: get(&c.failed),
            reconnects: get(&c.reconnects),
            delay_s: {
                let mut d: Vec<f64> = self
                    .delays_s
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .iter()
                    .copied()
                    .collect();
                d.sort_by(f64::total_cmp);
                let at = |q: f64| d[((d.len() - 1) as f64 * q).round() as usize];
                (!d.is_empty()).then(|| (at(0.5), at(0.99)))
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_full_queue_drops_its_oldest_and_counts_it() {
        let installation = crate::config::parse(
            "t",
            &crate::config::DEFAULT_INSTALLATION_TOML.replacen(
                "[[cameras]]",
                "[[cameras]]\nsource = { address = \"127.0.0.2\" }",
                1,
            ),
        )
        .unwrap();
        let state = SourceState::new(installation.sources[0].clone());
        let frame = |t| AcquiredFrame {
            time_ns: t,
            image: GreyImage::from_u8(2, 1, &[1, 2]).unwrap(),
            arrival_ns: t,
        };
        for t in 1..=6 {
            state.offer(frame(t));
        }
        assert_eq!(state.report().dropped, 2);
        for t in 3..=6 {
            assert_eq!(state.next().await.map(|f| f.time_ns), Some(t));
        }
        state.close();
        assert!(state.next().await.is_none());
    }
}
