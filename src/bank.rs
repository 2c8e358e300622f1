//! The filter bank: one filter ([`crate::filter::LinkFilter`]) per measured link of a
//! [`crate::model::Model`]; targets evaluated by composing the predicted
//! links of their paths; raw results from measurement groups.

use crate::chain::{Consistency, LinkId, compose_path, fuse};
use crate::filter::{
    BankSettings, Disposition, FilterError, LinkFilter, LinkFilterRecord, NS_PER_S,
};
use crate::geometry::{Mat6, Pose, PoseCov, ReportedSigmas};
use crate::model::{LinkKind, Model};
use std::collections::{BTreeMap, HashMap, VecDeque};
use std::sync::Arc;

/// How many past states each link keeps, so that targets can be evaluated at recent times
/// whatever order the links' samples arrived in.
const LINK_HISTORY: usize = 256;

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

/// A raw result: the composition of the raw samples of one measurement group.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RawResult {
    /// Index of the target in the model.
    pub target: usize,
    /// The group's time (ns).
    pub time_ns: i64,
    /// `target_from_base` composed from the raw samples.
    pub target_from_base: PoseCov,
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
    pub target: usize,
    /// The time evaluated (ns).
    pub time_ns: i64,
    /// Its status.
    pub status: TargetStatus,
    /// `target_from_base` with covariance; `None` while initialising.
    pub target_from_base: Option<PoseCov>,
    /// Time since the newest sample on the path (s); 0 when evaluated at that sample.
    pub age_s: f64,
    /// Disagreement of redundant paths, where several had data.
    pub consistency: Option<Consistency>,
    /// How many of the target's independent paths had data.
    pub paths_used: usize,
}

/// A link's state in the bank.
#[derive(Debug, Clone, PartialEq)]
pub struct LinkStatus {
    /// Samples ingested (fused, outliers and out-of-order alike).
    pub n_samples: u64,
    /// Samples flagged as outliers.
    pub n_outliers: u64,
    /// Restarts after a run of consistent outliers.
    pub n_reinitializations: u64,
    /// Time of the newest sample (ns).
    pub last_time_ns: Option<i64>,
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

#[derive(Debug, Clone, Default)]
struct Group {
    samples: HashMap<LinkId, PoseCov>,
    emitted: Vec<bool>,
}

/// A measured link's filter and its recent past states.
#[derive(Debug, Clone)]
struct MeasuredSlot {
    filter: LinkFilter,
    /// Past states, oldest first, each after a fused sample or a restart.
    history: VecDeque<LinkFilter>,
    /// Recent sample times, for the observed rate.
    recent_times: VecDeque<i64>,
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
}

/// One filter per measured link of an model.
#[derive(Debug, Clone)]
pub struct FilterBank {
    model: Arc<Model>,
    settings: BankSettings,
    measured: Vec<Option<MeasuredSlot>>,
    /// Per calibrated link: its calibrations, `(valid_from_ns, pose)`, oldest first; the one in
    /// the installation file is valid from the beginning of time.
    calibrations: Vec<Vec<(i64, PoseCov)>>,
    status: Vec<LinkStatus>,
    groups: BTreeMap<i64, Group>,
    /// Per link: the targets whose independent paths use it.
    targets_of_link: Vec<Vec<usize>>,
    /// Per target: the time of the newest filtered result.
    frontier_ns: Vec<Option<i64>>,
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
        for (ti, t) in model.targets.iter().enumerate() {
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
                    LinkKind::Measured(m) => Some(MeasuredSlot {
                        filter: LinkFilter::new(m.tuning),
                        history: VecDeque::new(),
                        recent_times: VecDeque::new(),
                    }),
                    LinkKind::Calibrated { .. } => None,
                })
                .collect(),
            calibrations: model
                .links
                .iter()
                .map(|l| match &l.kind {
                    LinkKind::Calibrated { parent_from_child } => {
                        vec![(i64::MIN, *parent_from_child)]
                    }
                    LinkKind::Measured(_) => Vec::new(),
                })
                .collect(),
            frontier_ns: vec![None; model.targets.len()],
            status: vec![
                LinkStatus {
                    n_samples: 0,
                    n_outliers: 0,
                    n_reinitializations: 0,
                    last_time_ns: None,
                };
                n
            ],
            groups: BTreeMap::new(),
            targets_of_link,
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
                    })
                })
                .collect(),
            calibrations: self.calibrations.clone(),
            status: self.status.clone(),
            groups: BTreeMap::new(),
            targets_of_link: self.targets_of_link.clone(),
            frontier_ns: self.frontier_ns.clone(),
        }
    }

    /// The measurement model the bank filters.
    pub fn model(&self) -> &Model {
        &self.model
    }

    /// Adds a calibration of a calibrated link, valid from `valid_from_ns` (until a later one).
    /// Returns false for a measured link.
    pub fn add_calibration(
        &mut self,
        link: LinkId,
        valid_from_ns: i64,
        parent_from_child: PoseCov,
    ) -> bool {
        match self.calibrations.get_mut(link.0) {
            Some(list) if !list.is_empty() => {
                let at = list.partition_point(|(t, _)| *t <= valid_from_ns);
                list.insert(at, (valid_from_ns, parent_from_child));
                true
            }
            _ => false,
        }
    }

    /// Removes a calibration added with [`Self::add_calibration`] (a write that did not commit).
    pub fn remove_calibration(&mut self, link: LinkId, valid_from_ns: i64) {
        if let Some(list) = self.calibrations.get_mut(link.0)
            && let Some(i) = list.iter().rposition(|(t, _)| *t == valid_from_ns)
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
            *s = LinkStatus {
                n_samples: 0,
                n_outliers: 0,
                n_reinitializations: 0,
                last_time_ns: None,
            };
        }
        self.frontier_ns.iter_mut().for_each(|f| *f = None);
        self.groups.clear();
        self.restore(record)
    }

    /// The calibration of a calibrated link in force at `time_ns`.
    pub fn calibration_at(&self, link: LinkId, time_ns: i64) -> Option<PoseCov> {
        let list = self.calibrations.get(link.0)?;
        let at = list.partition_point(|(t, _)| *t <= time_ns);
        list.get(at.checked_sub(1)?).map(|(_, p)| *p)
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
    pub fn targets_of_link(&self, link: LinkId) -> &[usize] {
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
    pub fn target_liveness(&self, target: usize, time_ns: i64, tolerance_s: f64) -> TargetLiveness {
        let mut worst: Option<(LinkId, LinkLag)> = None;
        let Some(spec) = self.model.targets.get(target) else {
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
        let disposition = slot.filter.update(sample.time_ns, &z);
        if matches!(
            disposition,
            Disposition::Initialized
                | Disposition::Fused { .. }
                | Disposition::Reinitialized { .. }
        ) {
            if matches!(disposition, Disposition::Reinitialized { .. }) {
                // The past states describe the link before the step: evaluating an older time
                // through them would mix the two.
                slot.history.clear();
            }
            slot.history.push_back(slot.filter.clone());
            if slot.history.len() > LINK_HISTORY {
                slot.history.pop_front();
            }
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
        let (raw_results, needs_stored_group) = match self.add_to_group(link, sample.time_ns, z) {
            Some(r) => (r, false),
            None => (Vec::new(), true),
        };
        let mut filtered_results = Vec::new();
        for ti in self.targets_of_link[link.0].clone() {
            let Some(frontier) = self.frontier(ti) else {
                continue;
            };
            if self.frontier_ns[ti].is_some_and(|f| frontier <= f) {
                continue;
            }
            if let Ok(estimate) = self.evaluate(ti, frontier) {
                self.frontier_ns[ti] = Some(frontier);
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
    pub fn frontier(&self, target: usize) -> Option<i64> {
        let spec = &self.model.targets[target];
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

    /// Adds a sample to its measurement group and returns the raw results it completes, or
    /// `None` when the sample is older than every group kept in memory.
    fn add_to_group(&mut self, link: LinkId, time_ns: i64, z: PoseCov) -> Option<Vec<RawResult>> {
        let n_targets = self.model.targets.len();
        let oldest_kept = self.groups.keys().next().copied();
        if self.groups.len() >= self.settings.group_window
            && oldest_kept.is_some_and(|o| time_ns < o)
        {
            // Older than every group still assembled: only the store can complete it.
            return None;
        }
        let group = self.groups.entry(time_ns).or_insert_with(|| Group {
            samples: HashMap::new(),
            emitted: vec![false; n_targets],
        });
        group.samples.insert(link, z);
        let group = &self.groups[&time_ns];
        let out = self.compose_group(link, time_ns, &group.samples, &group.emitted);
        if let Some(g) = self.groups.get_mut(&time_ns) {
            for r in &out {
                g.emitted[r.target] = true;
            }
        }
        while self.groups.len() > self.settings.group_window {
            self.groups.pop_first();
        }
        Some(out)
    }

    /// The raw results of a measurement group given all its samples (`samples`: the
    /// measurements of every link at `time_ns`, as [`Self::measurement`] makes them), for the
    /// targets on `link`'s paths that the group completes. For groups too old for memory
    /// ([`SampleOutcome::needs_stored_group`]): the caller reads the other links' samples of
    /// that time from the store.
    pub fn raw_results_of_group(
        &self,
        link: LinkId,
        time_ns: i64,
        samples: &HashMap<LinkId, PoseCov>,
    ) -> Vec<RawResult> {
        let none = vec![false; self.model.targets.len()];
        self.compose_group(link, time_ns, samples, &none)
    }

    /// Composes, for each target on `link`'s paths not yet `emitted`, the raw result of a
    /// group whose every path is complete in `samples`.
    fn compose_group(
        &self,
        link: LinkId,
        time_ns: i64,
        samples: &HashMap<LinkId, PoseCov>,
        emitted: &[bool],
    ) -> Vec<RawResult> {
        let mut out = Vec::new();
        for &ti in &self.targets_of_link[link.0] {
            if emitted[ti] {
                continue;
            }
            let target = &self.model.targets[ti];
            let mut estimates = Vec::new();
            let mut complete = true;
            for path in &target.resolution.paths {
                let mut missing = false;
                let composed = compose_path(path, |l| match self.calibration_at(l, time_ns) {
                    Some(c) => c,
                    None => match samples.get(&l) {
                        Some(s) => *s,
                        None => {
                            missing = true;
                            PoseCov::identity()
                        }
                    },
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
            if let Ok(f) = fuse(&estimates, self.settings.consistency_probability) {
                out.push(RawResult {
                    target: ti,
                    time_ns,
                    target_from_base: f.estimate,
                    consistency: f.consistency,
                });
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
        let source = if time_ns >= current {
            Some(&slot.filter)
        } else {
            slot.history
                .iter()
                .rev()
                .find(|f| f.time_ns().is_some_and(|t| t <= time_ns))
        };
        match source.and_then(|f| f.predict(time_ns)) {
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
    pub fn latest_time_ns(&self, target: usize) -> Option<i64> {
        self.model.targets[target]
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
        for &ti in &self.targets_of_link[link.0] {
            self.frontier_ns[ti] = None;
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
                };
            }
        }
        for (name, f) in &record.frontiers {
            if let Some(i) = self.model.targets.iter().position(|t| &t.name == name) {
                self.frontier_ns[i] = Some(*f);
            }
        }
        skipped
    }

    /// Evaluates a target at `time_ns`: predicts every measured link of its paths to that
    /// time, composes each path with covariance and fuses the paths that have data.
    pub fn evaluate(&self, target: usize, time_ns: i64) -> Result<TargetEstimate, FilterError> {
        let spec = self
            .model
            .targets
            .get(target)
            .ok_or_else(|| FilterError::UnknownTarget(target.to_string()))?;
        let mut estimates = Vec::new();
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
                let mut it = links.into_iter();
                estimates.push(compose_path(path, |_| {
                    it.next().unwrap_or_else(PoseCov::identity)
                }));
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
            target_from_base: Some(fused.estimate),
            age_s,
            consistency: fused.consistency,
            paths_used,
        })
    }
}
