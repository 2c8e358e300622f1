//! The filter bank: one filter per measured link; targets evaluated by composing the predicted
//! links of their paths; raw results from measurement groups.

use super::{BankSettings, Disposition, FilterError, LinkFilter, NS_PER_S};
use crate::chain::{Consistency, LinkId, compose_path, fuse};
use crate::config::{Installation, LinkKind};
use crate::geometry::{Mat6, Pose, PoseCov, ReportedSigmas, check_covariance};
use std::collections::{BTreeMap, HashMap};

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
    /// Index of the target in the installation.
    pub target: usize,
    /// The group's time (ns).
    pub time_ns: i64,
    /// `target_from_base` composed from the raw samples.
    pub target_from_base: PoseCov,
    /// Disagreement of redundant paths, where there are several.
    pub consistency: Option<Consistency>,
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
}

/// The state of a target's result.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TargetStatus {
    /// Every link is current and redundant paths agree.
    Ok,
    /// A link on the path has had no sample for longer than its staleness limit.
    Stale,
    /// Redundant paths disagree, or one of them has no data yet.
    Degraded,
    /// Some measured link on every path has had no sample yet.
    Initializing,
    /// The time asked for is after the newest sample: the result is a prediction.
    Predicted,
}

impl TargetStatus {
    /// The name used on the wire.
    pub fn name(self) -> &'static str {
        match self {
            TargetStatus::Ok => "ok",
            TargetStatus::Stale => "stale",
            TargetStatus::Degraded => "degraded",
            TargetStatus::Initializing => "initializing",
            TargetStatus::Predicted => "predicted",
        }
    }
}

/// A target evaluated at a time.
#[derive(Debug, Clone, PartialEq)]
pub struct TargetEstimate {
    /// Index of the target in the installation.
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

/// A measured link's filtered pose at a time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkEstimate {
    /// The link.
    pub link: LinkId,
    /// `parent_from_child` with covariance.
    pub parent_from_child: PoseCov,
}

#[derive(Debug, Clone, Default)]
struct Group {
    samples: HashMap<LinkId, PoseCov>,
    emitted: Vec<bool>,
}

/// One filter per measured link of an installation.
#[derive(Debug, Clone)]
pub struct FilterBank {
    installation: Installation,
    settings: BankSettings,
    filters: Vec<Option<LinkFilter>>,
    calibrations: Vec<Option<PoseCov>>,
    status: Vec<LinkStatus>,
    groups: BTreeMap<i64, Group>,
    /// Per link: the targets whose independent paths use it.
    targets_of_link: Vec<Vec<usize>>,
}

impl FilterBank {
    /// A bank for the installation, every filter uninitialised.
    pub fn new(installation: &Installation) -> Self {
        let n = installation.links.len();
        let mut targets_of_link = vec![Vec::new(); n];
        for (ti, t) in installation.targets.iter().enumerate() {
            for path in &t.resolution.paths {
                for l in path.links() {
                    if !targets_of_link[l.0].contains(&ti) {
                        targets_of_link[l.0].push(ti);
                    }
                }
            }
        }
        Self {
            settings: installation.filter,
            filters: installation
                .links
                .iter()
                .map(|l| match &l.kind {
                    LinkKind::Measured(m) => Some(LinkFilter::new(m.tuning)),
                    LinkKind::Calibrated { .. } => None,
                })
                .collect(),
            calibrations: installation
                .links
                .iter()
                .map(|l| match &l.kind {
                    LinkKind::Calibrated { parent_from_child } => Some(*parent_from_child),
                    LinkKind::Measured(_) => None,
                })
                .collect(),
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
            installation: installation.clone(),
        }
    }

    /// The installation the bank filters.
    pub fn installation(&self) -> &Installation {
        &self.installation
    }

    /// Replaces a calibrated link's pose (a new calibration). Returns false for a measured link.
    pub fn set_calibration(&mut self, link: LinkId, parent_from_child: PoseCov) -> bool {
        match self.calibrations.get_mut(link.0) {
            Some(Some(c)) => {
                *c = parent_from_child;
                true
            }
            _ => false,
        }
    }

    /// The filter of a measured link.
    pub fn filter(&self, link: LinkId) -> Option<&LinkFilter> {
        self.filters.get(link.0).and_then(Option::as_ref)
    }

    /// A link's counters.
    pub fn link_status(&self, link: LinkId) -> &LinkStatus {
        &self.status[link.0]
    }

    /// The measurement covariance of a sample: its own, else the link's default.
    pub fn measurement(&self, sample: &Sample) -> Result<PoseCov, FilterError> {
        let spec = &self.installation.links[sample.link.0];
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
        check_covariance(&z.cov).map_err(|e| FilterError::BadMeasurement {
            link: spec.name.clone(),
            reason: e.to_string(),
        })?;
        if z.cov.cholesky().is_none() {
            return Err(FilterError::BadMeasurement {
                link: spec.name.clone(),
                reason: "it is singular (a measurement is never exact)".into(),
            });
        }
        Ok(z)
    }

    /// Ingests one sample: filters it, and assembles raw results of completed groups.
    pub fn ingest(&mut self, sample: &Sample) -> Result<SampleOutcome, FilterError> {
        let z = self.measurement(sample)?;
        let link = sample.link;
        let Some(filter) = self.filters[link.0].as_mut() else {
            return Err(FilterError::NotMeasured(
                self.installation.links[link.0].name.clone(),
            ));
        };
        let disposition = filter.update(sample.time_ns, &z);
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
        let raw_results = self.add_to_group(link, sample.time_ns, z);
        Ok(SampleOutcome {
            link,
            time_ns: sample.time_ns,
            disposition,
            measurement: z,
            raw_results,
        })
    }

    fn add_to_group(&mut self, link: LinkId, time_ns: i64, z: PoseCov) -> Vec<RawResult> {
        let n_targets = self.installation.targets.len();
        let oldest_kept = self.groups.keys().next().copied();
        if self.groups.len() >= self.settings.group_window
            && oldest_kept.is_some_and(|o| time_ns < o)
        {
            // Older than every group still assembled: it cannot complete one.
            return Vec::new();
        }
        let group = self.groups.entry(time_ns).or_insert_with(|| Group {
            samples: HashMap::new(),
            emitted: vec![false; n_targets],
        });
        group.samples.insert(link, z);
        let mut out = Vec::new();
        for &ti in &self.targets_of_link[link.0] {
            let group = &self.groups[&time_ns];
            if group.emitted[ti] {
                continue;
            }
            let target = &self.installation.targets[ti];
            let mut estimates = Vec::new();
            let mut complete = true;
            for path in &target.resolution.paths {
                let mut missing = false;
                let composed = compose_path(path, |l| match self.calibrations[l.0] {
                    Some(c) => c,
                    None => match group.samples.get(&l) {
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
            if let Some(g) = self.groups.get_mut(&time_ns) {
                g.emitted[ti] = true;
            }
        }
        while self.groups.len() > self.settings.group_window {
            self.groups.pop_first();
        }
        out
    }

    /// A measured link's filtered pose predicted to `time_ns`; `None` before its first sample.
    pub fn link_estimate(
        &self,
        link: LinkId,
        time_ns: i64,
    ) -> Result<Option<PoseCov>, FilterError> {
        match (&self.filters[link.0], &self.calibrations[link.0]) {
            (_, Some(c)) => Ok(Some(*c)),
            (Some(f), None) => match f.predict(time_ns) {
                None => Ok(None),
                Some(Ok(p)) => Ok(Some(p)),
                Some(Err(filter_ns)) => Err(FilterError::BeforeFilterTime {
                    link: self.installation.links[link.0].name.clone(),
                    requested_ns: time_ns,
                    filter_ns,
                }),
            },
            (None, None) => Ok(None),
        }
    }

    /// The newest time any filter of the target's paths has reached (ns).
    pub fn latest_time_ns(&self, target: usize) -> Option<i64> {
        self.installation.targets[target]
            .resolution
            .paths
            .iter()
            .flat_map(|p| p.links())
            .filter_map(|l| self.filters[l.0].as_ref().and_then(LinkFilter::time_ns))
            .max()
    }

    /// Evaluates a target at `time_ns`: predicts every measured link of its paths to that
    /// time, composes each path with covariance and fuses the paths that have data.
    pub fn evaluate(&self, target: usize, time_ns: i64) -> Result<TargetEstimate, FilterError> {
        let spec = self
            .installation
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
                if let (LinkKind::Measured(m), Some(last)) = (
                    &self.installation.links[l.0].kind,
                    self.status[l.0].last_time_ns,
                ) {
                    newest_ns = Some(newest_ns.map_or(last, |n| n.max(last)));
                    let limit_s = self.settings.stale_after_periods / m.expected_rate_hz;
                    if (time_ns - last) as f64 / NS_PER_S > limit_s {
                        stale = true;
                    }
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
