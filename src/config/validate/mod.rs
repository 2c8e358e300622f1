//! Validation of the installation file: every problem found, each with its line.
//!
//! [`Validator`] walks the raw file ([`super::raw`]) section by section, turning each into its
//! domain type (the core's [`crate::model`] types, or the deployment settings of
//! [`super`]) and collecting a [`ConfigProblem`] for everything wrong, so that one run of
//! `check-config` lists them all. This module holds the walk ([`Validator::installation`]) and
//! the checks every section uses (a number in its range, a duration, a pose, a sigma, a word of
//! a vocabulary); each section's own checks are in a file of their own (`server`, `fleet`,
//! `cameras`, `markers`, `links`, `targets`, `access`; `[outputs]` and `[cameras.source]`'s
//! types beside their checks in [`super`]).

use super::error::LineIndex;
use super::raw::{self, RawFile, RawPose, RawSigma};
use super::{
    AcceptanceSettings, AuthSettings, CalibrationReportFile, CameraAddress, CameraSource,
    CentralSettings, ConfigProblem, FeatureSetting, FleetSettings, FrameSettings, Installation,
    NotifyLevel, NotifySettings, PixelFormat, ReportSettings, RerunMode, RerunSettings,
    RetentionSettings, Scope, ServerSettings, SiteName, TimestampMode, TokenSpec, TriggerMode,
    UpstreamSettings, WebhookSpec,
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

mod acceptance;
mod access;
mod cameras;
mod fleet;
mod links;
mod markers;
mod server;
mod targets;

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
        let reports = self.reports(&raw);
        let acceptance = self.acceptance(&raw, &targets);
        let frames = self.frames(&raw);
        let pnp = self.pnp(&raw);
        let fleet = self.fleet(&raw, server.as_ref());
        let sources = self.sources(&raw);
        let calibration_reports = self.calibration_reports(&raw);
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
            reports: reports?,
            acceptance: acceptance?,
            frames: frames?,
            fleet: fleet?,
            sources: sources?,
            calibration_reports,
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
}
