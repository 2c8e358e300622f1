//! Per-link error-state Kalman filters on SE(3) (the bank that evaluates targets from them is
//! [`crate::bank`]).
//!
//! Each measured link has its own filter (`docs/interface.md`, "Filtering"), because each link has its own
//! camera, rate and noise. The state is the link pose on SE(3) (and, for the dynamic models,
//! rates); the error state is a left perturbation as everywhere in the core:
//!
//! * `static`: random walk, `T` constant plus process noise (tunnels, slow structures);
//! * `constant_velocity`: `T <- Exp(nu dt) T` with white-noise acceleration of the twist `nu`;
//! * `oscillatory`: `T = Exp(x) M`, a slowly drifting mean `M` (random walk) and per axis a
//!   second-order Gauss-Markov oscillation `x'' + 2 mu x' + (mu^2 + lambda^2) x = w` (ship hull
//!   flexure: static plus wave-driven dynamic flexure).
//!
//! Time steps are irregular: process noise is discretised for the actual `dt` (closed form for
//! the random walk and the white-noise acceleration, Van Loan for the oscillator). Updates gate
//! the innovation `y = Log(Z * T^-1)` with a 6-dof chi-square test; a sample over the gate is an
//! outlier, kept and reported but not fused. A run of mutually consistent outliers is a real
//! step (a bumped station): the filter re-initialises on it and says so. The covariance update
//! is in Joseph form.
//!
//! **Out-of-order samples.** A sample older than the filter's time is not fused (a Kalman filter
//! cannot take back the predictions it has made since); it is reported as
//! [`Disposition::OutOfOrder`] so that the caller stores it as raw data. A sample at exactly the
//! filter's time is fused as a second measurement of that instant.
//!
//! Time is integer nanoseconds of the measurement, never the wall clock.

mod adapt;
mod kalman;
mod link;
mod tuning;

pub use adapt::{Bounds, InnovationReport, InnovationWindow, MotionEstimator, MotionFit};

pub use link::{
    CV_RATE_PRIOR_S, Disposition, DispositionKind, LinkFilter, LinkFilterRecord, OutlierRecord,
};
pub use tuning::{BankSettings, FilterTuning, MotionModel, OscillationTuning};

/// Errors of the filtering layer.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FilterError {
    /// The link is not a measured link of the installation.
    #[error("`{0}` is not a measured link")]
    NotMeasured(String),
    /// A target that the installation does not have.
    #[error("unknown target `{0}`")]
    UnknownTarget(String),
    /// A filter asked for a time before its state (filters do not run backwards).
    #[error("time {requested_ns} ns is before the filter time {filter_ns} ns of link `{link}`")]
    BeforeFilterTime {
        /// The link.
        link: String,
        /// The requested time.
        requested_ns: i64,
        /// The filter's time.
        filter_ns: i64,
    },
    /// A measurement covariance that cannot be used.
    #[error("measurement covariance of `{link}` is unusable: {reason}")]
    BadMeasurement {
        /// The link.
        link: String,
        /// Why.
        reason: String,
    },
    /// A chain error while composing.
    #[error(transparent)]
    Chain(#[from] crate::chain::ChainError),
}

/// Nanoseconds per second.
pub const NS_PER_S: f64 = 1e9;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bank::TargetStatus;

    /// Every stored name reads back as what was stored, and nothing else reads at all.
    #[test]
    fn stored_vocabularies_round_trip_and_refuse_unknown_names() {
        for &s in TargetStatus::ALL {
            assert_eq!(TargetStatus::parse(s.name()), Some(s));
        }
        for &k in DispositionKind::ALL {
            assert_eq!(DispositionKind::parse(k.name()), Some(k));
        }
        let names: std::collections::HashSet<_> =
            TargetStatus::ALL.iter().map(|s| s.name()).collect();
        assert_eq!(names.len(), TargetStatus::ALL.len(), "names are distinct");
        for unknown in ["", "OK", "fine", "out-of-order"] {
            assert_eq!(TargetStatus::parse(unknown), None);
            assert_eq!(DispositionKind::parse(unknown), None);
        }
    }
}
