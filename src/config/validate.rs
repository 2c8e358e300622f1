//! Validation of the installation file: every problem found, each with its line.
//!
//! [`Validator`] walks the raw file ([`super::raw`]) section by section, turning each into its
//! domain type (the core's [`crate::model`] types, or the deployment settings of
//! [`super`]) and collecting a [`ConfigProblem`] for everything wrong, so that one run of
//! `check-config` lists them all.

use super::error::LineIndex;
use super::raw::{self, RawFile, RawPose, RawSigma};
use super::{
    AuthSettings, CameraAddress, CameraSource, CentralSettings, ConfigProblem, FeatureSetting,
    FleetSettings, FrameSettings, Installation, NotifyLevel, NotifySettings, PixelFormat,
    RerunMode, RerunSettings, RetentionSettings, Scope, ServerSettings, SiteName, TimestampMode,
    TokenSpec, TriggerMode, UpstreamSettings, WebhookSpec,
};
use crate::alarms::AlarmThresholds;
use crate::chain::{ChainError, Topology};
use crate::filter::{BankSettings, FilterTuning, MotionModel};
use crate::geometry::{
    Pose, PoseCov, ReportedSigmas, Rotation, pose_from_parts, rotation_from_euler,
    rotation_from_matrix, rotation_from_quaternion_wxyz, validate_finite,
};
use crate::model::{
    Camera, DiscTarget, LinkKind, LinkSpec, Marker, MeasuredLink, Model, PnpSettings, TargetSpec,
};
use crate::vision::{CameraModel, Polarity};
use std::net::SocketAddr;
use toml::Spanned;

/// The longest duration the file may give (seconds; a leap year). Durations become timers, and
/// a timer of 1e20 s overflows in the task that sets it.
const MAX_DURATION_S: f64 = 366.0 * 86_400.0;
use std::path::PathBuf;
use std::sync::Arc;

/// A disc imaging under this many pixels across is warned of.
const MIN_TARGET_PX: f64 = 4.0;

/// Splits `<parent>_from_<child>` into its frames.
fn split_link_name(name: &str) -> Option<(&str, &str)> {
    let mut parts = name.split("_from_");
    match (parts.next(), parts.next(), parts.next()) {
        (Some(parent), Some(child), None) if !parent.is_empty() && !child.is_empty() => {
            Some((parent, child))
        }
        _ => None,
    }
}

/// True for a frame name made of letters, digits, `-` and `_`.
fn is_valid_frame_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 64
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        && !name.contains("_from_")
}

pub(super) struct Validator {
    pub(super) lines: LineIndex,
    pub(super) problems: Vec<ConfigProblem>,
    /// What is valid but probably not meant (`check-config` prints them, `serve` logs them).
    pub(super) warnings: Vec<ConfigProblem>,
    /// Where each marker is declared, for warnings about it.
    pub(super) marker_at: std::collections::HashMap<String, usize>,
}

impl Validator {
    pub(super) fn problem(&mut self, offset: usize, message: String) {
        let (line, _) = self.lines.locate(offset);
        self.problems.push(ConfigProblem {
            line: Some(line),
            column: None,
            message,
        });
    }

    /// Something valid but probably not meant, at `offset`'s line.
    pub(super) fn warning(&mut self, offset: usize, message: String) {
        let (line, _) = self.lines.locate(offset);
        self.warnings.push(ConfigProblem {
            line: Some(line),
            column: None,
            message,
        });
    }

    fn finite(&mut self, at: usize, what: &str, values: &[f64]) -> bool {
        match validate_finite(what, values) {
            Ok(()) => true,
            Err(e) => {
                self.problem(at, e.to_string());
                false
            }
        }
    }

    fn positive(&mut self, at: usize, what: &str, value: f64) -> bool {
        if value.is_finite() && value > 0.0 {
            true
        } else {
            self.problem(at, format!("{what} must be a positive number, not {value}"));
            false
        }
    }

    /// True when `value` is positive and at most `max`, the plausible limit of what it
    /// measures (the same the API holds posted sigmas to): a sigma or a filter's noise beyond
    /// it would make every result of the targets it reaches huge or not finite.
    fn plausible(&mut self, at: usize, what: &str, value: f64, max: f64) -> bool {
        if !self.positive(at, what, value) {
            return false;
        }
        if value > max {
            self.problem(
                at,
                format!("{what} is {value:e}, beyond the plausible limit of {max:e}"),
            );
            return false;
        }
        true
    }

    /// A rotation's sigma or noise strength (arc-seconds, per second or root second).
    fn plausible_rotation(&mut self, at: usize, what: &str, value: f64) -> bool {
        self.plausible(at, what, value, crate::geometry::MAX_ROTATION_SIGMA_ARCSEC)
    }

    /// A translation's sigma or noise strength (mm, per second or root second).
    fn plausible_translation(&mut self, at: usize, what: &str, value: f64) -> bool {
        self.plausible(at, what, value, crate::geometry::MAX_TRANSLATION_SIGMA_MM)
    }

    /// True when `value` lies in `[lo, hi]`; otherwise says so at `at`. Every number that sizes
    /// memory or a duration is bounded this way: a value far outside what makes sense would
    /// overflow the task that uses it, long after the service started.
    pub(super) fn within(&mut self, at: usize, what: &str, value: f64, lo: f64, hi: f64) -> bool {
        if value.is_finite() && (lo..=hi).contains(&value) {
            true
        } else {
            self.problem(at, format!("{what} must lie in [{lo}, {hi}], not {value}"));
            false
        }
    }

    fn pose(&mut self, at: usize, what: &str, raw: &RawPose) -> Option<Pose> {
        let forms = [
            raw.q_wxyz.is_some(),
            raw.euler_deg.is_some(),
            raw.r.is_some(),
        ]
        .iter()
        .filter(|&&b| b)
        .count();
        if forms != 1 {
            self.problem(
                at,
                format!(
                    "{what} needs exactly one rotation: `q_wxyz`, `euler_deg` or `r` (found {forms})"
                ),
            );
            return None;
        }
        let rotation: Result<Rotation, _> = if let Some(q) = raw.q_wxyz {
            rotation_from_quaternion_wxyz(q)
        } else if let Some(e) = raw.euler_deg {
            rotation_from_euler(e.map(f64::to_radians))
        } else if let Some(r) = raw.r {
            rotation_from_matrix(r)
        } else {
            return None;
        };
        match rotation.and_then(|r| pose_from_parts(raw.t_mm, r)) {
            Ok(p) => Some(p),
            Err(e) => {
                self.problem(at, format!("{what}: {e}"));
                None
            }
        }
    }

    fn sigmas(&mut self, at: usize, what: &str, raw: &RawSigma) -> Option<ReportedSigmas> {
        let rotation_arcsec = raw.rotation_arcsec.per_axis();
        let translation_mm = raw.translation_mm.per_axis();
        let mut ok = true;
        for v in rotation_arcsec {
            ok &= self.plausible_rotation(at, &format!("{what}.rotation_arcsec"), v);
        }
        for v in translation_mm {
            ok &= self.plausible_translation(at, &format!("{what}.translation_mm"), v);
        }
        ok.then_some(ReportedSigmas {
            rotation_arcsec,
            translation_mm,
        })
    }

    pub(super) fn installation(&mut self, source: &str, raw: RawFile) -> Option<Installation> {
        let server = self.server(&raw);
        let rerun = self.rerun(&raw);
        let cameras = self.cameras(&raw);
        let markers = self.markers(&raw);
        let (topology, links) = self.links(&raw);
        let targets = self.targets(&raw, &topology);
        let auth = self.auth(&raw);
        let notify = self.notify(&raw);
        let outputs = self.outputs(&raw);
        let filter = self.bank_settings(&raw);
        let retention = self.retention(&raw, server.as_ref());
        let frames = self.frames(&raw);
        let pnp = self.pnp(&raw);
        let fleet = self.fleet(&raw, server.as_ref());
        let sources = self.sources(&raw);
        let mut frames_seen = std::collections::HashSet::new();
        for c in &raw.cameras {
            if !frames_seen.insert(c.get_ref().frame.clone()) {
                self.problem(
                    c.span().start,
                    format!("duplicate camera on frame `{}`", c.get_ref().frame),
                );
            }
        }
        for m in &raw.markers {
            if !frames_seen.insert(m.get_ref().frame.clone()) {
                self.problem(
                    m.span().start,
                    format!(
                        "frame `{}` already has a camera or marker; a frame is one rigid body's, a station joins two with a calibrated link",
                        m.get_ref().frame
                    ),
                );
            }
        }
        let model = Model {
            cameras,
            markers,
            topology,
            links,
            targets,
            filter: filter?,
            pnp: pnp?,
        };
        self.small_targets(&model);
        Some(Installation {
            source: source.to_owned(),
            server: server?,
            rerun: rerun?,
            model: Arc::new(model),
            auth,
            notify,
            outputs,
            retention: retention?,
            frames: frames?,
            fleet: fleet?,
            sources: sources?,
            warnings: std::mem::take(&mut self.warnings),
        })
    }

    /// Warns of disc targets that image under [`MIN_TARGET_PX`] across at a measured link's
    /// nominal pose: too small to find reliably.
    fn small_targets(&mut self, model: &Model) {
        for spec in &model.links {
            let LinkKind::Measured(m) = &spec.kind else {
                continue;
            };
            let Some(nominal) = m.nominal else { continue };
            let link = model.topology.link(spec.id);
            let (parent, child) = (
                model.topology.frame_name(link.parent),
                model.topology.frame_name(link.child),
            );
            let (Some(camera), Some(marker)) = (model.camera(parent), model.marker(child)) else {
                continue;
            };
            let Some(target) = marker.target else {
                continue;
            };
            let smallest = marker
                .points_mm
                .iter()
                .map(|p| {
                    let z = (nominal * nalgebra::Point3::from(*p)).z;
                    camera.intrinsics.fx_px.min(camera.intrinsics.fy_px) * target.diameter_mm / z
                })
                .fold(f64::INFINITY, f64::min);
            if smallest < MIN_TARGET_PX {
                let at = self.marker_at.get(child).copied().unwrap_or(0);
                self.warning(at, format!(
                        "marker `{child}`: its {} mm discs image {smallest:.1} px across in camera `{parent}` at the nominal pose of `{}`, under {MIN_TARGET_PX} px: too small to find reliably",
                        target.diameter_mm, spec.name
                    ));
            }
        }
    }

    fn pnp(&mut self, raw: &RawFile) -> Option<PnpSettings> {
        let empty = raw::RawPnp::default();
        let (at, r) = match &raw.pnp {
            Some(s) => (s.span().start, s.get_ref()),
            None => (0, &empty),
        };
        let max_reprojection_rms_px = r.max_reprojection_rms_px.unwrap_or(1.0);
        let inlier_threshold_px = r.inlier_threshold_px.unwrap_or(2.0);
        let ok = self.positive(at, "pnp.max_reprojection_rms_px", max_reprojection_rms_px)
            & self.positive(at, "pnp.inlier_threshold_px", inlier_threshold_px);
        ok.then_some(PnpSettings {
            max_reprojection_rms_px,
            robust: r.robust.unwrap_or(false),
            inlier_threshold_px,
        })
    }

    fn retention(
        &mut self,
        raw: &RawFile,
        server: Option<&ServerSettings>,
    ) -> Option<RetentionSettings> {
        let empty = raw::RawRetention::default();
        let (at, r) = match &raw.retention {
            Some(s) => (s.span().start, s.get_ref()),
            None => (0, &empty),
        };
        let samples_days = r.samples_days.unwrap_or(90.0);
        let results_days = r.results_days.unwrap_or(90.0);
        let mut ok = self.positive(at, "retention.samples_days", samples_days)
            & self.positive(at, "retention.results_days", results_days);
        let disk_budget_bytes = match r.disk_budget_mb {
            None => None,
            Some(mb) => {
                ok &= self.positive(at, "retention.disk_budget_mb", mb);
                if server.is_some_and(|s| s.database.sqlite_path().is_none()) {
                    self.problem(
                        at,
                        "retention.disk_budget_mb applies to an SQLite file; a PostgreSQL \
                         server's disk is its own administrator's business"
                            .into(),
                    );
                    ok = false;
                }
                Some((mb * 1e6) as u64)
            }
        };
        ok.then_some(RetentionSettings {
            samples_days,
            results_days,
            disk_budget_bytes,
        })
    }

    /// `[site]`, `[upstream]` and `[central]`: a site that pushes names itself and uses an
    /// SQLite file (its outbox); a centre runs on PostgreSQL.
    fn fleet(&mut self, raw: &RawFile, server: Option<&ServerSettings>) -> Option<FleetSettings> {
        let mut ok = true;
        let site = match &raw.site {
            None => None,
            Some(s) => {
                let name = &s.get_ref().name;
                let parsed = SiteName::parse(name);
                if parsed.is_none() {
                    self.problem(
                        s.span().start,
                        format!(
                            "site.name `{name}` is not a site name: 1 to {} lowercase letters, digits, `-` or `_`, starting with a letter or digit",
                            SiteName::MAX_LEN
                        ),
                    );
                    ok = false;
                }
                parsed
            }
        };
        let upstream = match &raw.upstream {
            None => None,
            Some(s) => {
                let at = s.span().start;
                let u = s.get_ref();
                if raw.site.is_none() {
                    self.problem(
                        at,
                        "[upstream] needs the site's name: add `[site] name = \"...\"`".into(),
                    );
                    ok = false;
                }
                if server.is_some_and(|s| s.database.sqlite_path().is_none()) {
                    self.problem(
                        at,
                        "[upstream] needs an SQLite database (server.database): the site's file is its outbox".into(),
                    );
                    ok = false;
                }
                let url = match url::Url::parse(&u.url) {
                    Ok(url) if matches!(url.scheme(), "http" | "https") && url.has_host() => {
                        Some(url)
                    }
                    _ => {
                        self.problem(
                            at,
                            format!("upstream.url `{}` is not an http:// or https:// URL", u.url),
                        );
                        None
                    }
                };
                let token = match (&u.token, &u.token_file) {
                    (Some(_), Some(_)) => {
                        self.problem(at, "upstream: give token or token_file, not both".into());
                        ok = false;
                        None
                    }
                    (Some(t), None) if t.trim().is_empty() => {
                        self.problem(at, "upstream.token is empty".into());
                        ok = false;
                        None
                    }
                    (Some(t), None) => Some(t.trim().to_owned()),
                    (None, Some(f)) => match std::fs::read_to_string(f) {
                        Ok(t) if !t.trim().is_empty() => Some(t.trim().to_owned()),
                        Ok(_) => {
                            self.problem(at, format!("upstream.token_file `{f}` is empty"));
                            ok = false;
                            None
                        }
                        Err(e) => {
                            self.problem(
                                at,
                                format!("upstream.token_file `{f}` cannot be read: {e}"),
                            );
                            ok = false;
                            None
                        }
                    },
                    (None, None) => None,
                };
                let raw_kbit_s = u.raw_kbit_s.unwrap_or(0.0);
                if raw_kbit_s != 0.0 {
                    // The wait after a batch is its bits over this: a tiny budget would make a
                    // wait of centuries (and an uploader that dies computing it).
                    ok &= self.within(at, "upstream.raw_kbit_s (or 0)", raw_kbit_s, 0.01, 1e7);
                }
                let heartbeat_s = u.heartbeat_s.unwrap_or(10.0);
                ok &= self.duration(at, "upstream.heartbeat_s", heartbeat_s, 0.05, 86_400.0);
                let batch_rows = u.batch_rows.unwrap_or(20_000);
                // A batch is read into memory whole: a million rows is gigabytes.
                ok &= self.within(at, "upstream.batch_rows", batch_rows as f64, 1.0, 1e6);
                let batch_mb = u.batch_mb.unwrap_or(0.25);
                ok &= self.within(at, "upstream.batch_mb", batch_mb, 0.01, 1024.0);
                url.map(|url| UpstreamSettings {
                    url,
                    token,
                    raw_kbit_s,
                    batch_rows,
                    batch_bytes: (batch_mb * 1e6) as usize,
                    heartbeat_s,
                })
            }
        };
        let central = match &raw.central {
            Some(s) if s.get_ref().enabled => {
                let at = s.span().start;
                if server.is_some_and(|s| s.database.sqlite_path().is_some()) {
                    self.problem(
                        at,
                        "[central] needs a PostgreSQL database (server.database = \"postgres://...\")".into(),
                    );
                    ok = false;
                }
                let max_sync_mb = s.get_ref().max_sync_mb.unwrap_or(128.0);
                ok &= self.within(at, "central.max_sync_mb", max_sync_mb, 1.0, 4096.0);
                let raw_days = s.get_ref().raw_days.unwrap_or(30.0);
                let results_days = s.get_ref().results_days.unwrap_or(365.0);
                ok &= self.positive(at, "central.raw_days", raw_days);
                ok &= self.positive(at, "central.results_days", results_days);
                if raw_days > results_days {
                    self.problem(
                        at,
                        format!(
                            "central.raw_days ({raw_days}) is longer than central.results_days \
                             ({results_days}): raw results share the results' daily partitions, \
                             which go at results_days"
                        ),
                    );
                    ok = false;
                }
                Some(CentralSettings {
                    max_sync_bytes: (max_sync_mb * 1e6) as usize,
                    raw_days,
                    results_days,
                })
            }
            _ => None,
        };
        (ok && (raw.upstream.is_none() || upstream.is_some())).then_some(FleetSettings {
            site,
            upstream,
            central,
        })
    }

    fn frames(&mut self, raw: &RawFile) -> Option<FrameSettings> {
        let empty = raw::RawFrames::default();
        let (at, f) = match &raw.frames {
            Some(s) => (s.span().start, s.get_ref()),
            None => (0, &empty),
        };
        let archive_every_s = f.archive_every_s.unwrap_or(60.0);
        let archive_max_mb = f.archive_max_mb.unwrap_or(1024.0);
        let mut ok = self.duration(at, "frames.archive_every_s", archive_every_s, 0.001, 31e6)
            & self.within(at, "frames.archive_max_mb", archive_max_mb, 0.001, 1e9);
        if f.archive_dir.as_deref() == Some("") {
            self.problem(
                at,
                "frames.archive_dir is empty: leave it out to keep no archive".to_owned(),
            );
            ok = false;
        }
        ok.then(|| FrameSettings {
            archive_dir: f.archive_dir.as_ref().map(PathBuf::from),
            archive_every_s,
            archive_max_mb,
        })
    }

    fn probability(
        &mut self,
        at: usize,
        what: &str,
        value: Option<f64>,
        default: f64,
    ) -> Option<f64> {
        match value {
            None => Some(default),
            Some(p) if p > 0.5 && p < 1.0 => Some(p),
            Some(p) => {
                self.problem(
                    at,
                    format!("{what} must be a probability between 0.5 and 1 (exclusive), not {p}"),
                );
                None
            }
        }
    }

    /// The `[filter]` section.
    fn bank_settings(&mut self, raw: &RawFile) -> Option<BankSettings> {
        let empty = raw::RawFilter::default();
        let (at, f) = match &raw.filter {
            Some(s) => (s.span().start, s.get_ref()),
            None => (0, &empty),
        };
        let defaults = BankSettings::default();
        let consistency = self.probability(
            at,
            "filter.consistency_probability",
            f.consistency_probability,
            defaults.consistency_probability,
        );
        let gate = self.probability(at, "filter.gate_probability", f.gate_probability, 0.999);
        let stale = f
            .stale_after_periods
            .unwrap_or(defaults.stale_after_periods);
        let stale_ok = self.positive(at, "filter.stale_after_periods", stale);
        if f.reinit_after_outliers == Some(0) {
            self.problem(at, "filter.reinit_after_outliers must be at least 1".into());
        }
        let tolerance_ok = match f.group_tolerance_ms {
            Some(ms) if !(0.0..=10_000.0).contains(&ms) => {
                self.problem(
                    at,
                    format!("filter.group_tolerance_ms must be from 0 to 10000 (got {ms})"),
                );
                false
            }
            _ => true,
        };
        gate?;
        (stale_ok && tolerance_ok && f.reinit_after_outliers != Some(0)).then_some(BankSettings {
            stale_after_periods: stale,
            consistency_probability: consistency?,
            group_tolerance_ns: f.group_tolerance_ms.map(|ms| (ms * 1e6).round() as i64),
            ..defaults
        })
    }

    /// `server.database`: a `postgres://` URL, or else an SQLite file path.
    fn database(&mut self, raw: Option<&toml::Spanned<String>>) -> Option<crate::config::Database> {
        use crate::config::{Database, PostgresUrl};
        let Some(s) = raw else {
            return Some(Database::Sqlite(PathBuf::from("brokenray.db")));
        };
        let text = s.get_ref().trim();
        if text.starts_with("postgres:") || text.starts_with("postgresql:") {
            match PostgresUrl::parse(text) {
                Some(url) if url.database_name().is_some() => Some(Database::Postgres(url)),
                Some(_) => {
                    self.problem(
                        s.span().start,
                        "server.database: the PostgreSQL URL names no database; write it like \
                         postgres://user:password@127.0.0.1:5432/brokenray"
                            .into(),
                    );
                    None
                }
                None => {
                    self.problem(
                        s.span().start,
                        "server.database is not a valid PostgreSQL URL; write it like \
                         postgres://user:password@127.0.0.1:5432/brokenray"
                            .into(),
                    );
                    None
                }
            }
        } else if text.is_empty() {
            self.problem(
                s.span().start,
                "server.database is empty: give an SQLite file or a postgres:// URL".into(),
            );
            None
        } else {
            Some(Database::Sqlite(PathBuf::from(text)))
        }
    }

    fn server(&mut self, raw: &RawFile) -> Option<ServerSettings> {
        let listen = match &raw.server.listen {
            None => SocketAddr::from(([127, 0, 0, 1], 7878)),
            Some(s) => match s.get_ref().parse() {
                Ok(a) => a,
                Err(_) => {
                    self.problem(
                        s.span().start,
                        format!(
                            "server.listen `{}` is not an address like 127.0.0.1:7878",
                            s.get_ref()
                        ),
                    );
                    return None;
                }
            },
        };
        let r = &raw.server;
        Some(ServerSettings {
            listen,
            database: self.database(r.database.as_ref())?,
            max_body_bytes: self.count(
                "server.max_body_bytes",
                r.max_body_bytes.as_ref(),
                32 * 1024 * 1024,
                1024,
                1 << 34,
            )?,
            max_batch_samples: self.count(
                "server.max_batch_samples",
                r.max_batch_samples.as_ref(),
                100_000,
                1,
                100_000_000,
            )?,
            events_max_hz: match &r.events_max_hz {
                None => 10.0,
                Some(hz) => {
                    let (at, hz) = (hz.span().start, *hz.get_ref());
                    if !self.within(at, "server.events_max_hz", hz, 0.001, 1000.0) {
                        return None;
                    }
                    hz
                }
            },
            max_future_s: self.seconds(
                "server.max_future_s",
                r.max_future_s.as_ref(),
                5.0,
                0.0,
                MAX_DURATION_S,
            )?,
            clock_tolerance_s: self.seconds(
                "server.clock_tolerance_s",
                r.clock_tolerance_s.as_ref(),
                2.0,
                0.0,
                MAX_DURATION_S,
            )?,
            allowed_hosts: r.allowed_hosts.clone().unwrap_or_default(),
            max_connections: match &r.max_connections {
                None => None,
                n => Some(self.count("server.max_connections", n.as_ref(), 0, 16, 1_000_000)?),
            },
            max_connections_per_address: match &r.max_connections_per_address {
                None => None,
                n => Some(self.count(
                    "server.max_connections_per_address",
                    n.as_ref(),
                    0,
                    1,
                    1_000_000,
                )?),
            },
            header_timeout_s: self.seconds(
                "server.header_timeout_s",
                r.header_timeout_s.as_ref(),
                10.0,
                0.0,
                1e6,
            )?,
            shutdown_grace_s: self.seconds(
                "server.shutdown_grace_s",
                r.shutdown_grace_s.as_ref(),
                10.0,
                0.0,
                1e6,
            )?,
            max_heavy_reads: self.count(
                "server.max_heavy_reads",
                r.max_heavy_reads.as_ref(),
                2,
                1,
                1024,
            )?,
        })
    }

    /// A whole number with a default, refused (not clamped) outside `[lo, hi]`, at its line.
    fn count(
        &mut self,
        key: &str,
        value: Option<&Spanned<usize>>,
        default: usize,
        lo: usize,
        hi: usize,
    ) -> Option<usize> {
        let Some(value) = value else {
            return Some(default);
        };
        let n = *value.get_ref();
        if (lo..=hi).contains(&n) {
            Some(n)
        } else {
            self.problem(
                value.span().start,
                format!("{key} must lie in [{lo}, {hi}], not {n}"),
            );
            None
        }
    }

    /// A duration in seconds with a default, refused outside `[lo_s, hi_s]` at its line. Every
    /// duration of the file goes through here or [`Validator::duration`]: one bounded beyond
    /// [`MAX_DURATION_S`] would overflow the timer that uses it, long after the start.
    fn seconds(
        &mut self,
        key: &str,
        value: Option<&Spanned<f64>>,
        default: f64,
        lo_s: f64,
        hi_s: f64,
    ) -> Option<f64> {
        let Some(value) = value else {
            return Some(default);
        };
        let s = *value.get_ref();
        self.duration(value.span().start, key, s, lo_s, hi_s)
            .then_some(s)
    }

    /// True when `value_s` is a duration in `[lo_s, hi_s]` (`hi_s` at most
    /// [`MAX_DURATION_S`]); otherwise says so at `at`.
    fn duration(&mut self, at: usize, key: &str, value_s: f64, lo_s: f64, hi_s: f64) -> bool {
        debug_assert!(
            hi_s <= MAX_DURATION_S,
            "{key}: a bound past the longest duration"
        );
        if value_s.is_finite() && (lo_s..=hi_s.min(MAX_DURATION_S)).contains(&value_s) {
            true
        } else {
            self.problem(
                at,
                format!("{key} must lie in [{lo_s}, {hi_s}] seconds, not {value_s}"),
            );
            false
        }
    }

    fn rerun(&mut self, raw: &RawFile) -> Option<RerunSettings> {
        let r = &raw.rerun;
        let (mut save, mut connect, mut serve) = (false, false, false);
        let mut ok = true;
        if let Some(m) = &r.mode {
            let names: Vec<&str> = match m.get_ref() {
                raw::RawModes::One(s) => vec![s.as_str()],
                raw::RawModes::Several(v) => v.iter().map(String::as_str).collect(),
            };
            for name in &names {
                match RerunMode::parse(name) {
                    Some(RerunMode::Off) if names.len() == 1 => {}
                    Some(RerunMode::Save) => save = true,
                    Some(RerunMode::Connect) => connect = true,
                    Some(RerunMode::Serve) => serve = true,
                    found => {
                        self.problem(
                            m.span().start,
                            if found == Some(RerunMode::Off) {
                                "rerun.mode `off` cannot be combined with other modes".to_owned()
                            } else {
                                format!(
                                    "rerun.mode `{name}` is not one of {}",
                                    RerunMode::WORDS.join(", ")
                                )
                            },
                        );
                        ok = false;
                    }
                }
            }
        }
        // Rates become periods and sizes byte counts: each bounded to what makes sense.
        let mut bounded =
            |v: &Option<toml::Spanned<f64>>, name: &str, default: f64, lo: f64, hi: f64| match v {
                None => Some(default),
                Some(x) => self
                    .within(
                        x.span().start,
                        &format!("rerun.{name}"),
                        *x.get_ref(),
                        lo,
                        hi,
                    )
                    .then_some(*x.get_ref()),
            };
        let memory_mb = bounded(
            &r.serve_memory_limit_mb,
            "serve_memory_limit_mb",
            256.0,
            1.0,
            1e6,
        );
        let rotate_hours = bounded(&r.rotate_hours, "rotate_hours", 24.0, 0.001, 87_600.0);
        let rotate_max_mb = bounded(&r.rotate_max_mb, "rotate_max_mb", 1024.0, 0.001, 1e7);
        let scene_hz = bounded(&r.scene_hz, "scene_hz", 2.0, 0.001, 1e6);
        let series_hz = bounded(&r.series_hz, "series_hz", 10.0, 0.001, 1e6);
        let image_hz = bounded(&r.image_hz, "image_hz", 1.0, 0.001, 1e6);
        let queue_capacity = match &r.queue_capacity {
            None => Some(4096),
            Some(q) if (1..=10_000_000).contains(q.get_ref()) => usize::try_from(*q.get_ref()).ok(),
            Some(q) => {
                self.problem(
                    q.span().start,
                    format!(
                        "rerun.queue_capacity must be between 1 and 10000000, not {}",
                        q.get_ref()
                    ),
                );
                None
            }
        };
        let serve_listen = match &r.serve_listen {
            None => Some(SocketAddr::from(([127, 0, 0, 1], 9876))),
            Some(a) => match a.get_ref().parse::<SocketAddr>() {
                Ok(addr) => Some(addr),
                Err(e) => {
                    self.problem(
                        a.span().start,
                        format!(
                            "rerun.serve_listen `{}` is not an address such as 127.0.0.1:9876: {e}",
                            a.get_ref()
                        ),
                    );
                    None
                }
            },
        };
        if !ok {
            return None;
        }
        Some(RerunSettings {
            save,
            connect,
            serve,
            recordings_dir: PathBuf::from(r.recordings_dir.as_deref().unwrap_or("recordings")),
            url: r
                .url
                .clone()
                .unwrap_or_else(|| "rerun+http://127.0.0.1:9876/proxy".to_owned()),
            serve_listen: serve_listen?,
            serve_memory_limit_bytes: (memory_mb? * 1e6) as u64,
            rotate_after_s: rotate_hours? * 3600.0,
            rotate_max_bytes: (rotate_max_mb? * 1e6) as u64,
            queue_capacity: queue_capacity?,
            scene_hz: scene_hz?,
            series_hz: series_hz?,
            image_hz: image_hz?,
        })
    }

    fn cameras(&mut self, raw: &RawFile) -> Vec<Camera> {
        let mut out = Vec::new();
        for spanned in &raw.cameras {
            let at = spanned.span().start;
            let c = spanned.get_ref();
            let what = format!("camera `{}`", c.frame);
            let mut ok = self.frame_name(at, &c.frame);
            if c.width == 0 || c.height == 0 {
                self.problem(at, format!("{what}: width and height must be positive"));
                ok = false;
            }
            ok &= self.positive(at, &format!("{what}: fx"), c.fx);
            ok &= self.positive(at, &format!("{what}: fy"), c.fy);
            ok &= self.finite(at, &format!("{what}: principal point"), &[c.cx, c.cy]);
            ok &= self.finite(at, &format!("{what}: distortion"), &c.distortion);
            ok &= self.positive(at, &format!("{what}: pixel_sigma"), c.pixel_sigma);
            if let Some(gain) = c.gain_e_per_dn {
                ok &= self.positive(at, &format!("{what}: gain_e_per_dn"), gain);
            }
            let intrinsics_covariance = match &c.intrinsics_covariance {
                Some(values) => match intrinsics_covariance(values) {
                    Ok(cov) => Some(cov),
                    Err(reason) => {
                        self.problem(at, format!("{what}: intrinsics_covariance {reason}"));
                        ok = false;
                        None
                    }
                },
                None => {
                    self.warning(at, format!(
                            "{what}: no intrinsics_covariance, so its calibration is taken as exact and no sigma includes its error (`brokenray calibrate-camera --out` writes it)"
                        ));
                    None
                }
            };
            if ok {
                out.push(Camera {
                    frame: c.frame.clone(),
                    intrinsics: CameraModel {
                        fx_px: c.fx,
                        fy_px: c.fy,
                        cx_px: c.cx,
                        cy_px: c.cy,
                        distortion: c.distortion,
                        width_px: c.width,
                        height_px: c.height,
                    },
                    pixel_sigma_px: c.pixel_sigma,
                    gain_e_per_dn: c.gain_e_per_dn,
                    intrinsics_covariance,
                });
            }
        }
        out
    }

    /// Every camera's `[cameras.source]`; `None` when one has a problem.
    fn sources(&mut self, raw: &RawFile) -> Option<Vec<CameraSource>> {
        let mut out = Vec::new();
        let mut ok = true;
        let mut addresses = std::collections::HashMap::new();
        for spanned in &raw.cameras {
            let c = spanned.get_ref();
            let Some(s) = &c.source else { continue };
            // Problems point at the source's own table.
            let at = s.span().start;
            match self.source(at, &c.frame, s.get_ref()) {
                Some(source) => {
                    if let Some(other) =
                        addresses.insert(source.address.to_string(), c.frame.clone())
                    {
                        self.problem(
                            at,
                            format!(
                                "camera `{}`: source.address `{}` is camera `{other}`'s already",
                                c.frame, source.address
                            ),
                        );
                        ok = false;
                    }
                    out.push(source);
                }
                None => ok = false,
            }
        }
        // The cameras of a trigger group share its rate and its trigger.
        for (i, a) in out.iter().enumerate() {
            if a.trigger == TriggerMode::FreeRun {
                continue;
            }
            if let Some(b) = out[..i]
                .iter()
                .find(|b| b.trigger != TriggerMode::FreeRun && b.trigger_group == a.trigger_group)
                && (b.trigger != a.trigger || b.rate_hz != a.rate_hz)
            {
                let at = raw
                    .cameras
                    .iter()
                    .find(|c| c.get_ref().frame == a.camera)
                    .and_then(|c| c.get_ref().source.as_ref())
                    .map_or(0, |s| s.span().start);
                self.problem(
                    at,
                    format!(
                        "camera `{}`: source.trigger_group `{}` has camera `{}` with trigger `{}` at {} Hz; a group's cameras share one trigger and one rate",
                        a.camera, a.trigger_group, b.camera, b.trigger, b.rate_hz
                    ),
                );
                ok = false;
            }
        }
        ok.then_some(out)
    }

    /// One camera's `[cameras.source]`.
    fn source(
        &mut self,
        at: usize,
        camera: &str,
        s: &super::raw::RawSource,
    ) -> Option<CameraSource> {
        let what = format!("camera `{camera}`: source");
        let mut ok = true;
        let address = CameraAddress::parse(&s.address)
            .map_err(|e| self.problem(at, format!("{what}.address {e}")))
            .ok();
        let pixel_format = self.word(
            at,
            &format!("{what}.pixel_format"),
            s.pixel_format.as_deref(),
            PixelFormat::Mono8,
        );
        let trigger = self.word(
            at,
            &format!("{what}.trigger"),
            s.trigger.as_deref(),
            TriggerMode::FreeRun,
        );
        let timestamp = self.word(
            at,
            &format!("{what}.timestamp"),
            s.timestamp.as_deref(),
            TimestampMode::HostFit,
        );
        let rate_hz = s.rate_hz.unwrap_or(10.0);
        ok &= self.within(at, &format!("{what}.rate_hz"), rate_hz, 0.01, 1000.0);
        if let Some(e) = s.exposure_us {
            ok &= self.within(at, &format!("{what}.exposure_us"), e, 1.0, 10e6);
            if e * 1e-6 >= 1.0 / rate_hz {
                self.problem(
                    at,
                    format!(
                        "{what}.exposure_us {e} does not fit in a frame period at rate_hz {rate_hz}"
                    ),
                );
                ok = false;
            }
        }
        if let Some(g) = s.gain_db {
            ok &= self.within(at, &format!("{what}.gain_db"), g, -20.0, 60.0);
        }
        if let Some(o) = s.stamp_offset_us {
            ok &= self.within(at, &format!("{what}.stamp_offset_us"), o, -10e6, 10e6);
        }
        if let Some(l) = s.latency_us {
            ok &= self.within(at, &format!("{what}.latency_us"), l, 0.0, 10e6);
        }
        let tai_offset_s = s.tai_offset_s.unwrap_or(37.0);
        ok &= self.within(at, &format!("{what}.tai_offset_s"), tai_offset_s, -1e9, 1e9);
        let tolerance_ms = s.tolerance_ms.unwrap_or(100.0);
        ok &= self.within(
            at,
            &format!("{what}.tolerance_ms"),
            tolerance_ms,
            0.1,
            60_000.0,
        );
        if let Some(p) = s.packet_size_bytes
            && !(576..=16_384).contains(&p)
        {
            self.problem(
                at,
                format!("{what}.packet_size_bytes {p} is outside 576 to 16384"),
            );
            ok = false;
        }
        let mut features = Vec::new();
        for f in &s.features {
            match FeatureSetting::parse(f) {
                Ok(f) => features.push(f),
                Err(e) => {
                    self.problem(at, format!("{what}.features {e}"));
                    ok = false;
                }
            }
        }
        let group = s
            .trigger_group
            .clone()
            .unwrap_or_else(|| "default".to_owned());
        if group.is_empty() || group.len() > 64 {
            self.problem(
                at,
                format!("{what}.trigger_group must be 1 to 64 characters"),
            );
            ok = false;
        }
        if trigger == Some(TriggerMode::Line) && s.trigger_line.is_none() {
            self.warning(
                at,
                format!("{what}: trigger `line` with no trigger_line: Line0 is taken"),
            );
        }
        if timestamp == Some(TimestampMode::Host) {
            self.warning(at, format!(
                    "{what}: timestamp `host` takes a frame's arrival minus latency_us as its time: the transfer's jitter (milliseconds) moves every result of a moving structure; `ptp` or `host_fit` do not"
                ));
        }
        Some(CameraSource {
            camera: camera.to_owned(),
            address: address?,
            pixel_format: pixel_format?,
            trigger: trigger?,
            trigger_group: group,
            trigger_line: s.trigger_line.clone().unwrap_or_else(|| "Line0".to_owned()),
            rate_hz,
            exposure_us: s.exposure_us,
            gain_db: s.gain_db,
            timestamp: timestamp?,
            stamp_offset_us: s.stamp_offset_us,
            latency_us: s.latency_us,
            tai_offset_s,
            tolerance_ms,
            packet_size_bytes: s.packet_size_bytes,
            features,
        })
        .filter(|_| ok)
    }

    /// A vocabulary's word, `default` when absent; a problem naming the key and the words
    /// otherwise.
    fn word<W: crate::words::Word>(
        &mut self,
        at: usize,
        what: &str,
        text: Option<&str>,
        default: W,
    ) -> Option<W> {
        let Some(text) = text else {
            return Some(default);
        };
        match W::ALL.iter().find(|w| w.word() == text) {
            Some(w) => Some(*w),
            None => {
                let words: Vec<String> = W::words().iter().map(|w| format!("`{w}`")).collect();
                self.problem(
                    at,
                    format!("{what} `{text}` is not one of {}", words.join(", ")),
                );
                None
            }
        }
    }

    fn markers(&mut self, raw: &RawFile) -> Vec<Marker> {
        let mut out = Vec::new();
        for spanned in &raw.markers {
            let at = spanned.span().start;
            let m = spanned.get_ref();
            let what = format!("marker `{}`", m.frame);
            let mut ok = self.frame_name(at, &m.frame);
            if m.points_mm.len() < 4 {
                self.problem(
                    at,
                    format!("{what} needs at least 4 points, has {}", m.points_mm.len()),
                );
                ok = false;
            }
            for (i, p) in m.points_mm.iter().enumerate() {
                ok &= self.finite(at, &format!("{what}: points_mm[{i}]"), p);
            }
            let ids = match &m.ids {
                Some(ids) if ids.len() != m.points_mm.len() => {
                    self.problem(
                        at,
                        format!(
                            "{what} has {} ids for {} points",
                            ids.len(),
                            m.points_mm.len()
                        ),
                    );
                    ok = false;
                    Vec::new()
                }
                Some(ids) => {
                    let unique: std::collections::HashSet<_> = ids.iter().collect();
                    if unique.len() != ids.len() {
                        self.problem(at, format!("{what} has duplicate point ids"));
                        ok = false;
                    }
                    ids.clone()
                }
                None => (0..m.points_mm.len() as u32).collect(),
            };
            let target = match &m.target {
                None => None,
                Some(t) => {
                    if t.kind != "disc" {
                        self.problem(
                            at,
                            format!("{what}: target kind `{}` is not known (`disc`)", t.kind),
                        );
                        ok = false;
                    }
                    ok &= self.positive(at, &format!("{what}: target.diameter_mm"), t.diameter_mm);
                    let polarity = match t.polarity.as_deref() {
                        None | Some("bright") => Polarity::Bright,
                        Some("dark") => Polarity::Dark,
                        Some(other) => {
                            self.problem(
                                at,
                                format!(
                                    "{what}: target polarity `{other}` is not `bright` or `dark`"
                                ),
                            );
                            ok = false;
                            Polarity::Bright
                        }
                    };
                    Some(DiscTarget {
                        diameter_mm: t.diameter_mm,
                        polarity,
                    })
                }
            };
            let normals = match &m.normals {
                None => vec![[0.0, 0.0, 1.0]; m.points_mm.len()],
                Some(normals) => {
                    if normals.len() != m.points_mm.len() {
                        self.problem(
                            at,
                            format!(
                                "{what} has {} normals for {} points",
                                normals.len(),
                                m.points_mm.len()
                            ),
                        );
                        ok = false;
                    }
                    normals
                        .iter()
                        .enumerate()
                        .map(|(i, n)| {
                            let norm = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                            if !(norm.is_finite() && norm > 1e-9) {
                                self.problem(
                                    at,
                                    format!(
                                        "{what}: normals[{i}] must be a finite, non-zero vector"
                                    ),
                                );
                                ok = false;
                                return [0.0, 0.0, 1.0];
                            }
                            [n[0] / norm, n[1] / norm, n[2] / norm]
                        })
                        .collect()
                }
            };
            if ok && let Some(target) = &target {
                let points: Vec<crate::geometry::Vec3> = m
                    .points_mm
                    .iter()
                    .map(|p| crate::geometry::Vec3::from(*p))
                    .collect();
                // Within a quarter of a disc's diameter a point is where another was: the
                // search with no prior cannot tell them apart.
                let tolerance_mm = 0.25 * target.diameter_mm;
                if let Some((k, onto)) = crate::model::layout_symmetries(&points, tolerance_mm)
                    .first()
                    .and_then(|map| map.iter().enumerate().find(|(k, m)| k != *m))
                {
                    self.warning(at, format!(
                            "{what}: its layout maps onto itself under a turn (point {k} onto point {onto}, within {tolerance_mm} mm): with no prediction it cannot be identified (it is tracked from its nominal pose); move a point off the symmetry"
                        ));
                }
            }
            if ok {
                self.marker_at.insert(m.frame.clone(), at);
                out.push(Marker {
                    frame: m.frame.clone(),
                    points_mm: m.points_mm.clone(),
                    ids,
                    target,
                    normals,
                });
            }
        }
        out
    }

    fn frame_name(&mut self, at: usize, name: &str) -> bool {
        if is_valid_frame_name(name) {
            true
        } else {
            self.problem(
                at,
                format!(
                    "frame name `{name}` must be 1 to 64 letters, digits, `-` or `_`, and must not contain `_from_`"
                ),
            );
            false
        }
    }

    fn links(&mut self, raw: &RawFile) -> (Topology, Vec<LinkSpec>) {
        let mut topology = Topology::new();
        // Frames of cameras and markers exist even when no link touches them.
        for c in &raw.cameras {
            if is_valid_frame_name(&c.get_ref().frame) {
                topology.add_frame(&c.get_ref().frame);
            }
        }
        for m in &raw.markers {
            if is_valid_frame_name(&m.get_ref().frame) {
                topology.add_frame(&m.get_ref().frame);
            }
        }
        let mut specs = Vec::new();
        let empty_filter = raw::RawFilter::default();
        for spanned in &raw.links {
            let at = spanned.span().start;
            let l = spanned.get_ref();
            let Some((parent, child)) = split_link_name(&l.name) else {
                self.problem(
                    at,
                    format!(
                        "link name `{}` is not of the form <parent>_from_<child>",
                        l.name
                    ),
                );
                continue;
            };
            let mut ok = self.frame_name(at, parent) & self.frame_name(at, child);
            for (key, given, expected) in
                [("parent", &l.parent, parent), ("child", &l.child, child)]
            {
                if let Some(given) = given
                    && given != expected
                {
                    self.problem(
                            at,
                            format!(
                                "link `{}` does not match its frames: its name says {key} `{expected}` but {key} = `{given}`",
                                l.name
                            ),
                        );
                    ok = false;
                }
            }
            let kind = match l.kind.as_str() {
                "calibrated" => self.calibrated(at, l),
                "measured" => self.measured(
                    at,
                    l,
                    raw.filter.as_ref().map_or(&empty_filter, |f| f.get_ref()),
                ),
                other => {
                    self.problem(
                        at,
                        format!(
                            "link `{}`: kind `{other}` is not one of calibrated, measured",
                            l.name
                        ),
                    );
                    None
                }
            };
            let (Some(kind), true) = (kind, ok) else {
                continue;
            };
            match topology.add_link(&l.name, parent, child) {
                Ok(id) => specs.push(LinkSpec {
                    id,
                    name: l.name.clone(),
                    kind,
                }),
                Err(e) => self.problem(at, e.to_string()),
            }
        }
        (topology, specs)
    }

    fn calibrated(&mut self, at: usize, l: &raw::RawLink) -> Option<LinkKind> {
        let what = format!("calibrated link `{}`", l.name);
        for (key, present) in [
            ("model", l.model.is_some()),
            ("expected_rate_hz", l.expected_rate_hz.is_some()),
            ("nominal", l.nominal.is_some()),
            ("random_walk", l.random_walk.is_some()),
            ("acceleration_noise", l.acceleration_noise.is_some()),
            ("oscillation", l.oscillation.is_some()),
        ] {
            if present {
                self.problem(
                    at,
                    format!("{what}: `{key}` applies to measured links only"),
                );
            }
        }
        let Some(raw_pose) = &l.pose else {
            self.problem(at, format!("{what} needs `pose`"));
            return None;
        };
        let Some(raw_sigma) = &l.sigma else {
            self.problem(
                at,
                format!("{what} needs `sigma` (its calibration uncertainty; a calibration is never exact)"),
            );
            return None;
        };
        let pose = self.pose(at, &format!("{what}: pose"), raw_pose)?;
        let sigmas = self.sigmas(at, &format!("{what}: sigma"), raw_sigma)?;
        Some(LinkKind::Calibrated {
            parent_from_child: PoseCov::from_reported_sigmas(pose, &sigmas),
        })
    }

    /// A motion model by its name.
    fn motion_model(&mut self, at: usize, what: &str, name: &str) -> Option<MotionModel> {
        let model = MotionModel::parse(name);
        if model.is_none() {
            self.problem(
                at,
                format!(
                    "{what}: model `{name}` is not one of static, constant_velocity, oscillatory"
                ),
            );
        }
        model
    }

    /// A target's `[targets.filter]`: its filter's model and tuning instead of its links'.
    fn target_filter(
        &mut self,
        at: usize,
        target: &str,
        f: &raw::RawTargetFilter,
        raw_filter: &raw::RawFilter,
    ) -> Option<crate::model::TargetFilter> {
        let what = format!("target `{target}` filter");
        let Some(name) = f.model.as_deref() else {
            self.problem(at, format!("{what} needs `model`"));
            return None;
        };
        let model = self.motion_model(at, &what, name)?;
        let fit_from_data = f.fit_from_data.unwrap_or(true);
        if fit_from_data && model != MotionModel::Oscillatory {
            self.problem(
                at,
                format!("{what}: `fit_from_data` applies to the oscillatory model (set it false, or leave it out)"),
            );
            return None;
        }
        let keys = TuningKeys {
            random_walk: f.random_walk,
            acceleration_noise: f.acceleration_noise,
            oscillation: f.oscillation,
        };
        let tuning = self.tuning(at, &what, model, keys, raw_filter)?;
        Some(crate::model::TargetFilter {
            tuning,
            fit_from_data: fit_from_data && model == MotionModel::Oscillatory,
        })
    }

    /// A motion model's tuning from its keys (`random_walk`, `acceleration_noise`,
    /// `oscillation`), each checked against the model it applies to.
    fn tuning(
        &mut self,
        at: usize,
        what: &str,
        model: MotionModel,
        keys: TuningKeys,
        raw_filter: &raw::RawFilter,
    ) -> Option<FilterTuning> {
        let mut t = FilterTuning::default_for(model);
        let mut ok = true;
        if let Some(rw) = keys.random_walk {
            if model == MotionModel::ConstantVelocity {
                self.problem(
                    at,
                    format!("{what}: `random_walk` applies to the static and oscillatory models"),
                );
                ok = false;
            }
            ok &= self.plausible_rotation(
                at,
                &format!("{what}: random_walk.rotation_arcsec_per_sqrt_s"),
                rw.rotation_arcsec_per_sqrt_s,
            );
            ok &= self.plausible_translation(
                at,
                &format!("{what}: random_walk.translation_mm_per_sqrt_s"),
                rw.translation_mm_per_sqrt_s,
            );
            t.random_walk_rotation_arcsec_per_sqrt_s = rw.rotation_arcsec_per_sqrt_s;
            t.random_walk_translation_mm_per_sqrt_s = rw.translation_mm_per_sqrt_s;
        }
        if let Some(a) = keys.acceleration_noise {
            if model != MotionModel::ConstantVelocity {
                self.problem(
                    at,
                    format!("{what}: `acceleration_noise` applies to the constant_velocity model"),
                );
                ok = false;
            }
            ok &= self.plausible_rotation(
                at,
                &format!("{what}: acceleration_noise.rotation_arcsec_per_s_sqrt_s"),
                a.rotation_arcsec_per_s_sqrt_s,
            );
            ok &= self.plausible_translation(
                at,
                &format!("{what}: acceleration_noise.translation_mm_per_s_sqrt_s"),
                a.translation_mm_per_s_sqrt_s,
            );
            t.acceleration_rotation_arcsec_per_s_sqrt_s = a.rotation_arcsec_per_s_sqrt_s;
            t.acceleration_translation_mm_per_s_sqrt_s = a.translation_mm_per_s_sqrt_s;
        }
        if let Some(o) = keys.oscillation {
            if model != MotionModel::Oscillatory {
                self.problem(
                    at,
                    format!("{what}: `oscillation` applies to the oscillatory model"),
                );
                ok = false;
            }
            ok &= self.duration(
                at,
                &format!("{what}: oscillation.period_s"),
                o.period_s,
                1e-6,
                MAX_DURATION_S,
            );
            ok &= self.duration(
                at,
                &format!("{what}: oscillation.correlation_time_s"),
                o.correlation_time_s,
                1e-6,
                MAX_DURATION_S,
            );
            for v in o.rotation_arcsec.per_axis() {
                ok &=
                    self.plausible_rotation(at, &format!("{what}: oscillation.rotation_arcsec"), v);
            }
            for v in o.translation_mm.per_axis() {
                ok &= self.plausible_translation(
                    at,
                    &format!("{what}: oscillation.translation_mm"),
                    v,
                );
            }
            t.oscillation = crate::filter::OscillationTuning {
                period_s: o.period_s,
                correlation_time_s: o.correlation_time_s,
                rotation_arcsec: o.rotation_arcsec.per_axis(),
                translation_mm: o.translation_mm.per_axis(),
            };
        }
        if let Some(g) = raw_filter.gate_probability {
            t.gate_probability = g;
        }
        if let Some(n) = raw_filter.reinit_after_outliers {
            t.reinit_after_outliers = n.max(1);
        }
        ok.then_some(t)
    }

    fn measured(
        &mut self,
        at: usize,
        l: &raw::RawLink,
        raw_filter: &raw::RawFilter,
    ) -> Option<LinkKind> {
        let what = format!("measured link `{}`", l.name);
        if l.pose.is_some() {
            self.problem(
                at,
                format!("{what}: `pose` is for calibrated links; a measured link's designed pose is `nominal`"),
            );
        }
        let model = self.motion_model(at, &what, l.model.as_deref().unwrap_or("static"))?;
        let Some(raw_sigma) = &l.sigma else {
            self.problem(
                at,
                format!("{what} needs `sigma` (the default measurement noise)"),
            );
            return None;
        };
        let sigmas = self.sigmas(at, &format!("{what}: sigma"), raw_sigma)?;
        let Some(rate) = l.expected_rate_hz else {
            self.problem(at, format!("{what} needs `expected_rate_hz`"));
            return None;
        };
        if !self.within(at, &format!("{what}: expected_rate_hz"), rate, 1e-4, 1e5) {
            return None;
        }
        let nominal = match &l.nominal {
            Some(p) => Some(self.pose(at, &format!("{what}: nominal"), p)?),
            None => None,
        };
        let keys = TuningKeys {
            random_walk: l.random_walk,
            acceleration_noise: l.acceleration_noise,
            oscillation: l.oscillation,
        };
        let tuning = self.tuning(at, &what, model, keys, raw_filter)?;
        Some(LinkKind::Measured(MeasuredLink {
            tuning,
            default_sigmas: sigmas,
            expected_rate_hz: rate,
            nominal,
        }))
    }

    fn targets(&mut self, raw: &RawFile, topology: &Topology) -> Vec<TargetSpec> {
        let mut out: Vec<TargetSpec> = Vec::new();
        if raw.targets.is_empty() {
            // An empty or mistaken file would otherwise run a service that measures nothing.
            self.problems.push(ConfigProblem {
                line: None,
                column: None,
                message: "the installation has no [[targets]]: nothing would be measured \
                          (see `brokenray default-config` for a complete file)"
                    .to_owned(),
            });
        }
        for spanned in &raw.targets {
            let at = spanned.span().start;
            let t = spanned.get_ref();
            if out.iter().any(|o| o.name == t.name) {
                self.problem(at, format!("duplicate target `{}`", t.name));
                continue;
            }
            let alarms = self.alarms(at, &t.name, &t.alarms);
            let filter = match &t.filter {
                Some(f) => match self.target_filter(
                    at,
                    &t.name,
                    f,
                    raw.filter
                        .as_ref()
                        .map_or(&raw::RawFilter::default(), |f| f.get_ref()),
                ) {
                    Some(f) => Some(f),
                    None => continue,
                },
                None => None,
            };
            let resolution = match topology.resolve(&t.base, &t.name) {
                Ok(r) => r,
                Err(ChainError::UnknownFrame(f)) => {
                    self.problem(
                        at,
                        format!("target `{}`: frame `{f}` is not introduced by any link, camera or marker", t.name),
                    );
                    continue;
                }
                Err(e) => {
                    self.problem(at, e.to_string());
                    continue;
                }
            };
            out.push(TargetSpec {
                name: t.name.clone(),
                frame: resolution.target,
                base: resolution.base,
                resolution,
                alarms,
                filter,
            });
        }
        out
    }

    fn alarms(&mut self, at: usize, target: &str, a: &raw::RawAlarms) -> AlarmThresholds {
        let what = format!("target `{target}` alarms");
        for (name, v) in [
            ("warn_rotation_arcsec", a.warn_rotation_arcsec),
            ("alarm_rotation_arcsec", a.alarm_rotation_arcsec),
            ("warn_translation_mm", a.warn_translation_mm),
            ("alarm_translation_mm", a.alarm_translation_mm),
        ] {
            if let Some(v) = v {
                self.positive(at, &format!("{what}: {name}"), v);
            }
        }
        for (kind, warn, alarm) in [
            ("rotation", a.warn_rotation_arcsec, a.alarm_rotation_arcsec),
            ("translation", a.warn_translation_mm, a.alarm_translation_mm),
        ] {
            if let (Some(w), Some(al)) = (warn, alarm)
                && w >= al
            {
                self.problem(
                    at,
                    format!(
                        "{what}: the {kind} warn level ({w}) must be below the alarm level ({al})"
                    ),
                );
            }
        }
        let hysteresis = a.hysteresis.unwrap_or(0.1);
        if !(0.0..0.5).contains(&hysteresis) {
            self.problem(
                at,
                format!("{what}: hysteresis must be a fraction from 0 up to 0.5, not {hysteresis}"),
            );
        }
        let dwell_s = a.dwell_s.unwrap_or(1.0);
        self.duration(
            at,
            &format!("{what}: dwell_s"),
            dwell_s,
            0.0,
            MAX_DURATION_S,
        );
        for (name, v) in [
            ("rate_rotation_arcsec_per_s", a.rate_rotation_arcsec_per_s),
            ("rate_translation_mm_per_s", a.rate_translation_mm_per_s),
        ] {
            if let Some(v) = v {
                self.positive(at, &format!("{what}: {name}"), v);
            }
        }
        AlarmThresholds {
            warn_rotation_arcsec: a.warn_rotation_arcsec,
            alarm_rotation_arcsec: a.alarm_rotation_arcsec,
            warn_translation_mm: a.warn_translation_mm,
            alarm_translation_mm: a.alarm_translation_mm,
            hysteresis,
            dwell_s,
            rate_rotation_arcsec_per_s: a.rate_rotation_arcsec_per_s,
            rate_translation_mm_per_s: a.rate_translation_mm_per_s,
        }
    }

    fn notify(&mut self, raw: &RawFile) -> NotifySettings {
        let mut webhooks = Vec::new();
        for (i, spanned) in raw.notify.webhooks.iter().enumerate() {
            let at = spanned.span().start;
            let w = spanned.get_ref();
            let what = format!("notify.webhooks[{i}]");
            let mut ok = true;
            let scheme_ok = ["http://", "https://"]
                .iter()
                .any(|p| w.url.len() > p.len() && w.url[..p.len()].eq_ignore_ascii_case(p));
            if !scheme_ok || w.url.chars().any(char::is_whitespace) {
                self.problem(
                    at,
                    format!(
                        "{what}.url must be an http:// or https:// URL, not `{}`",
                        w.url
                    ),
                );
                ok = false;
            }
            if w.secret.is_empty() {
                self.problem(
                    at,
                    format!("{what}.secret is empty: the receiver checks the signature with it"),
                );
                ok = false;
            }
            let min_level = match w.min_level.as_deref() {
                None | Some("warn") => NotifyLevel::Warn,
                Some("alarm") => NotifyLevel::Alarm,
                Some(other) => {
                    self.problem(
                        at,
                        format!("{what}.min_level `{other}` is not one of warn, alarm"),
                    );
                    ok = false;
                    NotifyLevel::Warn
                }
            };
            let timeout_s = w.timeout_s.unwrap_or(10.0);
            ok &= self.duration(at, &format!("{what}.timeout_s"), timeout_s, 0.01, 3600.0);
            let max_attempts = w.max_attempts.unwrap_or(8);
            if !(1..=100).contains(&max_attempts) {
                self.problem(
                    at,
                    format!("{what}.max_attempts must be from 1 to 100, not {max_attempts}"),
                );
                ok = false;
            }
            if ok {
                webhooks.push(WebhookSpec {
                    url: w.url.clone(),
                    secret: w.secret.clone(),
                    min_level,
                    timeout_s,
                    max_attempts,
                });
            }
        }
        NotifySettings { webhooks }
    }

    fn auth(&mut self, raw: &RawFile) -> AuthSettings {
        let mut tokens: Vec<TokenSpec> = Vec::new();
        for spanned in &raw.auth.tokens {
            let at = spanned.span().start;
            let t = spanned.get_ref();
            let hex = t.sha256.to_ascii_lowercase();
            if hex.len() != 64 || !hex.chars().all(|c| c.is_ascii_hexdigit()) {
                self.problem(
                    at,
                    format!("token `{}`: sha256 must be 64 hexadecimal digits", t.name),
                );
                continue;
            }
            if tokens.iter().any(|o| o.sha256_hex == hex) {
                self.problem(
                    at,
                    format!("token `{}`: the same sha256 is listed twice", t.name),
                );
                continue;
            }
            let mut scopes = Vec::new();
            for s in &t.scopes {
                match s.as_str() {
                    "read" => scopes.push(Scope::Read),
                    "ingest" => scopes.push(Scope::Ingest),
                    "admin" => scopes.push(Scope::Admin),
                    "sync" => scopes.push(Scope::Sync),
                    other => self.problem(
                        at,
                        format!(
                            "token `{}`: scope `{other}` is not one of read, ingest, admin, sync",
                            t.name
                        ),
                    ),
                }
            }
            if t.scopes.is_empty() {
                self.problem(
                    at,
                    format!(
                        "token `{}`: no scopes; give at least one of read, ingest, admin",
                        t.name
                    ),
                );
                continue;
            }
            let site = match &t.site {
                None => None,
                Some(name) => {
                    let parsed = SiteName::parse(name);
                    if parsed.is_none() {
                        self.problem(
                            at,
                            format!("token `{}`: site `{name}` is not a site name", t.name),
                        );
                        continue;
                    }
                    parsed
                }
            };
            if scopes.contains(&Scope::Sync) != site.is_some() {
                self.problem(
                    at,
                    format!(
                        "token `{}`: a `sync` token names the one site it uploads for (`site = \"...\"`), and only a sync token names a site",
                        t.name
                    ),
                );
                continue;
            }
            tokens.push(TokenSpec {
                name: t.name.clone(),
                sha256_hex: hex,
                scopes,
                site,
            });
        }
        AuthSettings { tokens }
    }
}

/// The tuning keys of a measured link or a target's filter.
#[derive(Debug, Clone, Copy)]
struct TuningKeys {
    random_walk: Option<raw::RawRandomWalk>,
    acceleration_noise: Option<raw::RawAcceleration>,
    oscillation: Option<raw::RawOscillation>,
}

/// A camera's `intrinsics_covariance` (81 numbers, row-major, `fx fy cx cy k1 k2 p1 p2 k3`)
/// checked: finite, symmetric, positive semi-definite (a calibration's fixed parameters leave
/// zero rows); otherwise what is wrong with it.
fn intrinsics_covariance(values: &[f64]) -> Result<crate::chain::IntrinsicsCovariance, String> {
    if values.len() != 81 {
        return Err(format!(
            "must have 81 numbers (9 x 9, row-major, in the order fx fy cx cy k1 k2 p1 p2 k3), not {}",
            values.len()
        ));
    }
    if let Some((i, v)) = values.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(format!("entry {i} is not a finite number ({v})"));
    }
    let cov = crate::chain::IntrinsicsCovariance::from_row_slice(values);
    // Plausible variances: a focal length or principal point known to 10 000 px, a
    // distortion term to 100, is no calibration at all; beyond, the sigmas it feeds are huge
    // or not finite.
    const NAMES: [&str; 9] = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"];
    for (i, name) in NAMES.iter().enumerate() {
        let max = if i < 4 { 1e8 } else { 1e4 };
        let v = cov[(i, i)];
        if v > max {
            return Err(format!(
                "has a variance of {v:e} for {name} (entry {}), beyond the plausible {max:e}",
                i * 10
            ));
        }
    }
    let scale = cov.amax().max(f64::MIN_POSITIVE);
    for i in 0..9 {
        for j in 0..i {
            if (cov[(i, j)] - cov[(j, i)]).abs() > 1e-9 * scale {
                return Err(format!(
                    "is not symmetric (row {i}, column {j}: {} against {})",
                    cov[(i, j)],
                    cov[(j, i)]
                ));
            }
        }
    }
    let smallest = nalgebra::SymmetricEigen::new((cov + cov.transpose()) * 0.5)
        .eigenvalues
        .min();
    // The file's numbers are rounded, so a tiny negative eigenvalue is rounding: at most a
    // billionth of the largest entry, and never more than 1e-9 whatever the entries.
    if smallest < -1e-9 * scale.min(1.0) {
        return Err(format!(
            "is not positive semi-definite (an eigenvalue of {smallest:e})"
        ));
    }
    Ok(cov)
}
