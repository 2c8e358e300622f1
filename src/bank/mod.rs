//! The filter bank: one filter ([`crate::filter::LinkFilter`]) per measured link of a
//! [`crate::model::Model`], and one per target; raw results from measurement groups.
//!
//! **Filtering where the deformation is.** A target's filtered pose is the filter of its own
//! raw results (each measurement group composed along the target's paths, with the composed
//! covariance), not the composition of separately filtered links: a relay station's motion
//! enters two links of a path and cancels exactly in their composition, which each link's
//! filter, lagging that motion with its own gains, would no longer do. The link filters stay
//! for what is the link's own: outlier gating, the links endpoint, liveness, and bringing a
//! sample exposed at another instant to its group's time. A target's motion model is the most
//! dynamic of its measured links'; the oscillation's strengths, period and drift are fitted
//! from its raw results ([`crate::filter::MotionEstimator`]) and its normalised innovations
//! watched ([`crate::filter::InnovationWindow`]), so a model that does not fit the data says so.
//!
//! This file holds the facade ([`FilterBank`]: ingest, evaluation, liveness, budgets) and the
//! types it answers with; a measured link's slot is in `slot`, a target's own filter and its
//! tuning in `track`, measurement groups and the raw results composed from them in `groups`,
//! calibrated links' calibrations and the calibration stamps in `calibrations`, and the saved
//! state ([`BankRecord`]) in `record`.

use crate::chain::{
    Budget, Consistency, Contributor, ErrorTerms, Factor, LinkId, SourcedPose, compose_path,
    compose_path_terms, factor_of_covariance, fuse, fuse_terms,
};
use crate::deformation::{CalibrationStamp, MeasuredPose};
use crate::filter::{
    BankSettings, Bounds, Disposition, FilterError, FilterTuning, InnovationReport,
    InnovationWindow, LinkFilter, LinkFilterRecord, MotionEstimator, MotionFit, MotionModel,
    NS_PER_S,
};
use crate::geometry::{Mat6, Pose, PoseCov, ReportedSigmas, adjoint, se3_log};
use crate::model::TargetId;
use crate::model::{LinkKind, Model};
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::Arc;

mod calibrations;
mod groups;
mod record;
mod slot;
mod track;

use calibrations::{Calibration, camera_stamp};
use groups::Group;
pub use record::BankRecord;
use slot::{MeasuredSlot, RATE_WINDOW, remember, state_at};
pub use track::{CONSISTENCY_JUDGED_FROM, TargetTuning};
use track::{TargetTrack, target_tuning_of};

/// How uncertain a sample is.
#[derive(Debug, Clone, Copy, PartialEq)]
#[allow(
    clippy::large_enum_variant,
    reason = "passed by value per sample; boxing would allocate on the ingest path"
)]
pub enum MeasurementUncertainty {
    /// The link's configured default sigmas.
    Default,
    /// Per-axis sigmas as users read them (see [`crate::geometry::PoseCov::from_reported_sigmas`]).
    Sigmas(ReportedSigmas),
    /// A full 6x6 covariance of the left perturbation `[rho (mm); phi (rad)]`.
    Covariance(Mat6),
}

/// One measured link pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// The measured link.
    pub link: LinkId,
    /// Measurement time (ns since the Unix epoch, UTC).
    pub time_ns: i64,
    /// The measured `parent_from_child`.
    pub parent_from_child: Pose,
    /// Its uncertainty.
    pub uncertainty: MeasurementUncertainty,
}

/// Half the shortest expected period of the model's measured links (ns): how far apart the
/// exposures of one measurement group may be unless the installation says otherwise. Cameras
/// that expose together are far inside it; a group never takes two periods of one link.
pub fn default_group_tolerance_ns(model: &Model) -> i64 {
    let fastest_hz = model
        .links
        .iter()
        .filter_map(|l| match &l.kind {
            LinkKind::Measured(m) => Some(m.expected_rate_hz),
            LinkKind::Calibrated { .. } => None,
        })
        .filter(|r| r.is_finite() && *r > 0.0)
        .fold(0.0f64, f64::max);
    if fastest_hz > 0.0 {
        (0.5e9 / fastest_hz).round() as i64
    } else {
        0
    }
}

/// A raw result: the composition of the raw samples of one measurement group.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RawResult {
    /// Index of the target in the model.
    pub target: TargetId,
    /// The group's time (ns).
    pub time_ns: i64,
    /// `target_from_base` composed from the raw samples, with its whole covariance, the
    /// systematic part of it (cameras' intrinsics and calibrations, the same error in every
    /// result of that geometry; the rest is the samples' noise) and the calibrations it was
    /// measured with.
    pub target_from_base: MeasuredPose,
    /// Disagreement of redundant paths, where there are several.
    pub consistency: Option<Consistency>,
}

impl RawResult {
    /// Its status: degraded when its redundant paths disagree beyond chance, ok otherwise (a
    /// raw result is never stale: it is made from samples of one instant).
    pub fn status(&self) -> TargetStatus {
        if self.consistency.is_some_and(|c| !c.is_consistent()) {
            TargetStatus::Degraded
        } else {
            TargetStatus::Ok
        }
    }
}

/// What ingesting one sample did.
#[derive(Debug, Clone, PartialEq)]
pub struct SampleOutcome {
    /// The link.
    pub link: LinkId,
    /// The sample's time (ns).
    pub time_ns: i64,
    /// Fused, outlier, restart, ...
    pub disposition: Disposition,
    /// The measurement as used, with the covariance that applied.
    pub measurement: PoseCov,
    /// Raw results completed by this sample.
    pub raw_results: Vec<RawResult>,
    /// True when the sample is older than every measurement group still assembled in memory
    /// (a backfill after an outage): its group can only be completed from the stored samples
    /// of its time, with [`FilterBank::raw_results_of_group`].
    pub needs_stored_group: bool,
    /// Filtered results: for each target whose every link has now reached a newer time, the
    /// target evaluated at that time.
    pub filtered_results: Vec<TargetEstimate>,
}

crate::words! {
    /// Which results of a target: each measurement group composed as measured, or the
    /// filtered estimate.
    #[derive(PartialOrd, Ord)]
    pub enum ResultSource("result source") {
        /// Each measurement group composed as measured.
        Raw = "raw",
        /// The filtered results.
        Filtered = "filtered",
    }
}

crate::words! {
    /// The state of a target's result.
    pub enum TargetStatus("target status") {
        /// Every link is current and redundant paths agree.
        Ok = "ok",
        /// A link on the path has had no sample for longer than its staleness limit.
        Stale = "stale",
        /// Redundant paths disagree, or one of them has no data yet.
        Degraded = "degraded",
        /// Some measured link on every path has had no sample yet.
        Initializing = "initializing",
        /// The time asked for is after the newest sample: the result is a prediction.
        Predicted = "predicted",
    }
}

/// A target evaluated at a time.
#[derive(Debug, Clone, PartialEq)]
pub struct TargetEstimate {
    /// Index of the target in the model.
    pub target: TargetId,
    /// The time evaluated (ns).
    pub time_ns: i64,
    /// Its status.
    pub status: TargetStatus,
    /// `target_from_base` with its whole covariance (the filter's, which is random, and the
    /// systematic part: cameras' intrinsics and calibrations, which no filtering reduces, zero
    /// when every calibration is taken as exact) and the calibrations it was measured with;
    /// `None` while initialising.
    pub target_from_base: Option<MeasuredPose>,
    /// Time since the newest sample on the path (s); 0 when evaluated at that sample.
    pub age_s: f64,
    /// Disagreement of redundant paths, where several had data.
    pub consistency: Option<Consistency>,
    /// How many of the target's independent paths had data.
    pub paths_used: usize,
}

/// A link's state in the bank (the default: nothing seen yet).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LinkStatus {
    /// Samples ingested (fused, outliers and out-of-order alike).
    pub n_samples: u64,
    /// Samples flagged as outliers.
    pub n_outliers: u64,
    /// Restarts after a run of consistent outliers.
    pub n_reinitializations: u64,
    /// Time of the newest sample (ns).
    pub last_time_ns: Option<i64>,
    /// Samples whose measurement group left memory without completing a raw result of any
    /// target the link serves (since start: a link whose exposures are never within the group
    /// tolerance of the others' shows here).
    pub n_ungrouped: u64,
    /// Samples whose measurement group has left memory, completed or not (since start).
    pub n_grouped_closed: u64,
}

impl LinkStatus {
    /// What is wrong with the link's grouping, when most of its samples (of at least 50 whose
    /// groups closed) never made a raw result: its exposures are not within the group
    /// tolerance of the other links' on its targets' paths.
    pub fn grouping_problem(&self) -> Option<(u64, u64)> {
        (self.n_grouped_closed >= 50 && 2 * self.n_ungrouped > self.n_grouped_closed)
            .then_some((self.n_ungrouped, self.n_grouped_closed))
    }
}

/// How far a measured link is behind a time (see [`FilterBank::link_lag`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkLag {
    /// Seconds between the link's newest sample and the time asked about.
    pub behind_s: f64,
    /// The limit it was judged against (s).
    pub limit_s: f64,
    /// `behind_s` is more than `limit_s`.
    pub stale: bool,
}

/// A target's liveness at a time (see [`FilterBank::target_liveness`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TargetLiveness {
    /// A measured link on the target's paths is behind by more than its limit.
    pub stale: bool,
    /// The link with the largest `behind_s / limit_s`, and its lag; `None` before any link of
    /// the target has a sample.
    pub worst: Option<(LinkId, LinkLag)>,
}

/// One filter per measured link of an model.
#[derive(Debug, Clone)]
pub struct FilterBank {
    model: Arc<Model>,
    settings: BankSettings,
    measured: Vec<Option<MeasuredSlot>>,
    /// Per calibrated link: its calibrations, oldest first; the one in the installation file is
    /// valid from the beginning of time.
    calibrations: Vec<Vec<Calibration>>,
    status: Vec<LinkStatus>,
    groups: BTreeMap<i64, Group>,
    /// How far apart the exposures of one group may be (ns).
    group_tolerance_ns: i64,
    /// Per link: the targets whose independent paths use it.
    targets_of_link: Vec<Vec<TargetId>>,
    /// Per measured link: the stamp of its camera's calibration (intrinsics and their
    /// covariance; 0 for a link without a configured camera).
    camera_stamps: Vec<i64>,
    /// Per target: the time of the newest filtered result.
    frontier_ns: Vec<Option<i64>>,
    /// Per target: its own filter.
    tracks: Vec<TargetTrack>,
}

impl FilterBank {
    /// A bank for the model, every filter uninitialised.
    pub fn new(model: &Model) -> Self {
        Self::shared(Arc::new(model.clone()))
    }

    /// A bank sharing a model, every filter uninitialised.
    pub fn shared(model: Arc<Model>) -> Self {
        let n = model.links.len();
        let mut targets_of_link = vec![Vec::new(); n];
        for (ti, t) in model.target_ids() {
            for path in &t.resolution.paths {
                for l in path.links() {
                    if !targets_of_link[l.0].contains(&ti) {
                        targets_of_link[l.0].push(ti);
                    }
                }
            }
        }
        Self {
            settings: model.filter,
            measured: model
                .links
                .iter()
                .map(|l| match &l.kind {
                    LinkKind::Measured(m) => Some(MeasuredSlot::new(
                        m.tuning,
                        model
                            .camera_and_marker(l.id)
                            .is_some_and(|(_, c, _)| c.intrinsics_covariance.is_some()),
                    )),
                    LinkKind::Calibrated { .. } => None,
                })
                .collect(),
            calibrations: model
                .links
                .iter()
                .map(|l| match &l.kind {
                    LinkKind::Calibrated { parent_from_child } => {
                        vec![Calibration::new(i64::MIN, *parent_from_child)]
                    }
                    LinkKind::Measured(_) => Vec::new(),
                })
                .collect(),
            frontier_ns: vec![None; model.targets.len()],
            status: vec![LinkStatus::default(); n],
            groups: BTreeMap::new(),
            group_tolerance_ns: model
                .filter
                .group_tolerance_ns
                .unwrap_or_else(|| default_group_tolerance_ns(&model)),
            targets_of_link,
            camera_stamps: model
                .links
                .iter()
                .map(|l| {
                    model
                        .camera_and_marker(l.id)
                        .map_or(0, |(_, camera, _)| camera_stamp(camera))
                })
                .collect(),
            tracks: model
                .target_ids()
                .map(|(ti, t)| match t.filter {
                    Some(f) => TargetTrack::new(f.tuning, f.fit_from_data),
                    None => TargetTrack::new(target_tuning_of(&model, ti), true),
                })
                .collect(),
            model,
        }
    }

    /// A copy that can evaluate targets from the current states on (no past states, no
    /// pending measurement groups): cheap enough to publish after every commit.
    pub fn current_view(&self) -> Self {
        Self {
            model: Arc::clone(&self.model),
            settings: self.settings,
            measured: self
                .measured
                .iter()
                .map(|slot| {
                    slot.as_ref().map(|s| MeasuredSlot {
                        filter: s.filter.clone(),
                        history: VecDeque::new(),
                        recent_times: s.recent_times.clone(),
                        intrinsics: s.intrinsics,
                        uses_intrinsics: s.uses_intrinsics,
                    })
                })
                .collect(),
            calibrations: self.calibrations.clone(),
            status: self.status.clone(),
            groups: BTreeMap::new(),
            group_tolerance_ns: self.group_tolerance_ns,
            targets_of_link: self.targets_of_link.clone(),
            camera_stamps: self.camera_stamps.clone(),
            frontier_ns: self.frontier_ns.clone(),
            tracks: self.tracks.iter().map(TargetTrack::view).collect(),
        }
    }

    /// Restarts the filters of the targets whose paths use `link` (from their next raw result).
    fn restart_targets_of(&mut self, link: LinkId) {
        for &ti in &self.targets_of_link[link.0] {
            self.tracks[ti.0].reset();
        }
    }

    /// How a target is filtered now (see [`TargetTuning`]).
    pub fn target_tuning(&self, target: TargetId) -> Option<TargetTuning> {
        let track = self.tracks.get(target.0)?;
        Some(TargetTuning {
            tuning: *track.filter.tuning(),
            fit: track.fit,
            consistency: track.consistency.report(),
        })
    }

    /// Where the uncertainty of a target's newest result comes from, with that result's time:
    /// of the newest raw result, every contributor as it entered; of the filtered result, the
    /// systematic contributors as they entered and the filter's own random covariance shared
    /// among the measured links' noise (see [`Budget::filtered`]). `None` before the target's
    /// first raw result.
    pub fn budget(&self, target: TargetId, source: ResultSource) -> Option<(i64, Budget)> {
        let track = self.tracks.get(target.0)?;
        let terms = track.latest_terms.as_ref()?;
        let (time_ns, filtered) = track.latest_filtered?;
        Some((
            time_ns,
            match source {
                ResultSource::Raw => Budget::of(terms),
                ResultSource::Filtered => Budget::filtered(terms, &filtered),
            },
        ))
    }

    /// The measurement model the bank filters.
    pub fn model(&self) -> &Model {
        &self.model
    }

    /// The filter of a measured link.
    pub fn filter(&self, link: LinkId) -> Option<&LinkFilter> {
        self.measured
            .get(link.0)
            .and_then(Option::as_ref)
            .map(|s| &s.filter)
    }

    /// The observed sample rate of a measured link over its recent samples (Hz).
    pub fn observed_rate_hz(&self, link: LinkId) -> Option<f64> {
        let slot = self.measured.get(link.0)?.as_ref()?;
        let (first, last) = (slot.recent_times.front()?, slot.recent_times.back()?);
        let span_s = (last - first) as f64 / NS_PER_S;
        (span_s > 0.0).then(|| (slot.recent_times.len() - 1) as f64 / span_s)
    }

    /// The targets a link's independent paths serve.
    pub fn targets_of_link(&self, link: LinkId) -> &[TargetId] {
        &self.targets_of_link[link.0]
    }

    /// A link's counters.
    pub fn link_status(&self, link: LinkId) -> &LinkStatus {
        &self.status[link.0]
    }

    /// The newest sample time of any link (ns).
    pub fn newest_sample_ns(&self) -> Option<i64> {
        self.status.iter().filter_map(|s| s.last_time_ns).max()
    }

    /// How far a measured link's newest sample lies behind `time_ns`, and whether that is more
    /// than its staleness limit (`stale_after_periods` of its expected period). `None` for a
    /// calibrated link, or before its first sample.
    pub fn link_lag(&self, link: LinkId, time_ns: i64) -> Option<LinkLag> {
        self.link_lag_with(link, time_ns, 0.0)
    }

    /// [`Self::link_lag`] with `tolerance_s` added to the limit: judged against the server's
    /// clock, the tolerance covers the delay and skew between the measuring computer and the
    /// server.
    pub fn link_lag_with(&self, link: LinkId, time_ns: i64, tolerance_s: f64) -> Option<LinkLag> {
        let LinkKind::Measured(m) = &self.model.links[link.0].kind else {
            return None;
        };
        let last = self.status[link.0].last_time_ns?;
        let behind_s = (time_ns - last) as f64 / NS_PER_S;
        let limit_s = self.settings.stale_after_periods / m.expected_rate_hz + tolerance_s;
        Some(LinkLag {
            behind_s,
            limit_s,
            stale: behind_s > limit_s,
        })
    }

    /// A target's liveness at `time_ns` (the server's clock, for what is current): stale when
    /// any measured link on any of its paths is behind by more than its limit plus
    /// `tolerance_s`. Links without a sample yet are not stale (they have no data, which the
    /// target's status says).
    pub fn target_liveness(
        &self,
        target: TargetId,
        time_ns: i64,
        tolerance_s: f64,
    ) -> TargetLiveness {
        let mut worst: Option<(LinkId, LinkLag)> = None;
        let Some(spec) = self.model.targets.get(target.0) else {
            return TargetLiveness {
                stale: false,
                worst,
            };
        };
        for l in spec.resolution.paths.iter().flat_map(|p| p.links()) {
            if let Some(lag) = self.link_lag_with(l, time_ns, tolerance_s)
                && worst.is_none_or(|(_, w)| lag.behind_s / lag.limit_s > w.behind_s / w.limit_s)
            {
                worst = Some((l, lag));
            }
        }
        TargetLiveness {
            stale: worst.is_some_and(|(_, w)| w.stale),
            worst,
        }
    }

    /// The measurement covariance of a sample: its own, else the link's default.
    pub fn measurement(&self, sample: &Sample) -> Result<PoseCov, FilterError> {
        let spec = &self.model.links[sample.link.0];
        let LinkKind::Measured(m) = &spec.kind else {
            return Err(FilterError::NotMeasured(spec.name.clone()));
        };
        let pose = sample.parent_from_child;
        let z = match sample.uncertainty {
            MeasurementUncertainty::Default => {
                PoseCov::from_reported_sigmas(pose, &m.default_sigmas)
            }
            MeasurementUncertainty::Sigmas(s) => PoseCov::from_reported_sigmas(pose, &s),
            MeasurementUncertainty::Covariance(c) => PoseCov { pose, cov: c },
        };
        // A measurement must be positive definite: a Cholesky factorisation proves it (and is
        // much cheaper than the eigenvalues a semi-definite check needs).
        let scale = z.cov.amax().max(f64::MIN_POSITIVE);
        let reason = if z.cov.iter().any(|v| !v.is_finite()) {
            Some("it has a non-finite entry".to_owned())
        } else if (z.cov - z.cov.transpose()).amax() > 1e-9 * scale {
            Some("it is not symmetric".to_owned())
        } else if z.cov.cholesky().is_none() {
            Some("it is not positive definite (a measurement is never exact)".to_owned())
        } else {
            None
        };
        match reason {
            Some(reason) => Err(FilterError::BadMeasurement {
                link: spec.name.clone(),
                reason,
            }),
            None => Ok(z),
        }
    }

    /// Ingests one sample: filters it, and assembles raw results of completed groups.
    pub fn ingest(&mut self, sample: &Sample) -> Result<SampleOutcome, FilterError> {
        let z = self.measurement(sample)?;
        self.ingest_measurement(sample, z)
    }

    /// [`Self::ingest`] with the measurement already checked by [`Self::measurement`].
    pub fn ingest_measurement(
        &mut self,
        sample: &Sample,
        z: PoseCov,
    ) -> Result<SampleOutcome, FilterError> {
        let link = sample.link;
        let Some(slot) = self.measured[link.0].as_mut() else {
            return Err(FilterError::NotMeasured(
                self.model.links[link.0].name.clone(),
            ));
        };
        slot.refresh_intrinsics(&self.model, link, &z.pose);
        let disposition = slot.filter.update(sample.time_ns, &z);
        if matches!(
            disposition,
            Disposition::Initialized
                | Disposition::Fused { .. }
                | Disposition::Reinitialized { .. }
        ) {
            let restarted = matches!(disposition, Disposition::Reinitialized { .. });
            remember(&slot.filter, &mut slot.history, restarted);
        }
        if slot.recent_times.back().is_none_or(|&t| sample.time_ns > t) {
            slot.recent_times.push_back(sample.time_ns);
            if slot.recent_times.len() > RATE_WINDOW {
                slot.recent_times.pop_front();
            }
        }
        let status = &mut self.status[link.0];
        status.n_samples += 1;
        if disposition.is_outlier() {
            status.n_outliers += 1;
        }
        if matches!(disposition, Disposition::Reinitialized { .. }) {
            status.n_reinitializations += 1;
        }
        status.last_time_ns = Some(
            status
                .last_time_ns
                .map_or(sample.time_ns, |t| t.max(sample.time_ns)),
        );
        let (raw, needs_stored_group) = match self.add_to_group(link, sample.time_ns, z) {
            Some(r) => (r, false),
            None => (Vec::new(), true),
        };
        let (raw_results, raw_terms): (Vec<RawResult>, Vec<SourcedPose>) = raw.into_iter().unzip();
        // Each raw result feeds its target's filter; the target is evaluated at its time.
        let mut filtered_results = Vec::new();
        for (raw, terms) in raw_results.iter().zip(raw_terms) {
            let ti = raw.target;
            if self.frontier_ns[ti.0].is_some_and(|f| raw.time_ns <= f) {
                continue;
            }
            let random = raw.target_from_base.random();
            let d = self.tracks[ti.0].update(raw.time_ns, &random, terms);
            if d.is_outlier() || matches!(d, Disposition::OutOfOrder { .. }) {
                continue;
            }
            if let Ok(estimate) = self.evaluate(ti, raw.time_ns) {
                self.frontier_ns[ti.0] = Some(raw.time_ns);
                filtered_results.push(estimate);
            }
        }
        Ok(SampleOutcome {
            link,
            time_ns: sample.time_ns,
            disposition,
            measurement: z,
            raw_results,
            needs_stored_group,
            filtered_results,
        })
    }

    /// The time every measured link of the target's available paths has reached: the newest
    /// time at which the target can be evaluated from data rather than prediction.
    pub fn frontier(&self, target: TargetId) -> Option<i64> {
        let spec = &self.model.targets[target.0];
        let mut frontier: Option<i64> = None;
        for path in &spec.resolution.paths {
            let mut path_min: Option<i64> = Some(i64::MAX);
            for l in path.links() {
                if let Some(slot) = &self.measured[l.0] {
                    path_min = match (path_min, slot.filter.time_ns()) {
                        (Some(m), Some(t)) => Some(m.min(t)),
                        _ => None,
                    };
                }
            }
            if let Some(m) = path_min.filter(|&m| m != i64::MAX) {
                frontier = Some(frontier.map_or(m, |f| f.min(m)));
            }
        }
        frontier
    }

    /// A link's pose at `time_ns`: a calibrated link's calibration in force then, or a measured
    /// link's filtered pose predicted from its newest state at or before that time. `None`
    /// before a measured link's first sample; an error for a time older than its history.
    pub fn link_estimate(
        &self,
        link: LinkId,
        time_ns: i64,
    ) -> Result<Option<PoseCov>, FilterError> {
        if let Some(c) = self.calibration_at(link, time_ns) {
            return Ok(Some(c));
        }
        let Some(slot) = &self.measured[link.0] else {
            return Ok(None);
        };
        let Some(current) = slot.filter.time_ns() else {
            return Ok(None);
        };
        match state_at(&slot.filter, &slot.history, time_ns).and_then(|f| f.predict(time_ns)) {
            Some(Ok(p)) => Ok(Some(p)),
            _ => Err(FilterError::BeforeFilterTime {
                link: self.model.links[link.0].name.clone(),
                requested_ns: time_ns,
                filter_ns: slot
                    .history
                    .front()
                    .and_then(LinkFilter::time_ns)
                    .unwrap_or(current),
            }),
        }
    }

    /// The newest time any filter of the target's paths has reached (ns).
    pub fn latest_time_ns(&self, target: TargetId) -> Option<i64> {
        self.model.targets[target.0]
            .resolution
            .paths
            .iter()
            .flat_map(|p| p.links())
            .filter_map(|l| self.filter(l).and_then(LinkFilter::time_ns))
            .max()
    }

    /// Restarts a measured link's filter: it starts again from the link's next sample, whatever
    /// its time (recovery from a sample stamped far ahead, after which every correct sample is
    /// out of order, or from a station that moved). The link's newest time, the frontiers of
    /// the targets on its paths and the measurement groups kept in memory are forgotten with
    /// it; its counters stay. `false` for a calibrated link.
    pub fn reset_link(&mut self, link: LinkId) -> bool {
        let Some(slot) = self.measured[link.0].as_mut() else {
            return false;
        };
        slot.filter = LinkFilter::new(*slot.filter.tuning());
        slot.history.clear();
        slot.recent_times.clear();
        self.status[link.0].last_time_ns = None;
        self.restart_targets_of(link);
        for &ti in &self.targets_of_link[link.0] {
            self.frontier_ns[ti.0] = None;
        }
        self.groups.clear();
        true
    }

    /// Evaluates a target at `time_ns`: predicts every measured link of its paths to that
    /// time, composes each path with covariance and fuses the paths that have data.
    pub fn evaluate(&self, target: TargetId, time_ns: i64) -> Result<TargetEstimate, FilterError> {
        let spec = self
            .model
            .targets
            .get(target.0)
            .ok_or_else(|| FilterError::UnknownTarget(target.0.to_string()))?;
        let mut estimates = Vec::new();
        // Each available path with its links' estimates, for the error terms when they are
        // needed.
        let mut available_paths = Vec::new();
        let mut newest_ns: Option<i64> = None;
        let mut stale = false;
        for path in &spec.resolution.paths {
            let mut available = true;
            let mut links = Vec::with_capacity(path.steps.len());
            for l in path.links() {
                match self.link_estimate(l, time_ns)? {
                    Some(p) => links.push(p),
                    None => {
                        available = false;
                        break;
                    }
                }
                if let (Some(lag), Some(last)) =
                    (self.link_lag(l, time_ns), self.status[l.0].last_time_ns)
                {
                    newest_ns = Some(newest_ns.map_or(last, |n| n.max(last)));
                    stale |= lag.stale;
                }
            }
            if available {
                let mut it = links.iter();
                estimates.push(compose_path(path, |_| {
                    it.next().copied().unwrap_or_else(PoseCov::identity)
                }));
                available_paths.push((path, links));
            }
        }
        let paths_used = estimates.len();
        if estimates.is_empty() {
            return Ok(TargetEstimate {
                target,
                time_ns,
                status: TargetStatus::Initializing,
                target_from_base: None,
                age_s: 0.0,
                consistency: None,
                paths_used,
            });
        }
        let fused = fuse(&estimates, self.settings.consistency_probability)?;
        // The filtered links composed with their error terms: the systematic part as the links
        // compose now.
        let sourced = || -> Result<SourcedPose, FilterError> {
            let paths: Vec<SourcedPose> = available_paths
                .iter()
                .map(|(path, links)| {
                    let mut it = path.links().zip(links.iter());
                    compose_path_terms(path, |_| {
                        it.next()
                            .and_then(|(l, p)| self.sourced_link(l, time_ns, Some(p)))
                            .unwrap_or_else(SourcedPose::identity)
                    })
                })
                .collect();
            Ok(fuse_terms(paths, self.settings.consistency_probability)?.0)
        };
        // The target's own filter where it has a state for that time; before its first raw
        // result, the composition of the filtered links.
        let track = &self.tracks[target.0];
        // The systematic part, which no filtering reduces: as the newest raw result the
        // target's filter had carried it (the budget's), else as the links compose now.
        let (pose, systematic_cov) = match state_at(&track.filter, &track.history, time_ns)
            .and_then(|f| f.predict(time_ns))
        {
            Some(Ok(p)) => {
                let systematic = match &track.latest_terms {
                    Some(t) => t.terms.systematic(),
                    None => sourced()?.terms.systematic(),
                };
                (
                    PoseCov {
                        pose: p.pose,
                        cov: p.cov + systematic,
                    },
                    systematic,
                )
            }
            _ => {
                let s = sourced()?;
                (s.total(), s.terms.systematic())
            }
        };
        let age_s = newest_ns.map_or(0.0, |n| ((time_ns - n) as f64 / NS_PER_S).max(0.0));
        let inconsistent = fused.consistency.is_some_and(|c| !c.is_consistent());
        let status = if stale {
            TargetStatus::Stale
        } else if inconsistent || paths_used < spec.resolution.paths.len() {
            TargetStatus::Degraded
        } else if age_s > 0.0 {
            TargetStatus::Predicted
        } else {
            TargetStatus::Ok
        };
        Ok(TargetEstimate {
            target,
            time_ns,
            status,
            target_from_base: Some(MeasuredPose {
                whole: pose,
                systematic_cov,
                calibration: Some(self.calibration_stamp(target, time_ns)),
            }),
            age_s,
            consistency: fused.consistency,
            paths_used,
        })
    }
}
