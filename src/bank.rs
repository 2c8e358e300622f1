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

use crate::chain::{
    Budget, Consistency, Contributor, ErrorTerms, Factor, LinkId, SourcedPose, compose_path,
    compose_path_terms, factor_of_covariance, fuse, fuse_terms,
};
use crate::deformation::{CalibrationStamp, Measured};
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

/// How many past states each link keeps, so that targets can be evaluated at recent times
/// whatever order the links' samples arrived in.
const LINK_HISTORY: usize = 256;

/// The state of a filter to evaluate `time_ns` from: the current one when it is not newer,
/// else the newest past state at or before that time.
fn state_at<'a>(
    current: &'a LinkFilter,
    past: &'a VecDeque<LinkFilter>,
    time_ns: i64,
) -> Option<&'a LinkFilter> {
    if current.time_ns().is_some_and(|t| t <= time_ns) {
        return Some(current);
    }
    past.iter()
        .rev()
        .find(|f| f.time_ns().is_some_and(|t| t <= time_ns))
}

/// Keeps a filter's state after an update among its past states, the oldest dropped beyond
/// [`LINK_HISTORY`]; after a restart the older states, which describe the pose before the
/// step, are forgotten first.
fn remember(current: &LinkFilter, past: &mut VecDeque<LinkFilter>, restarted: bool) {
    if restarted {
        past.clear();
    }
    past.push_back(current.clone());
    if past.len() > LINK_HISTORY {
        past.pop_front();
    }
}

/// How many recent sample times each link keeps to estimate its observed rate.
const RATE_WINDOW: usize = 64;

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
    /// `target_from_base` composed from the raw samples, with its whole covariance (random and
    /// systematic).
    pub target_from_base: PoseCov,
    /// The systematic part of that covariance: cameras' intrinsics and calibrations, the same
    /// error in every result of that geometry (the rest is the samples' noise).
    pub systematic_cov: Mat6,
    /// The calibrations it was measured with.
    pub calibration: CalibrationStamp,
    /// Disagreement of redundant paths, where there are several.
    pub consistency: Option<Consistency>,
}

impl RawResult {
    /// The random part of the covariance: the samples' noise, what filtering averages down.
    pub fn random_cov(&self) -> Mat6 {
        self.target_from_base.cov - self.systematic_cov
    }

    /// The result as a deformation compares it with a reference.
    pub fn measured(&self) -> Measured<'_> {
        Measured {
            g_from_b: &self.target_from_base,
            systematic_cov: &self.systematic_cov,
            calibration: Some(self.calibration),
        }
    }

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
    /// systematic part); `None` while initialising.
    pub target_from_base: Option<PoseCov>,
    /// The systematic part of that covariance (cameras' intrinsics and calibrations: no
    /// filtering reduces it); zero when every calibration is taken as exact.
    pub systematic_cov: Mat6,
    /// The calibrations it was measured with.
    pub calibration: CalibrationStamp,
    /// Time since the newest sample on the path (s); 0 when evaluated at that sample.
    pub age_s: f64,
    /// Disagreement of redundant paths, where several had data.
    pub consistency: Option<Consistency>,
    /// How many of the target's independent paths had data.
    pub paths_used: usize,
}

impl TargetEstimate {
    /// The estimate `g_from_b` (its `target_from_base`) as a deformation compares it with a
    /// reference.
    pub fn measured<'a>(&'a self, g_from_b: &'a PoseCov) -> Measured<'a> {
        Measured {
            g_from_b,
            systematic_cov: &self.systematic_cov,
            calibration: Some(self.calibration),
        }
    }
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

/// The samples of one instant, within the group tolerance: each link's measurement and its own
/// exposure time.
#[derive(Debug, Clone, Default)]
struct Group {
    samples: HashMap<LinkId, (i64, PoseCov)>,
    emitted: Vec<bool>,
}

/// How many innovations a target's consistency is judged over.
const CONSISTENCY_WINDOW: usize = 250;

/// How many innovations a target's consistency needs before it is judged.
pub const CONSISTENCY_JUDGED_FROM: usize = CONSISTENCY_WINDOW / 2;

/// Two-sided probability of the band a target's mean NIS stays in when its filter fits.
const CONSISTENCY_PROBABILITY: f64 = 0.999;

/// A target's filter: fed by the target's raw results (see the module docs).
#[derive(Debug, Clone)]
struct TargetTrack {
    filter: LinkFilter,
    /// Past states, oldest first, each after a fused result or a restart.
    history: VecDeque<LinkFilter>,
    /// The tuning the target starts with (the installation's, or the most dynamic of its
    /// links').
    base_tuning: FilterTuning,
    /// Whether the oscillation's strengths are fitted from the data.
    fit_from_data: bool,
    /// Fits the oscillation from the data (`oscillatory` only).
    estimator: Option<MotionEstimator>,
    /// The newest fit in force, if any.
    fit: Option<MotionFit>,
    consistency: InnovationWindow,
    /// The error terms of the newest raw result fed: where its error comes from.
    latest_terms: Option<SourcedPose>,
    /// The time of the newest raw result fed and the filter's random estimate after it: the
    /// budget's. Both outlive a restart, so the newest result's budget is answered until the
    /// next one.
    latest_filtered: Option<(i64, PoseCov)>,
}

impl TargetTrack {
    fn new(tuning: FilterTuning, fit_from_data: bool) -> Self {
        Self {
            filter: LinkFilter::new(tuning),
            history: VecDeque::new(),
            base_tuning: tuning,
            fit_from_data,
            estimator: (fit_from_data && tuning.model == MotionModel::Oscillatory)
                .then(|| MotionEstimator::new(Bounds::default())),
            fit: None,
            consistency: InnovationWindow::new(6, CONSISTENCY_WINDOW, CONSISTENCY_PROBABILITY),
            latest_terms: None,
            latest_filtered: None,
        }
    }

    /// Back to the start (a rollback or a reset); the newest result's budget stays.
    fn reset(&mut self) {
        let (terms, filtered) = (self.latest_terms.take(), self.latest_filtered.take());
        *self = Self::new(self.base_tuning, self.fit_from_data);
        self.latest_terms = terms;
        self.latest_filtered = filtered;
    }

    /// Feeds one raw result: its random part (`z`, the samples' noise) is filtered; its
    /// systematic part does not average down and is added back to the filtered result.
    fn update(&mut self, time_ns: i64, z: &PoseCov, terms: SourcedPose) -> Disposition {
        let disposition = self.filter.update(time_ns, z);
        if !matches!(
            disposition,
            Disposition::Outlier { .. } | Disposition::OutOfOrder { .. }
        ) {
            self.latest_terms = Some(terms);
            self.latest_filtered = self
                .filter
                .predict(time_ns)
                .and_then(Result::ok)
                .map(|p| (time_ns, p));
        }
        match disposition {
            Disposition::Fused { nis } => self.consistency.push(nis),
            // An outlier is an innovation too, counted at the gate: a glint now and then
            // leaves the mean where it was, a model that does not fit (most samples over the
            // gate, as `static` on a ship) takes it out of its band.
            Disposition::Outlier { nis, .. } => self.consistency.push(nis.min(self.filter.gate())),
            Disposition::Reinitialized { nis, .. } => {
                // The window goes on across a restart: a model that keeps restarting does
                // not fit its data either.
                self.consistency.push(nis.min(self.filter.gate()));
                if let Some(e) = &mut self.estimator {
                    e.clear();
                }
            }
            _ => {}
        }
        if matches!(
            disposition,
            Disposition::Initialized
                | Disposition::Fused { .. }
                | Disposition::Reinitialized { .. }
        ) {
            if let Some(fit) = self.estimator.as_mut().and_then(|e| e.push(time_ns, z)) {
                self.filter.retune(fit.applied_to(&self.base_tuning));
                self.fit = Some(fit);
            }
            let restarted = matches!(disposition, Disposition::Reinitialized { .. });
            remember(&self.filter, &mut self.history, restarted);
        }
        disposition
    }

    /// A copy that evaluates from the current state on (see [`FilterBank::current_view`]): no
    /// past states, and no fitting (the window is the writer's).
    fn view(&self) -> Self {
        Self {
            filter: self.filter.clone(),
            history: VecDeque::new(),
            base_tuning: self.base_tuning,
            fit_from_data: self.fit_from_data,
            estimator: None,
            fit: self.fit,
            consistency: self.consistency.clone(),
            latest_terms: self.latest_terms.clone(),
            latest_filtered: self.latest_filtered,
        }
    }
}

/// How a target is filtered now: its model, the tuning in force (fitted from the data or as
/// configured) and since when, and whether its filter fits its data.
#[derive(Debug, Clone, PartialEq)]
pub struct TargetTuning {
    /// The tuning in force.
    pub tuning: FilterTuning,
    /// The fit it comes from (`None`: as configured, no fit yet or not adaptive).
    pub fit: Option<MotionFit>,
    /// The filter's normalised innovations over the recent window.
    pub consistency: InnovationReport,
}

/// The most dynamic motion model of a target's measured links, with that link's tuning: what
/// the target's own filter starts from.
fn target_tuning_of(model: &Model, target: TargetId) -> FilterTuning {
    let rank = |m: MotionModel| match m {
        MotionModel::Static => 0,
        MotionModel::ConstantVelocity => 1,
        MotionModel::Oscillatory => 2,
    };
    let mut best: Option<FilterTuning> = None;
    for path in &model.targets[target.0].resolution.paths {
        for l in path.links() {
            if let LinkKind::Measured(m) = &model.links[l.0].kind
                && best.is_none_or(|b| rank(m.tuning.model) > rank(b.model))
            {
                best = Some(m.tuning);
            }
        }
    }
    best.unwrap_or_else(|| FilterTuning::default_for(MotionModel::Static))
}

/// A measured link's filter and its recent past states.
#[derive(Debug, Clone)]
struct MeasuredSlot {
    filter: LinkFilter,
    /// Past states, oldest first, each after a fused sample or a restart.
    history: VecDeque<LinkFilter>,
    /// Recent sample times, for the observed rate.
    recent_times: VecDeque<i64>,
    /// The link's systematic error from its camera's intrinsics (see
    /// [`Model::intrinsics_factor`]) at the pose it was computed for: the camera's index and
    /// the factor. Computed again when the link has moved (see [`SENSITIVITY_MOVE_RAD`]).
    intrinsics: Option<(Pose, usize, Factor)>,
    /// Whether the link's camera has an intrinsics covariance (else it is taken as exact).
    uses_intrinsics: bool,
}

/// A calibration of a calibrated link: valid from (ns), the pose, its stamp (see
/// [`FilterBank::calibration_stamp`]) and its covariance's factor (see [`crate::chain`]).
type Calibration = (i64, PoseCov, i64, Factor);

/// A calibration valid from `valid_from_ns`, with its stamp and factor.
fn calibration(valid_from_ns: i64, pose: PoseCov) -> Calibration {
    (
        valid_from_ns,
        pose,
        pose_stamp(&pose),
        factor_of_covariance(&pose.cov),
    )
}

/// How far a link may turn (rad) or move (a fraction of its distance) before the
/// sensitivity of its pose to its camera's intrinsics is computed again: the sensitivity
/// changes with the geometry by about as much, far below the uncertainty of the covariance it
/// maps.
const SENSITIVITY_MOVE_RAD: f64 = 0.01;

impl MeasuredSlot {
    fn new(tuning: FilterTuning, uses_intrinsics: bool) -> Self {
        Self {
            filter: LinkFilter::new(tuning),
            history: VecDeque::new(),
            recent_times: VecDeque::new(),
            intrinsics: None,
            uses_intrinsics,
        }
    }

    /// Keeps the intrinsics factor current for a sample at `pose`.
    fn refresh_intrinsics(&mut self, model: &Model, link: LinkId, pose: &Pose) {
        let moved = |at: &Pose| {
            let d = se3_log(&(pose * at.inverse()));
            let distance = pose.translation.vector.norm().max(1.0);
            d.fixed_rows::<3>(3).norm() > SENSITIVITY_MOVE_RAD
                || d.fixed_rows::<3>(0).norm() > SENSITIVITY_MOVE_RAD * distance
        };
        if !self.uses_intrinsics {
            return;
        }
        if self.intrinsics.as_ref().is_none_or(|(at, _, _)| moved(at)) {
            self.intrinsics = model
                .intrinsics_factor(link, pose)
                .map(|(camera, f)| (*pose, camera, f));
        }
    }
}

/// The bank's state as plain records, for persistence.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BankRecord {
    /// Per measured link, by name: its filter state.
    pub filters: Vec<(String, LinkFilterRecord)>,
    /// Per link, by name: sample, outlier and restart counts and the newest sample time.
    pub counters: Vec<(String, u64, u64, u64, Option<i64>)>,
    /// Per target, by name: the time of the newest filtered result.
    pub frontiers: Vec<(String, i64)>,
    /// Per target, by name: its own filter's state.
    #[serde(default)]
    pub targets: Vec<(String, LinkFilterRecord)>,
}

/// One filter per measured link of an model.
#[derive(Debug, Clone)]
pub struct FilterBank {
    model: Arc<Model>,
    settings: BankSettings,
    measured: Vec<Option<MeasuredSlot>>,
    /// Per calibrated link: its calibrations, `(valid_from_ns, pose, stamp)`, oldest first
    /// (the stamp of the pose and its covariance, for [`Self::calibration_stamp`]); the one in
    /// the installation file is valid from the beginning of time.
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
                        vec![calibration(i64::MIN, *parent_from_child)]
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

    /// Adds a calibration of a calibrated link, valid from `valid_from_ns` (until a later one);
    /// the filters of the targets it serves start again. Returns false for a measured link.
    pub fn add_calibration(
        &mut self,
        link: LinkId,
        valid_from_ns: i64,
        parent_from_child: PoseCov,
    ) -> bool {
        match self.calibrations.get_mut(link.0) {
            Some(list) if !list.is_empty() => {
                let at = list.partition_point(|(t, _, _, _)| *t <= valid_from_ns);
                list.insert(at, calibration(valid_from_ns, parent_from_child));
                // The targets' raw results step with the new calibration: their filters start
                // again from the next one instead of taking the step for a deformation.
                self.restart_targets_of(link);
                true
            }
            _ => false,
        }
    }

    /// Removes a calibration added with [`Self::add_calibration`] (a write that did not commit).
    pub fn remove_calibration(&mut self, link: LinkId, valid_from_ns: i64) {
        if let Some(list) = self.calibrations.get_mut(link.0)
            && let Some(i) = list.iter().rposition(|(t, _, _, _)| *t == valid_from_ns)
            && list.len() > 1
        {
            list.remove(i);
        }
    }

    /// Returns every filter, counter and frontier to a recorded state (the last commit), as if
    /// nothing since had happened. Calibrations are kept. Returns what could not be restored.
    pub fn rollback(&mut self, record: &BankRecord) -> Vec<String> {
        for slot in self.measured.iter_mut().flatten() {
            slot.filter = LinkFilter::new(*slot.filter.tuning());
            slot.history.clear();
            slot.recent_times.clear();
        }
        for s in &mut self.status {
            *s = LinkStatus::default();
        }
        self.frontier_ns.iter_mut().for_each(|f| *f = None);
        self.tracks.iter_mut().for_each(TargetTrack::reset);
        self.groups.clear();
        self.restore(record)
    }

    /// The calibrations a target's result at `time_ns` is measured with: its measured links'
    /// cameras and the calibrations of its calibrated links in force then.
    pub fn calibration_stamp(&self, target: TargetId, time_ns: i64) -> CalibrationStamp {
        let stamps = self.model.targets[target.0]
            .resolution
            .paths
            .iter()
            .flat_map(|p| p.links())
            .map(|l| match self.calibration_entry_at(l, time_ns) {
                Some((_, _, stamp, _)) => *stamp,
                None => self.camera_stamps[l.0],
            });
        CalibrationStamp::of(stamps.map(|s| f64::from_bits(s as u64)))
    }

    /// The calibration of a calibrated link in force at `time_ns`.
    pub fn calibration_at(&self, link: LinkId, time_ns: i64) -> Option<PoseCov> {
        self.calibration_entry_at(link, time_ns)
            .map(|(_, p, _, _)| *p)
    }

    /// The calibration of a calibrated link in force at `time_ns`, with its stamp and factor.
    fn calibration_entry_at(&self, link: LinkId, time_ns: i64) -> Option<&Calibration> {
        let list = self.calibrations.get(link.0)?;
        let at = list.partition_point(|(t, _, _, _)| *t <= time_ns);
        list.get(at.checked_sub(1)?)
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
            let random = PoseCov {
                pose: raw.target_from_base.pose,
                cov: raw.random_cov(),
            };
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

    /// How far apart (ns) the exposures of one measurement group may be.
    pub fn group_tolerance_ns(&self) -> i64 {
        self.group_tolerance_ns
    }

    /// Adds a sample to its measurement group and returns the raw results it completes, or
    /// `None` when the sample is older than every group kept in memory.
    ///
    /// A sample joins the group nearest its time within the group tolerance that has no sample
    /// of its link yet, else starts one at its own time: the group's time is its first
    /// sample's. Each sample is brought to the group's time by its link's filter (see
    /// [`Self::at_group_time`]) when the group is composed.
    fn add_to_group(
        &mut self,
        link: LinkId,
        time_ns: i64,
        z: PoseCov,
    ) -> Option<Vec<(RawResult, SourcedPose)>> {
        let n_targets = self.model.targets.len();
        let tolerance = self.group_tolerance_ns;
        let oldest_kept = self.groups.keys().next().copied();
        if self.groups.len() >= self.settings.group_window
            && oldest_kept.is_some_and(|o| time_ns < o.saturating_sub(tolerance))
        {
            // Older than every group still assembled: only the store can complete it.
            return None;
        }
        let key = self
            .groups
            .range(time_ns.saturating_sub(tolerance)..=time_ns.saturating_add(tolerance))
            .filter(|(_, g)| !g.samples.contains_key(&link))
            .min_by_key(|(k, _)| (**k - time_ns).unsigned_abs())
            .map_or(time_ns, |(k, _)| *k);
        let group = self.groups.entry(key).or_insert_with(|| Group {
            samples: HashMap::new(),
            emitted: vec![false; n_targets],
        });
        group.samples.insert(link, (time_ns, z));
        let group = &self.groups[&key];
        // Most samples leave their group incomplete: compose only when a target of the link
        // has a sample of every measured link on its paths.
        let completes = self.targets_of_link[link.0].iter().any(|t| {
            !group.emitted[t.0]
                && self.model.targets[t.0].resolution.paths.iter().all(|p| {
                    p.links()
                        .all(|l| self.measured[l.0].is_none() || group.samples.contains_key(&l))
                })
        });
        let out = if completes {
            let samples = self.at_group_time(key, &group.samples);
            self.compose_group(link, key, &samples, &group.emitted)
        } else {
            Vec::new()
        };
        if let Some(g) = self.groups.get_mut(&key) {
            for (r, _) in &out {
                g.emitted[r.target.0] = true;
            }
        }
        while self.groups.len() > self.settings.group_window {
            if let Some((_, gone)) = self.groups.pop_first() {
                self.count_ungrouped(&gone);
            }
        }
        Some(out)
    }

    /// Counts, for each sample of a group leaving memory, whether the group completed nothing
    /// its link serves.
    fn count_ungrouped(&mut self, group: &Group) {
        for l in group.samples.keys() {
            self.status[l.0].n_grouped_closed += 1;
            if !self.targets_of_link[l.0]
                .iter()
                .any(|t| group.emitted.get(t.0).copied().unwrap_or(false))
            {
                self.status[l.0].n_ungrouped += 1;
            }
        }
    }

    /// The samples of a group brought to the group's time `group_ns`: a sample exposed at
    /// another time is moved by its link's motion between the two times as the link's filter
    /// predicts it from its state before both, its covariance widened by what the prediction
    /// adds over that interval (per axis), so that a raw result composes one instant.
    /// Without a filter state before both times (a link's first samples) a sample is taken as
    /// it is.
    fn at_group_time(
        &self,
        group_ns: i64,
        samples: &HashMap<LinkId, (i64, PoseCov)>,
    ) -> HashMap<LinkId, PoseCov> {
        samples
            .iter()
            .map(|(&l, &(t, z))| (l, self.moved(l, t, group_ns, z)))
            .collect()
    }

    /// Sample `z` of link `l` exposed at `from_ns`, moved to `to_ns` (see
    /// [`Self::at_group_time`]).
    fn moved(&self, l: LinkId, from_ns: i64, to_ns: i64, z: PoseCov) -> PoseCov {
        if from_ns == to_ns {
            return z;
        }
        let Some(slot) = self.measured.get(l.0).and_then(Option::as_ref) else {
            return z;
        };
        let state = state_at(&slot.filter, &slot.history, from_ns.min(to_ns));
        let predicted = |t: i64| state.and_then(|f| f.predict(t)).and_then(Result::ok);
        let (Some(at_from), Some(at_to)) = (predicted(from_ns), predicted(to_ns)) else {
            return z;
        };
        let delta = at_to.pose * at_from.pose.inverse();
        let (earlier, later) = if from_ns < to_ns {
            (&at_from.cov, &at_to.cov)
        } else {
            (&at_to.cov, &at_from.cov)
        };
        let added = Mat6::from_diagonal(&(later - earlier).diagonal().map(|v| v.max(0.0)));
        let ad = adjoint(&delta);
        PoseCov {
            pose: delta * z.pose,
            cov: ad * z.cov * ad.transpose() + added,
        }
    }

    /// The raw results of a measurement group at `time_ns` given all its samples (`samples`:
    /// each link's measurement, as [`Self::measurement`] makes it, with its own exposure time
    /// within the group tolerance), for the targets on `link`'s paths that the group
    /// completes. For groups too old for memory ([`SampleOutcome::needs_stored_group`]): the
    /// caller reads the other links' samples of that instant from the store.
    pub fn raw_results_of_group(
        &self,
        link: LinkId,
        time_ns: i64,
        samples: &HashMap<LinkId, (i64, PoseCov)>,
    ) -> Vec<RawResult> {
        let none = vec![false; self.model.targets.len()];
        let moved = self.at_group_time(time_ns, samples);
        self.compose_group(link, time_ns, &moved, &none)
            .into_iter()
            .map(|(r, _)| r)
            .collect()
    }

    /// A link's pose with its error terms: a calibrated link's calibration in force at
    /// `time_ns` (its covariance systematic), or a measured link's `measured` pose (a sample or
    /// a filtered estimate; its covariance the link's noise) with its camera's intrinsics
    /// error. `None` for a measured link without `measured`.
    fn sourced_link(
        &self,
        link: LinkId,
        time_ns: i64,
        measured: Option<&PoseCov>,
    ) -> Option<SourcedPose> {
        if let Some((_, c, _, factor)) = self.calibration_entry_at(link, time_ns) {
            return Some(SourcedPose {
                pose: c.pose,
                terms: ErrorTerms::of(Contributor::Calibration(link), *factor),
            });
        }
        let z = measured?;
        let mut terms = ErrorTerms::of(Contributor::Noise(link), factor_of_covariance(&z.cov));
        if let Some((_, camera, f)) = self
            .measured
            .get(link.0)
            .and_then(Option::as_ref)
            .and_then(|s| s.intrinsics.as_ref())
        {
            terms.add(Contributor::Intrinsics(*camera), *f);
        }
        Some(SourcedPose {
            pose: z.pose,
            terms,
        })
    }

    /// Composes, for each target on `link`'s paths not yet `emitted`, the raw result of a
    /// group whose every path is complete in `samples`.
    fn compose_group(
        &self,
        link: LinkId,
        time_ns: i64,
        samples: &HashMap<LinkId, PoseCov>,
        emitted: &[bool],
    ) -> Vec<(RawResult, SourcedPose)> {
        let mut out = Vec::new();
        for &ti in &self.targets_of_link[link.0] {
            if emitted[ti.0] {
                continue;
            }
            let target = &self.model.targets[ti.0];
            let mut estimates = Vec::new();
            let mut complete = true;
            for path in &target.resolution.paths {
                let mut missing = false;
                let composed = compose_path_terms(path, |l| {
                    self.sourced_link(l, time_ns, samples.get(&l))
                        .unwrap_or_else(|| {
                            missing = true;
                            SourcedPose::identity()
                        })
                });
                if missing {
                    complete = false;
                    break;
                }
                estimates.push(composed);
            }
            if !complete {
                continue;
            }
            if let Ok((sourced, f)) = fuse_terms(estimates, self.settings.consistency_probability) {
                let (random, systematic) = sourced.terms.parts();
                out.push((
                    RawResult {
                        target: ti,
                        time_ns,
                        target_from_base: PoseCov {
                            pose: sourced.pose,
                            cov: random + systematic,
                        },
                        systematic_cov: systematic,
                        calibration: self.calibration_stamp(ti, time_ns),
                        consistency: f.consistency,
                    },
                    sourced,
                ));
            }
        }
        out
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

    /// The bank's state as plain records (filters, counters, frontiers), for persistence.
    pub fn record(&self) -> BankRecord {
        let links = &self.model.links;
        BankRecord {
            filters: self
                .measured
                .iter()
                .enumerate()
                .filter_map(|(i, s)| {
                    s.as_ref()
                        .and_then(|s| s.filter.record())
                        .map(|r| (links[i].name.clone(), r))
                })
                .collect(),
            counters: self
                .status
                .iter()
                .enumerate()
                .filter(|(_, s)| s.n_samples > 0)
                .map(|(i, s)| {
                    (
                        links[i].name.clone(),
                        s.n_samples,
                        s.n_outliers,
                        s.n_reinitializations,
                        s.last_time_ns,
                    )
                })
                .collect(),
            frontiers: self
                .frontier_ns
                .iter()
                .enumerate()
                .filter_map(|(i, f)| f.map(|f| (self.model.targets[i].name.clone(), f)))
                .collect(),
            targets: self
                .tracks
                .iter()
                .enumerate()
                .filter_map(|(i, t)| {
                    t.filter
                        .record()
                        .map(|r| (self.model.targets[i].name.clone(), r))
                })
                .collect(),
        }
    }

    /// Restores a recorded state into this (fresh) bank. Entries for links or targets the
    /// installation no longer has, or whose model changed, are skipped and listed in the answer.
    pub fn restore(&mut self, record: &BankRecord) -> Vec<String> {
        let mut skipped = Vec::new();
        for (name, r) in &record.filters {
            let Some(id) = self.model.topology.link_id(name) else {
                skipped.push(format!("link `{name}` is no longer in the installation"));
                continue;
            };
            let Some(slot) = self.measured[id.0].as_mut() else {
                skipped.push(format!("link `{name}` is no longer measured"));
                continue;
            };
            match LinkFilter::restore(*slot.filter.tuning(), r) {
                Ok(f) => {
                    slot.history.clear();
                    slot.history.push_back(f.clone());
                    slot.filter = f;
                }
                Err(e) => skipped.push(format!("link `{name}`: {e}")),
            }
        }
        for (name, n, o, re, last) in &record.counters {
            if let Some(id) = self.model.topology.link_id(name) {
                self.status[id.0] = LinkStatus {
                    n_samples: *n,
                    n_outliers: *o,
                    n_reinitializations: *re,
                    last_time_ns: *last,
                    // Counted since start: groups are not kept across restarts.
                    ..LinkStatus::default()
                };
            }
        }
        for (name, f) in &record.frontiers {
            if let Some(i) = self.model.targets.iter().position(|t| &t.name == name) {
                self.frontier_ns[i] = Some(*f);
            }
        }
        for (name, r) in &record.targets {
            let Some(ti) = self.model.target_id(name) else {
                skipped.push(format!("target `{name}` is no longer in the installation"));
                continue;
            };
            let track = &mut self.tracks[ti.0];
            match LinkFilter::restore(track.base_tuning, r) {
                Ok(f) => {
                    track.history.clear();
                    track.history.push_back(f.clone());
                    track.filter = f;
                }
                Err(e) => skipped.push(format!("target `{name}`: {e}")),
            }
        }
        skipped
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
                systematic_cov: Mat6::zeros(),
                calibration: self.calibration_stamp(target, time_ns),
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
            target_from_base: Some(pose),
            systematic_cov,
            calibration: self.calibration_stamp(target, time_ns),
            age_s,
            consistency: fused.consistency,
            paths_used,
        })
    }
}

/// The stamp of a calibrated link's calibration: its pose and covariance.
fn pose_stamp(c: &PoseCov) -> i64 {
    let t = c.pose.translation.vector;
    let values = [t.x, t.y, t.z]
        .into_iter()
        .chain(c.pose.rotation.coords.iter().copied())
        .chain(c.cov.iter().copied());
    CalibrationStamp::of(values).0
}

/// The stamp of a camera's calibration: its intrinsics and their covariance.
fn camera_stamp(camera: &crate::model::Camera) -> i64 {
    let m = &camera.intrinsics;
    let mut values = vec![m.fx_px, m.fy_px, m.cx_px, m.cy_px];
    values.extend(m.distortion);
    if let Some(c) = &camera.intrinsics_covariance {
        values.extend(c.iter().copied());
    }
    CalibrationStamp::of(values).0
}
