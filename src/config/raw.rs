//! The file as written: serde types mirroring the TOML, before validation.
//!
//! Every table denies unknown keys, so a misspelt key is an error that names its line.

use serde::Deserialize;
use toml::Spanned;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawFile {
    #[serde(default)]
    pub server: RawServer,
    #[serde(default)]
    pub rerun: RawRerun,
    #[serde(default)]
    pub cameras: Vec<Spanned<RawCamera>>,
    #[serde(default)]
    pub markers: Vec<Spanned<RawMarker>>,
    #[serde(default)]
    pub links: Vec<Spanned<RawLink>>,
    #[serde(default)]
    pub targets: Vec<Spanned<RawTarget>>,
    #[serde(default)]
    pub auth: RawAuth,
    #[serde(default)]
    pub notify: RawNotify,
    #[serde(default)]
    pub outputs: RawOutputs,
    pub filter: Option<Spanned<RawFilter>>,
    pub retention: Option<Spanned<RawRetention>>,
    pub reports: Option<Spanned<RawReports>>,
    pub acceptance: Option<Spanned<RawAcceptance>>,
    pub pnp: Option<Spanned<RawPnp>>,
    pub frames: Option<Spanned<RawFrames>>,
    pub site: Option<Spanned<RawSite>>,
    pub upstream: Option<Spanned<RawUpstream>>,
    pub central: Option<Spanned<RawCentral>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSite {
    pub name: String,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawUpstream {
    pub url: String,
    pub token: Option<String>,
    pub token_file: Option<String>,
    pub raw_kbit_s: Option<f64>,
    pub batch_rows: Option<usize>,
    pub batch_mb: Option<f64>,
    pub heartbeat_s: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawCentral {
    pub enabled: bool,
    pub max_sync_mb: Option<f64>,
    pub raw_days: Option<f64>,
    pub results_days: Option<f64>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawFrames {
    pub archive_dir: Option<String>,
    pub archive_every_s: Option<f64>,
    pub archive_max_mb: Option<f64>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawPnp {
    pub max_reprojection_rms_px: Option<f64>,
    pub robust: Option<bool>,
    pub inlier_threshold_px: Option<f64>,
    pub lost_search_interval_s: Option<f64>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawRetention {
    pub samples_days: Option<f64>,
    pub results_days: Option<f64>,
    pub disk_budget_mb: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawReports {
    pub every_days: f64,
    pub folder: String,
    pub min_gap_s: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawAcceptance {
    pub reverify_every_days: Option<f64>,
    pub still_s: Option<f64>,
    pub settle_s: Option<f64>,
    pub step_s: Option<f64>,
    pub still_rms_arcsec: f64,
    pub still_rms_mm: f64,
    pub move_arcsec: f64,
    pub move_mm: f64,
    #[serde(default)]
    pub moves: Vec<Spanned<RawAcceptanceMove>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawAcceptanceMove {
    pub name: String,
    pub target: Option<String>,
    #[serde(default)]
    pub rotation_arcsec: [f64; 3],
    #[serde(default)]
    pub translation_mm: [f64; 3],
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawFilter {
    pub gate_probability: Option<f64>,
    pub reinit_after_outliers: Option<usize>,
    pub stale_after_periods: Option<f64>,
    pub consistency_probability: Option<f64>,
    pub group_tolerance_ms: Option<f64>,
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawRandomWalk {
    pub rotation_arcsec_per_sqrt_s: f64,
    pub translation_mm_per_sqrt_s: f64,
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawAcceleration {
    pub rotation_arcsec_per_s_sqrt_s: f64,
    pub translation_mm_per_s_sqrt_s: f64,
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawOscillation {
    pub period_s: f64,
    pub correlation_time_s: f64,
    pub rotation_arcsec: ScalarOr3,
    pub translation_mm: ScalarOr3,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawServer {
    pub listen: Option<Spanned<String>>,
    pub database: Option<Spanned<String>>,
    pub max_body_bytes: Option<Spanned<usize>>,
    pub max_batch_samples: Option<Spanned<usize>>,
    pub events_max_hz: Option<Spanned<f64>>,
    pub max_future_s: Option<Spanned<f64>>,
    pub clock_tolerance_s: Option<Spanned<f64>>,
    pub allowed_hosts: Option<Vec<String>>,
    pub max_connections: Option<Spanned<usize>>,
    pub max_connections_per_address: Option<Spanned<usize>>,
    pub header_timeout_s: Option<Spanned<f64>>,
    pub shutdown_grace_s: Option<Spanned<f64>>,
    pub max_heavy_reads: Option<Spanned<usize>>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawRerun {
    pub mode: Option<Spanned<RawModes>>,
    pub recordings_dir: Option<String>,
    pub url: Option<String>,
    pub serve_listen: Option<Spanned<String>>,
    pub serve_memory_limit_mb: Option<Spanned<f64>>,
    pub rotate_hours: Option<Spanned<f64>>,
    pub rotate_max_mb: Option<Spanned<f64>>,
    pub queue_capacity: Option<Spanned<i64>>,
    pub scene_hz: Option<Spanned<f64>>,
    pub series_hz: Option<Spanned<f64>>,
    pub image_hz: Option<Spanned<f64>>,
}

/// `mode = "save"` or `mode = ["save", "serve"]`.
#[derive(Debug, Deserialize)]
#[serde(untagged)]
pub(super) enum RawModes {
    One(String),
    Several(Vec<String>),
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawCamera {
    pub frame: String,
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    /// OpenCV's coefficients: 4, 5, 8 or 12 of `k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4`.
    #[serde(default)]
    pub distortion: Vec<f64>,
    pub pixel_sigma: f64,
    pub gain_e_per_dn: Option<f64>,
    /// `n x n` numbers, row-major, in the order `fx fy cx cy` and the lens model's terms.
    pub intrinsics_covariance: Option<Vec<f64>>,
    /// The HTML page `calibrate-camera --report` wrote for this calibration.
    pub calibration_report: Option<String>,
    pub source: Option<Spanned<RawSource>>,
}

/// `[cameras.source]`: where the service takes the camera's frames from itself.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSource {
    pub address: String,
    pub pixel_format: Option<String>,
    pub trigger: Option<String>,
    pub trigger_group: Option<String>,
    pub trigger_line: Option<String>,
    pub rate_hz: Option<f64>,
    pub exposure_us: Option<f64>,
    pub gain_db: Option<f64>,
    pub timestamp: Option<String>,
    pub stamp_offset_us: Option<f64>,
    pub latency_us: Option<f64>,
    pub tai_offset_s: Option<f64>,
    pub tolerance_ms: Option<f64>,
    pub packet_size_bytes: Option<u32>,
    #[serde(default)]
    pub features: Vec<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawMarker {
    pub frame: String,
    pub points_mm: Vec<[f64; 3]>,
    pub ids: Option<Vec<u32>>,
    pub target: Option<RawDiscTarget>,
    pub normals: Option<Vec<[f64; 3]>>,
}

/// What a marker's points are: `{ kind = "disc", diameter_mm, polarity }`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawDiscTarget {
    pub kind: String,
    pub diameter_mm: f64,
    pub polarity: Option<String>,
}

/// A pose: translation and exactly one rotation form.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawPose {
    pub t_mm: [f64; 3],
    pub q_wxyz: Option<[f64; 4]>,
    pub euler_deg: Option<[f64; 3]>,
    pub r: Option<[[f64; 3]; 3]>,
}

/// A scalar applied to all three axes, or one value per axis.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(untagged)]
pub(super) enum ScalarOr3 {
    Scalar(f64),
    PerAxis([f64; 3]),
}

impl ScalarOr3 {
    pub(super) fn per_axis(self) -> [f64; 3] {
        match self {
            ScalarOr3::Scalar(v) => [v; 3],
            ScalarOr3::PerAxis(v) => v,
        }
    }
}

#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSigma {
    pub rotation_arcsec: ScalarOr3,
    pub translation_mm: ScalarOr3,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawLink {
    pub name: String,
    pub kind: String,
    pub parent: Option<String>,
    pub child: Option<String>,
    pub pose: Option<RawPose>,
    pub sigma: Option<RawSigma>,
    pub model: Option<String>,
    pub expected_rate_hz: Option<f64>,
    pub nominal: Option<RawPose>,
    pub random_walk: Option<RawRandomWalk>,
    pub acceleration_noise: Option<RawAcceleration>,
    pub oscillation: Option<RawOscillation>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawTarget {
    pub name: String,
    pub base: String,
    #[serde(default)]
    pub alarms: RawAlarms,
    pub filter: Option<RawTargetFilter>,
}

/// `[targets.filter]`: the target filter's model and tuning instead of its links'.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawTargetFilter {
    pub model: Option<String>,
    pub fit_from_data: Option<bool>,
    pub random_walk: Option<RawRandomWalk>,
    pub acceleration_noise: Option<RawAcceleration>,
    pub oscillation: Option<RawOscillation>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawAlarms {
    pub warn_rotation_arcsec: Option<f64>,
    pub alarm_rotation_arcsec: Option<f64>,
    pub warn_translation_mm: Option<f64>,
    pub alarm_translation_mm: Option<f64>,
    pub hysteresis: Option<f64>,
    pub dwell_s: Option<f64>,
    pub rate_rotation_arcsec_per_s: Option<f64>,
    pub rate_translation_mm_per_s: Option<f64>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawAuth {
    #[serde(default)]
    pub tokens: Vec<Spanned<RawToken>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawToken {
    pub name: String,
    pub sha256: String,
    pub scopes: Vec<String>,
    pub site: Option<String>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawNotify {
    #[serde(default)]
    pub webhooks: Vec<Spanned<RawWebhook>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawWebhook {
    pub url: String,
    pub secret: String,
    pub min_level: Option<String>,
    pub timeout_s: Option<f64>,
    pub max_attempts: Option<u32>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawOutputs {
    #[serde(default)]
    pub mqtt: Vec<Spanned<RawMqtt>>,
    #[serde(default)]
    pub modbus: Vec<Spanned<RawModbus>>,
    #[serde(default)]
    pub nmea: Vec<Spanned<RawNmea>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawMqtt {
    pub url: String,
    pub client_id: Option<String>,
    pub topic_prefix: Option<String>,
    pub qos: Option<u8>,
    pub rate_hz: Option<f64>,
    pub username: Option<String>,
    pub password: Option<String>,
    pub ca_file: Option<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawModbus {
    pub listen: String,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawNmea {
    pub to: String,
    pub talker: Option<String>,
    pub rate_hz: Option<f64>,
    pub allow_broadcast: Option<bool>,
}
