//! Tuning from the data: the strengths of a motion model estimated from the measurements
//! themselves, and the filter's own consistency watched.
//!
//! [`MotionEstimator`] keeps a window of measured poses (each as its left perturbation
//! `Log(Z * A^-1)` about an anchor `A`, with its covariance) and refits, every few seconds, per
//! axis:
//!
//! * the **oscillation's sigma**: the variance of the series about a straight line (the slow
//!   drift removed), less the measurements' own mean variance (noise that the filter already
//!   knows), so `sigma^2 = var(x - trend) - mean(R_ii)`;
//! * the **period**: from the series' autocorrelation at a lag of a second,
//!   `rho(tau) = c(tau) / sigma^2` (noise is independent between groups, so it is not in
//!   `c(tau)`), and `rho = cos(2 pi tau / period)` for an oscillation;
//! * the **drift**: the trend's slope `s`, as the random walk whose spread over the window `W`
//!   matches it (`q = s^2 W`).
//!
//! Every figure is bounded ([`Bounds`]) so that no window, however odd, makes a filter that
//! cannot follow or cannot average. [`InnovationWindow`] keeps the normalised innovations of the
//! filter's updates over a window and says when their mean leaves the chi-square band that a
//! filter that fits its data stays in.
//!
//! Pure: times are the measurements' (ns), never the wall clock.

use super::tuning::{FilterTuning, OscillationTuning};
use crate::chain::chi_square_quantile;
use crate::geometry::{ARCSEC_PER_RAD, Pose, PoseCov, Twist, se3_log};
use std::collections::VecDeque;

/// How much data a fit uses and how often it is made.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bounds {
    /// The window (s).
    pub window_s: f64,
    /// The first fit waits for this much data (s).
    pub min_data_s: f64,
    /// A new fit every (s).
    pub refit_every_s: f64,
    /// Period range (s).
    pub period_s: (f64, f64),
    /// Oscillation sigma range, rotation (arc-seconds).
    pub rotation_arcsec: (f64, f64),
    /// Oscillation sigma range, translation (mm).
    pub translation_mm: (f64, f64),
    /// Drift range, rotation (arc-seconds per square-root second).
    pub drift_rotation_arcsec_per_sqrt_s: (f64, f64),
    /// Drift range, translation (mm per square-root second).
    pub drift_translation_mm_per_sqrt_s: (f64, f64),
}

impl Default for Bounds {
    fn default() -> Self {
        Self {
            window_s: 60.0,
            min_data_s: 20.0,
            refit_every_s: 5.0,
            period_s: (2.0, 60.0),
            rotation_arcsec: (0.5, 3600.0),
            translation_mm: (0.005, 50.0),
            drift_rotation_arcsec_per_sqrt_s: (0.01, 20.0),
            drift_translation_mm_per_sqrt_s: (1e-4, 0.2),
        }
    }
}

/// One fit of the motion's strengths.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionFit {
    /// The oscillation.
    pub oscillation: OscillationTuning,
    /// Random walk of the mean, rotation (arc-seconds per square-root second).
    pub drift_rotation_arcsec_per_sqrt_s: f64,
    /// Random walk of the mean, translation (mm per square-root second).
    pub drift_translation_mm_per_sqrt_s: f64,
    /// The measurement time of the fit (ns).
    pub time_ns: i64,
    /// How many measurements it used.
    pub samples: usize,
}

impl MotionFit {
    /// `tuning` with this fit's strengths.
    pub fn applied_to(&self, tuning: &FilterTuning) -> FilterTuning {
        FilterTuning {
            oscillation: OscillationTuning {
                correlation_time_s: tuning.oscillation.correlation_time_s,
                ..self.oscillation
            },
            random_walk_rotation_arcsec_per_sqrt_s: self.drift_rotation_arcsec_per_sqrt_s,
            random_walk_translation_mm_per_sqrt_s: self.drift_translation_mm_per_sqrt_s,
            ..*tuning
        }
    }
}

/// Estimates a pose's motion strengths from its measurements (see the module docs).
#[derive(Debug, Clone)]
pub struct MotionEstimator {
    bounds: Bounds,
    anchor: Option<Pose>,
    /// `(time_ns, x about the anchor, measurement variances)`.
    window: VecDeque<(i64, Twist, Twist)>,
    last_fit_ns: Option<i64>,
}

impl MotionEstimator {
    /// An empty estimator.
    pub fn new(bounds: Bounds) -> Self {
        Self {
            bounds,
            anchor: None,
            window: VecDeque::new(),
            last_fit_ns: None,
        }
    }

    /// Forgets every measurement (a filter that restarted on a step).
    pub fn clear(&mut self) {
        self.anchor = None;
        self.window.clear();
        self.last_fit_ns = None;
    }

    /// Adds a measurement; returns a new fit when one is due and the window holds enough.
    pub fn push(&mut self, time_ns: i64, z: &PoseCov) -> Option<MotionFit> {
        if self.window.back().is_some_and(|(t, _, _)| time_ns <= *t) {
            return None;
        }
        let anchor = *self.anchor.get_or_insert(z.pose);
        let x = se3_log(&(z.pose * anchor.inverse()));
        if !x.iter().all(|v| v.is_finite()) {
            return None;
        }
        self.window.push_back((time_ns, x, z.cov.diagonal()));
        let keep_from = time_ns - (self.bounds.window_s * 1e9) as i64;
        while self.window.front().is_some_and(|(t, _, _)| *t < keep_from) {
            self.window.pop_front();
        }
        let first = self.window.front()?.0;
        let span_s = (time_ns - first) as f64 / 1e9;
        if span_s < self.bounds.min_data_s {
            return None;
        }
        if self
            .last_fit_ns
            .is_some_and(|t| ((time_ns - t) as f64 / 1e9) < self.bounds.refit_every_s)
        {
            return None;
        }
        let fit = self.fit(time_ns)?;
        self.last_fit_ns = Some(time_ns);
        Some(fit)
    }

    fn fit(&self, time_ns: i64) -> Option<MotionFit> {
        let n = self.window.len();
        if n < 16 {
            return None;
        }
        let t0 = self.window.front()?.0;
        let ts: Vec<f64> = self
            .window
            .iter()
            .map(|(t, _, _)| (t - t0) as f64 / 1e9)
            .collect();
        let span_s = ts[n - 1];
        // The lag of the autocorrelation: a second, in samples at the window's mean rate.
        let dt_mean = span_s / (n - 1) as f64;
        let lag = ((1.0 / dt_mean).round() as usize).clamp(1, n / 4);
        let tau_s = lag as f64 * dt_mean;
        let t_mean = ts.iter().sum::<f64>() / n as f64;
        let t_var = ts.iter().map(|t| (t - t_mean).powi(2)).sum::<f64>();
        let b = &self.bounds;
        let mut sigma = [0.0; 6];
        let mut slope = [0.0; 6];
        let mut periods: Vec<(f64, f64)> = Vec::new();
        for axis in 0..6 {
            let xs: Vec<f64> = self.window.iter().map(|(_, x, _)| x[axis]).collect();
            let x_mean = xs.iter().sum::<f64>() / n as f64;
            let s = ts
                .iter()
                .zip(&xs)
                .map(|(t, x)| (t - t_mean) * (x - x_mean))
                .sum::<f64>()
                / t_var.max(f64::MIN_POSITIVE);
            let d: Vec<f64> = ts
                .iter()
                .zip(&xs)
                .map(|(t, x)| x - x_mean - s * (t - t_mean))
                .collect();
            let var_total = d.iter().map(|v| v * v).sum::<f64>() / n as f64;
            let noise = self.window.iter().map(|(_, _, r)| r[axis]).sum::<f64>() / n as f64;
            let var_x = (var_total - noise).max(0.0);
            let c_tau = d.iter().zip(&d[lag..]).map(|(a, b)| a * b).sum::<f64>() / (n - lag) as f64;
            // Axes whose oscillation stands clear of the noise say what the period is.
            if var_x > 3.0 * noise && var_x > 0.0 {
                let rho = (c_tau / var_x).clamp(-1.0, 1.0);
                let omega = rho.acos() / tau_s;
                if omega > 0.0 {
                    periods.push((
                        2.0 * std::f64::consts::PI / omega,
                        var_x / noise.max(1e-300),
                    ));
                }
            }
            sigma[axis] = var_x.sqrt();
            slope[axis] = s;
        }
        let period_s = if periods.is_empty() {
            // Nothing stands out of the noise: the middle of the range.
            (b.period_s.0 * b.period_s.1).sqrt()
        } else {
            // The median, weighted by how far each axis stands out of the noise.
            periods.sort_by(|a, b| a.0.total_cmp(&b.0));
            let total: f64 = periods.iter().map(|p| p.1).sum();
            let mut acc = 0.0;
            periods
                .iter()
                .find(|p| {
                    acc += p.1;
                    acc >= total / 2.0
                })
                .map_or(periods[0].0, |p| p.0)
        }
        .clamp(b.period_s.0, b.period_s.1);
        let clamp = |v: f64, r: (f64, f64)| v.clamp(r.0, r.1);
        let window_s = span_s.max(1.0);
        let drift = |axes: std::ops::Range<usize>| {
            axes.map(|i| slope[i] * slope[i] * window_s)
                .fold(0.0f64, f64::max)
                .sqrt()
        };
        Some(MotionFit {
            oscillation: OscillationTuning {
                period_s,
                correlation_time_s: f64::NAN,
                rotation_arcsec: std::array::from_fn(|i| {
                    clamp(sigma[3 + i] * ARCSEC_PER_RAD, b.rotation_arcsec)
                }),
                translation_mm: std::array::from_fn(|i| clamp(sigma[i], b.translation_mm)),
            },
            drift_rotation_arcsec_per_sqrt_s: clamp(
                drift(3..6) * ARCSEC_PER_RAD,
                b.drift_rotation_arcsec_per_sqrt_s,
            ),
            drift_translation_mm_per_sqrt_s: clamp(drift(0..3), b.drift_translation_mm_per_sqrt_s),
            time_ns,
            samples: n,
        })
    }
}

/// The normalised innovations of a filter over a window, judged against their chi-square band.
#[derive(Debug, Clone)]
pub struct InnovationWindow {
    dof: usize,
    capacity: usize,
    probability: f64,
    window: VecDeque<f64>,
}

/// What [`InnovationWindow`] says of its window.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InnovationReport {
    /// Mean normalised innovation squared over the window (the degrees of freedom expected).
    pub mean_nis: f64,
    /// How many innovations.
    pub samples: usize,
    /// The band of the mean that a fitting filter stays in, at the configured probability.
    pub band: (f64, f64),
}

impl InnovationReport {
    /// True when the mean is inside its band (or the window is too short to say).
    pub fn fits(&self) -> bool {
        self.samples < 2 || (self.band.0..=self.band.1).contains(&self.mean_nis)
    }
}

impl InnovationWindow {
    /// A window of `capacity` innovations of `dof` degrees of freedom; the band holds with
    /// `probability` (two-sided).
    pub fn new(dof: usize, capacity: usize, probability: f64) -> Self {
        Self {
            dof,
            capacity: capacity.max(1),
            probability,
            window: VecDeque::new(),
        }
    }

    /// Adds an innovation's NIS.
    pub fn push(&mut self, nis: f64) {
        if !nis.is_finite() {
            return;
        }
        self.window.push_back(nis);
        while self.window.len() > self.capacity {
            self.window.pop_front();
        }
    }

    /// Forgets every innovation.
    pub fn clear(&mut self) {
        self.window.clear();
    }

    /// The window's mean and band.
    pub fn report(&self) -> InnovationReport {
        let n = self.window.len();
        let mean = if n == 0 {
            f64::NAN
        } else {
            self.window.iter().sum::<f64>() / n as f64
        };
        let k = n.max(1);
        let tail = (1.0 - self.probability) / 2.0;
        let band = (
            chi_square_quantile(self.dof * k, tail) / k as f64,
            chi_square_quantile(self.dof * k, 1.0 - tail) / k as f64,
        );
        InnovationReport {
            mean_nis: mean,
            samples: n,
            band,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Mat6, se3_exp};
    use rand::SeedableRng;
    use rand::rngs::StdRng;
    use rand_distr::{Distribution, Normal};

    /// An oscillation of known sigma and period, measured with known noise, is recovered
    /// within the spread a minute of data allows.
    #[test]
    fn an_oscillation_of_known_strength_and_period_is_recovered() {
        let mut rng = StdRng::seed_from_u64(7);
        let (period, sigma_as, noise_as) = (10.0, 80.0, 15.0);
        let noise = Normal::new(0.0, noise_as / ARCSEC_PER_RAD).unwrap();
        // Per axis a sinusoid of sigma `sigma_as` (amplitude sqrt(2) sigma) and its own phase.
        let amplitude = sigma_as * 2f64.sqrt() / ARCSEC_PER_RAD;
        let phases = [0.3, 1.9, 4.0];
        let r = (noise_as / ARCSEC_PER_RAD).powi(2);
        let cov = Mat6::from_diagonal(&Twist::new(0.01, 0.01, 0.01, r, r, r));
        let mut est = MotionEstimator::new(Bounds::default());
        let mut fits = Vec::new();
        // Ten minutes: each fit sees a minute.
        for k in 0..15_000 {
            let t = k as f64 * 0.04;
            let mut xi = Twist::zeros();
            for (i, phase) in phases.iter().enumerate() {
                xi[3 + i] = amplitude * (std::f64::consts::TAU * t / period + phase).sin()
                    + noise.sample(&mut rng);
            }
            let z = PoseCov {
                pose: se3_exp(&xi),
                cov,
            };
            if let Some(f) = est.push((t * 1e9) as i64, &z) {
                fits.push(f);
            }
        }
        assert!(fits.len() > 100, "{} fits", fits.len());
        let mean =
            |f: &dyn Fn(&MotionFit) -> f64| fits.iter().map(f).sum::<f64>() / fits.len() as f64;
        let sigma = mean(&|f| f.oscillation.rotation_arcsec.iter().sum::<f64>() / 3.0);
        let period_fit = mean(&|f| f.oscillation.period_s);
        // A minute holds six whole periods: the fit's sigma is within 5 %, its period within
        // 10 % (the lag of a second sees a tenth of a period).
        assert!(
            (sigma / sigma_as - 1.0).abs() < 0.05,
            "sigma {sigma} against {sigma_as}"
        );
        assert!(
            (period_fit / period - 1.0).abs() < 0.1,
            "period {period_fit} against {period}"
        );
        for f in &fits {
            assert!(f.oscillation.period_s >= 2.0 && f.oscillation.period_s <= 60.0);
        }
    }

    /// Pure noise about a fixed pose: the oscillation found is at the floor of its bounds, not
    /// an invented motion.
    #[test]
    fn noise_alone_gives_an_oscillation_at_the_floor() {
        let mut rng = StdRng::seed_from_u64(3);
        let noise = Normal::new(0.0, 20.0 / ARCSEC_PER_RAD).unwrap();
        let r = (20.0 / ARCSEC_PER_RAD).powi(2);
        let cov = Mat6::from_diagonal(&Twist::new(0.04, 0.04, 0.04, r, r, r));
        let tnoise = Normal::new(0.0, 0.2).unwrap();
        let mut est = MotionEstimator::new(Bounds::default());
        let mut worst: f64 = 0.0;
        for k in 0..5000 {
            let xi = Twist::new(
                tnoise.sample(&mut rng),
                tnoise.sample(&mut rng),
                tnoise.sample(&mut rng),
                noise.sample(&mut rng),
                noise.sample(&mut rng),
                noise.sample(&mut rng),
            );
            let z = PoseCov {
                pose: se3_exp(&xi),
                cov,
            };
            if let Some(f) = est.push(k * 40_000_000, &z) {
                worst = f
                    .oscillation
                    .rotation_arcsec
                    .iter()
                    .fold(worst, |a, b| a.max(*b));
            }
        }
        // The noise variance's estimate over 1500 samples scatters by sqrt(2/1500) of it: an
        // oscillation below sqrt(4.5 sqrt(2/1500)) of the noise (8 of 20 arc-seconds), the
        // largest excess of a few hundred fits, cannot be told from noise. Nothing above.
        let limit = 20.0 * (4.5 * (2.0f64 / 1500.0).sqrt()).sqrt();
        assert!(
            worst < limit,
            "invented {worst} arc-seconds of oscillation (limit {limit})"
        );
    }

    /// The mean NIS of a filter that fits stays in its band; one whose innovations are twice
    /// their predicted size leaves it.
    #[test]
    fn consistency_band_holds_for_chi_square_and_refuses_inflated_innovations() {
        let mut rng = StdRng::seed_from_u64(11);
        let normal = Normal::new(0.0, 1.0).unwrap();
        let mut good = InnovationWindow::new(6, 250, 0.999);
        let mut bad = InnovationWindow::new(6, 250, 0.999);
        for _ in 0..1000 {
            let nis: f64 = (0..6)
                .map(|_| {
                    let v: f64 = normal.sample(&mut rng);
                    v * v
                })
                .sum();
            good.push(nis);
            bad.push(4.0 * nis);
        }
        let g = good.report();
        assert!(g.fits(), "{g:?}");
        assert!(
            (g.band.0 - 5.0).abs() < 0.6 && (g.band.1 - 7.05).abs() < 0.6,
            "{g:?}"
        );
        assert!(!bad.report().fits());
    }
}
