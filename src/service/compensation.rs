//! A target's result as a compensation answers it, wherever it comes from: the newest filtered
//! result judged now on the server's clock, the filters predicted to a later time, or the
//! stored results interpolated at a past one (on this service's store or a fleet site's copy).
//! The HTTP layer, the event stream and the plant's outputs shape the same [`Evaluated`].

use super::{Service, ServiceError};
use crate::bank::{ResultSource, TargetEstimate, TargetStatus};
use crate::clock::format_ns;
use crate::deformation::{Deformation, MeasuredPose, ReferenceVersion};
use crate::model::TargetId;

crate::words! {
    /// Where a compensation's value comes from.
    pub enum CompensationSource("compensation source") {
        /// The newest filtered result.
        Live = "live",
        /// The filters predicted to a later time.
        Predicted = "predicted",
        /// Stored results, interpolated.
        History = "history",
    }
}

/// A target's result to answer, wherever it came from.
#[derive(Debug, Clone)]
pub struct Evaluated {
    /// Its time; none before the first result.
    pub time_ns: Option<i64>,
    /// The target's status at that time.
    pub status: TargetStatus,
    /// Seconds from the result's time to now on the server's clock.
    pub age_s: Option<f64>,
    /// Where it came from.
    pub source: CompensationSource,
    /// `G_from_B` with its whole covariance, its systematic part and its calibrations.
    pub estimate: Option<MeasuredPose>,
    /// Redundant paths' agreement, where several were fused.
    pub consistency: Option<crate::chain::Consistency>,
}

impl Evaluated {
    /// No result yet.
    pub fn none(source: CompensationSource) -> Self {
        Evaluated {
            time_ns: None,
            status: TargetStatus::Initializing,
            age_s: None,
            source,
            estimate: None,
            consistency: None,
        }
    }

    /// A stored result as it was.
    pub fn stored(r: &crate::store::StoredResult, source: CompensationSource) -> Self {
        Evaluated {
            time_ns: Some(r.time_ns),
            status: r.status,
            age_s: Some(r.age_s),
            source,
            estimate: Some(r.estimate),
            consistency: None,
        }
    }

    /// An estimate of the filter bank as it was evaluated.
    pub fn estimated(e: &TargetEstimate, source: CompensationSource) -> Self {
        Evaluated {
            time_ns: Some(e.time_ns),
            status: e.status,
            age_s: Some(e.age_s),
            source,
            estimate: e.target_from_base,
            consistency: e.consistency,
        }
    }

    /// The deformation against `reference` (none without a result or a reference).
    pub fn deformation(&self, reference: Option<&ReferenceVersion>) -> Option<Deformation> {
        Some(Deformation::new(
            &reference?.reference,
            self.estimate.as_ref()?,
        ))
    }

    /// Target `ti`'s stored filtered results in `store` at `at_ns`, interpolated between the
    /// two around it; not found before the first (`name` names the target in the message).
    pub async fn from_history(
        store: &crate::store::Store,
        ti: TargetId,
        name: &str,
        at_ns: i64,
    ) -> Result<Evaluated, ServiceError> {
        let (before, after) = store
            .results_around(ti, ResultSource::Filtered, at_ns)
            .await?;
        let Some(before) = before else {
            return Err(ServiceError::NotFound(format!(
                "target `{name}` has no filtered result at or before {}",
                format_ns(at_ns)
            )));
        };
        // The pose and its whole covariance interpolated; the systematic part and the
        // calibrations are the earlier result's.
        let estimate = match after {
            Some(after) if before.time_ns < at_ns => {
                let a = (at_ns - before.time_ns) as f64 / (after.time_ns - before.time_ns) as f64;
                MeasuredPose {
                    whole: before.estimate.whole.interpolate(&after.estimate.whole, a),
                    ..before.estimate
                }
            }
            _ => before.estimate,
        };
        Ok(Evaluated {
            time_ns: Some(at_ns),
            estimate: Some(estimate),
            ..Evaluated::stored(&before, CompensationSource::History)
        })
    }
}

impl Service {
    /// A live result of target `ti` judged now on the server's clock (status `stale` when a
    /// link of the target stopped, the age from the result's time to now).
    pub fn evaluate_live(&self, ti: TargetId, estimate: &TargetEstimate) -> Evaluated {
        let now = self.snapshot().judge(
            ti,
            Some(estimate),
            self.now_ns(),
            self.installation().server.clock_tolerance_s,
        );
        Evaluated {
            status: now.status,
            age_s: now.age_s,
            ..Evaluated::estimated(estimate, CompensationSource::Live)
        }
    }
}
