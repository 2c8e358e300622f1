//! Filter models and their tuning, with defaults per model.

use crate::geometry::{ARCSEC_PER_RAD, Twist};

crate::words! {
    /// How a measured link's pose is expected to move.
    pub enum MotionModel("filter model") {
        /// Random walk: constant pose plus process noise.
        Static = "static",
        /// White-noise acceleration of the twist.
        ConstantVelocity = "constant_velocity",
        /// Second-order Gauss-Markov oscillation per axis around a slowly drifting mean.
        Oscillatory = "oscillatory",
    }
}

/// The oscillation of the `oscillatory` model, per axis:
/// `x'' + 2 mu x' + (mu^2 + lambda^2) x = w`, with `lambda = 2 pi / period_s` and
/// `mu = 1 / correlation_time_s`, scaled so that `x` has the given stationary sigmas.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OscillationTuning {
    /// The dominant period (s).
    pub period_s: f64,
    /// How long the oscillation stays coherent (s): the inverse of the damping `mu`.
    pub correlation_time_s: f64,
    /// Stationary standard deviation of the rotation oscillation, per axis (arc-seconds).
    pub rotation_arcsec: [f64; 3],
    /// Stationary standard deviation of the translation oscillation, per axis (mm).
    pub translation_mm: [f64; 3],
}

/// The tuning of one link's filter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FilterTuning {
    /// The model.
    pub model: MotionModel,
    /// `static`, and the drifting mean of `oscillatory`: random-walk density of the rotation
    /// (arc-seconds per square-root second) and translation (mm per square-root second).
    pub random_walk_rotation_arcsec_per_sqrt_s: f64,
    /// See [`Self::random_walk_rotation_arcsec_per_sqrt_s`].
    pub random_walk_translation_mm_per_sqrt_s: f64,
    /// `constant_velocity`: white-noise acceleration density of the rotation
    /// (arc-seconds per second per square-root second).
    pub acceleration_rotation_arcsec_per_s_sqrt_s: f64,
    /// `constant_velocity`: the same for the translation (mm per second per square-root second).
    pub acceleration_translation_mm_per_s_sqrt_s: f64,
    /// `oscillatory`: the oscillation.
    pub oscillation: OscillationTuning,
    /// The innovation gate probability (6 dof chi-square), 0.999 by default.
    pub gate_probability: f64,
    /// After this many consecutive, mutually consistent outliers the filter re-initialises on
    /// them (a real step, such as a bumped station).
    pub reinit_after_outliers: usize,
}

impl FilterTuning {
    /// The defaults of a model: a link that follows real changes within seconds while averaging
    /// away pixel noise at tens of hertz.
    pub fn default_for(model: MotionModel) -> Self {
        Self {
            model,
            random_walk_rotation_arcsec_per_sqrt_s: match model {
                MotionModel::Oscillatory => 0.5,
                _ => 2.0,
            },
            random_walk_translation_mm_per_sqrt_s: match model {
                MotionModel::Oscillatory => 0.005,
                _ => 0.02,
            },
            acceleration_rotation_arcsec_per_s_sqrt_s: 20.0,
            acceleration_translation_mm_per_s_sqrt_s: 0.2,
            oscillation: OscillationTuning {
                period_s: 10.0,
                correlation_time_s: 20.0,
                rotation_arcsec: [60.0; 3],
                translation_mm: [0.5; 3],
            },
            gate_probability: 0.999,
            reinit_after_outliers: 5,
        }
    }

    /// Random-walk spectral density per axis, `[rho (mm^2/s); phi (rad^2/s)]`.
    pub(crate) fn random_walk_density(&self) -> Twist {
        density(
            self.random_walk_translation_mm_per_sqrt_s,
            self.random_walk_rotation_arcsec_per_sqrt_s,
        )
    }

    /// White-noise acceleration density per axis, `[rho (mm^2/s^3); phi (rad^2/s^3)]`.
    pub(crate) fn acceleration_density(&self) -> Twist {
        density(
            self.acceleration_translation_mm_per_s_sqrt_s,
            self.acceleration_rotation_arcsec_per_s_sqrt_s,
        )
    }

    /// Stationary variance of the oscillation per axis, `[rho (mm^2); phi (rad^2)]`.
    pub(crate) fn oscillation_variance(&self) -> Twist {
        let o = &self.oscillation;
        let r = o.rotation_arcsec.map(|s| (s / ARCSEC_PER_RAD).powi(2));
        let t = o.translation_mm.map(|s| s * s);
        Twist::new(t[0], t[1], t[2], r[0], r[1], r[2])
    }

    /// `(mu, lambda)` of the oscillator (1/s, rad/s).
    pub(crate) fn oscillator_rates(&self) -> (f64, f64) {
        (
            1.0 / self.oscillation.correlation_time_s,
            2.0 * std::f64::consts::PI / self.oscillation.period_s,
        )
    }
}

fn density(translation_mm: f64, rotation_arcsec: f64) -> Twist {
    let t = translation_mm * translation_mm;
    let r = (rotation_arcsec / ARCSEC_PER_RAD).powi(2);
    Twist::new(t, t, t, r, r, r)
}

/// Settings of the whole bank.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BankSettings {
    /// A link with no sample for longer than this many expected periods makes its targets
    /// `stale`.
    pub stale_after_periods: f64,
    /// Probability of the redundant-path consistency quantile.
    pub consistency_probability: f64,
    /// How many recent timestamps are kept to assemble measurement groups into raw results.
    pub group_window: usize,
    /// How far apart (ns) the exposures of one measurement group may be; `None`: half the
    /// shortest expected period of the measured links.
    pub group_tolerance_ns: Option<i64>,
}

impl Default for BankSettings {
    fn default() -> Self {
        Self {
            stale_after_periods: 5.0,
            consistency_probability: 0.999,
            group_window: 64,
            group_tolerance_ns: None,
        }
    }
}
