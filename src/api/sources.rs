//! The state of a camera `serve` takes frames from itself ([`crate::acquire`], its frames taken
//! by [`crate::intake`]) as `GET /api/v1/cameras` shows it.

use crate::acquire::{SourceReport, SourceStatus};
use crate::clock::format_ns;
use crate::config::{TimestampMode, TriggerMode};
use serde::Serialize;

/// A camera source's state in `GET /api/v1/cameras`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct SourceOut {
    /// The camera's address (`[cameras.source] address`).
    pub address: String,
    /// Where it stands.
    pub status: SourceStatus,
    /// Whether frames arrive.
    pub connected: bool,
    /// The camera's vendor and model, once connected.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub device: Option<String>,
    /// What starts an exposure.
    pub trigger: TriggerMode,
    /// Where frame times come from.
    pub timestamp: TimestampMode,
    /// The exposure in force (µs).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub exposure_us: Option<f64>,
    /// `ptp`: the camera's PTP status as last read (`Slave` is synchronised).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ptp_status: Option<String>,
    /// `host_fit`: the device clock against the host's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub clock_fit: Option<ClockFitOut>,
    /// Complete frames received.
    pub frames_received: u64,
    /// Frames ingested.
    pub frames_ingested: u64,
    /// Frames dropped, oldest first, from a full queue (four frames) before ingest took them.
    pub frames_dropped: u64,
    /// Buffers that arrived incomplete (lost packets), not used.
    pub incomplete_buffers: u64,
    /// Frames refused for their time (PTP not synchronised, a time far from the host's clock).
    pub frames_refused_time: u64,
    /// Frames taken before `host_fit`'s clock fit settled (its first three seconds after a
    /// connection), not used: their time is not known well enough.
    pub frames_before_clock_fit: u64,
    /// Frames ingest refused or failed on.
    pub frames_failed: u64,
    /// Connections made again after a loss.
    pub reconnects: u64,
    /// Median delay from the middle of the exposure to the result committed, over the newest
    /// 1000 frames (ms).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub delay_median_ms: Option<f64>,
    /// Its 99th percentile (ms).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub delay_p99_ms: Option<f64>,
    /// The last error.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_error: Option<String>,
    /// When it happened (RFC 3339).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_error_at: Option<String>,
}

/// A device clock's fit to the host's clock.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct ClockFitOut {
    /// Host minus device clock (ms).
    pub offset_ms: f64,
    /// How much faster the host's clock runs (ppm).
    pub drift_ppm: f64,
    /// RMS of the pairs about the fitted line (µs).
    pub residual_rms_us: f64,
    /// Pairs in the fit.
    pub pairs: usize,
    /// Latched pairs (`true`) or the frames' arrivals.
    pub latched: bool,
}

impl From<SourceReport> for SourceOut {
    fn from(r: SourceReport) -> Self {
        let d = r.detail;
        SourceOut {
            address: r.address,
            status: d.status,
            connected: d.status == SourceStatus::Streaming,
            device: d.device,
            trigger: r.trigger,
            timestamp: r.timestamp,
            exposure_us: d.exposure_us,
            ptp_status: d.ptp_status,
            clock_fit: d.clock_fit.map(|f| ClockFitOut {
                offset_ms: f.offset_ns / 1e6,
                drift_ppm: f.drift_ppm,
                residual_rms_us: f.residual_rms_ns / 1e3,
                pairs: f.pairs,
                latched: f.latched,
            }),
            frames_received: r.received,
            frames_ingested: r.ingested,
            frames_dropped: r.dropped,
            incomplete_buffers: r.incomplete,
            frames_refused_time: r.refused_time,
            frames_before_clock_fit: r.settling,
            frames_failed: r.failed,
            reconnects: r.reconnects,
            delay_median_ms: r.delay_s.map(|d| d.0 * 1e3),
            delay_p99_ms: r.delay_s.map(|d| d.1 * 1e3),
            last_error_at: d.last_error.as_ref().map(|e| format_ns(e.1)),
            last_error: d.last_error.map(|e| e.0),
        }
    }
}
