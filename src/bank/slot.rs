//! A measured link's slot in the bank: its filter, its recent past states (so targets can be
//! evaluated at recent times whatever order samples arrive in), its observed rate, and the
//! systematic error its camera's intrinsics give it.

use super::*;

/// How many past states each link keeps, so that targets can be evaluated at recent times
/// whatever order the links' samples arrived in.
pub(super) const LINK_HISTORY: usize = 256;

/// The state of a filter to evaluate `time_ns` from: the current one when it is not newer,
/// else the newest past state at or before that time.
pub(super) fn state_at<'a>(
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
pub(super) fn remember(current: &LinkFilter, past: &mut VecDeque<LinkFilter>, restarted: bool) {
    if restarted {
        past.clear();
    }
    past.push_back(current.clone());
    if past.len() > LINK_HISTORY {
        past.pop_front();
    }
}

/// How many recent sample times each link keeps to estimate its observed rate.
pub(super) const RATE_WINDOW: usize = 64;

/// A measured link's filter and its recent past states.
#[derive(Debug, Clone)]
pub(super) struct MeasuredSlot {
    pub(super) filter: LinkFilter,
    /// Past states, oldest first, each after a fused sample or a restart.
    pub(super) history: VecDeque<LinkFilter>,
    /// Recent sample times, for the observed rate.
    pub(super) recent_times: VecDeque<i64>,
    /// The link's systematic error from its camera's intrinsics (see
    /// [`Model::intrinsics_factor`]) at the pose it was computed for: the camera's index and
    /// the factor. Computed again when the link has moved (see [`SENSITIVITY_MOVE_RAD`]).
    pub(super) intrinsics: Option<(Pose, usize, Factor)>,
    /// Whether the link's camera has an intrinsics covariance (else it is taken as exact).
    pub(super) uses_intrinsics: bool,
}

/// How far a link may turn (rad) or move (a fraction of its distance) before the
/// sensitivity of its pose to its camera's intrinsics is computed again: the sensitivity
/// changes with the geometry by about as much, far below the uncertainty of the covariance it
/// maps.
pub(super) const SENSITIVITY_MOVE_RAD: f64 = 0.01;

impl MeasuredSlot {
    pub(super) fn new(tuning: FilterTuning, uses_intrinsics: bool) -> Self {
        Self {
            filter: LinkFilter::new(tuning),
            history: VecDeque::new(),
            recent_times: VecDeque::new(),
            intrinsics: None,
            uses_intrinsics,
        }
    }

    /// Keeps the intrinsics factor current for a sample at `pose`.
    pub(super) fn refresh_intrinsics(&mut self, model: &Model, link: LinkId, pose: &Pose) {
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
