//! A target's own filter, fed by its raw results: its tuning (the most dynamic of its links',
//! or the installation's), the oscillation fitted from the data, and its consistency watched.

use super::*;

/// How many innovations a target's consistency is judged over.
pub(super) const CONSISTENCY_WINDOW: usize = 250;

/// How many innovations a target's consistency needs before it is judged.
pub const CONSISTENCY_JUDGED_FROM: usize = CONSISTENCY_WINDOW / 2;

/// Two-sided probability of the band a target's mean NIS stays in when its filter fits.
pub(super) const CONSISTENCY_PROBABILITY: f64 = 0.999;

/// A target's filter: fed by the target's raw results (see the module docs).
#[derive(Debug, Clone)]
pub(super) struct TargetTrack {
    pub(super) filter: LinkFilter,
    /// Past states, oldest first, each after a fused result or a restart.
    pub(super) history: VecDeque<LinkFilter>,
    /// The tuning the target starts with (the installation's, or the most dynamic of its
    /// links').
    pub(super) base_tuning: FilterTuning,
    /// Whether the oscillation's strengths are fitted from the data.
    pub(super) fit_from_data: bool,
    /// Fits the oscillation from the data (`oscillatory` only).
    pub(super) estimator: Option<MotionEstimator>,
    /// The newest fit in force, if any.
    pub(super) fit: Option<MotionFit>,
    pub(super) consistency: InnovationWindow,
    /// The error terms of the newest raw result fed: where its error comes from.
    pub(super) latest_terms: Option<SourcedPose>,
    /// The time of the newest raw result fed and the filter's random estimate after it: the
    /// budget's. Both outlive a restart, so the newest result's budget is answered until the
    /// next one.
    pub(super) latest_filtered: Option<(i64, PoseCov)>,
}

impl TargetTrack {
    pub(super) fn new(tuning: FilterTuning, fit_from_data: bool) -> Self {
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
    pub(super) fn reset(&mut self) {
        let (terms, filtered) = (self.latest_terms.take(), self.latest_filtered.take());
        *self = Self::new(self.base_tuning, self.fit_from_data);
        self.latest_terms = terms;
        self.latest_filtered = filtered;
    }

    /// Feeds one raw result: its random part (`z`, the samples' noise) is filtered; its
    /// systematic part does not average down and is added back to the filtered result.
    pub(super) fn update(&mut self, time_ns: i64, z: &PoseCov, terms: SourcedPose) -> Disposition {
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
    pub(super) fn view(&self) -> Self {
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
pub(super) fn target_tuning_of(model: &Model, target: TargetId) -> FilterTuning {
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
