//! Tuning from the data: the strengths of a motion model estimated from the measurements
//! themselves, and the filter's own consistency watched.
//!
//! [`MotionEstimator`] keeps a window (180 s) of measured poses (each as its left perturbation
//! `Log(Z * A^-1)` about an anchor `A`, with its covariance) and refits, every few seconds, per
//! axis:
//!
//! * the **oscillation's sigma**: the covariance of neighbouring values of the series about a
//!   straight line (the slow drift removed), through the fitted oscillator's correlation over
//!   one step, `sigma^2 = c(dt) / rho(dt)`: measurement noise is independent between groups,
//!   so it is not in `c(dt)`, and an error of the measurements' own sigmas does not leak into
//!   it (it would into `var(x) - mean(R)`, which on a noisy axis is a small difference of
//!   large numbers);
//! * the **period and correlation time**: from the series' autocorrelation at lags of 0.5 to
//!   4 s, `rho(tau) = c(tau) / sigma^2` (noise is independent between groups, so it is not in
//!   `c(tau)`), pooled over the axes that stand out of the noise, fitted by the oscillator's
//!   own `rho(tau) = exp(-mu tau) (cos(lambda tau) + mu / lambda sin(lambda tau))` (the
//!   damping sets how much of the motion a filter cannot predict);
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
    /// Correlation time range (s): `1 / mu`, how long the oscillation keeps its phase.
    pub correlation_time_s: (f64, f64),
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
            window_s: 180.0,
            min_data_s: 20.0,
            refit_every_s: 5.0,
            period_s: (2.0, 60.0),
            correlation_time_s: (2.0, 200.0),
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
            oscillation: self.oscillation,
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
        // The autocorrelation's lags: every half second up to four, in samples at the
        // window's mean rate.
        let dt_mean = span_s / (n - 1) as f64;
        let lags: Vec<usize> = (1..=8)
            .map(|j| ((0.5 * j as f64 / dt_mean).round() as usize).clamp(1, n / 4))
            .collect();
        let t_mean = ts.iter().sum::<f64>() / n as f64;
        let t_var = ts.iter().map(|t| (t - t_mean).powi(2)).sum::<f64>();
        let b = &self.bounds;
        let mut lag1_c = [0.0; 6];
        let mut slope = [0.0; 6];
        // Pooled over the axes that stand out of the noise: sum of c(tau_j), sum of var_x.
        let mut pooled_c = vec![0.0; lags.len()];
        let mut pooled_var = 0.0;
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
            let noise = self.window.iter().map(|(_, _, r)| r[axis]).sum::<f64>() / n as f64;
            // The covariance of neighbouring results: the motion's variance, to the few
            // parts in a thousand the motion changes in one step, and free of the noise
            // (independent between groups), so no error of the measurements' sigmas leaks
            // into it as it would into `var(x) - mean(R)`.
            let var_x =
                (d.iter().zip(&d[1..]).map(|(a, b)| a * b).sum::<f64>() / (n - 1) as f64).max(0.0);
            // Axes whose oscillation stands clear of what the noise leaves in its estimate
            // (the covariance of n independent noise pairs scatters by 1/sqrt(n) of the noise
            // variance) say what its dynamics are; each weighs by the inverse of its noise.
            let resolvable = 5.0 * noise / (n as f64).sqrt();
            if var_x > resolvable && noise > 0.0 {
                let w = 1.0 / noise;
                for (c, &lag) in pooled_c.iter_mut().zip(&lags) {
                    *c += w * d.iter().zip(&d[lag..]).map(|(a, b)| a * b).sum::<f64>()
                        / (n - lag) as f64;
                }
                pooled_var += w * var_x;
            }
            lag1_c[axis] = var_x;
            slope[axis] = s;
        }
        let (period_s, correlation_time_s) = if pooled_var > 0.0 {
            let rho: Vec<(f64, f64)> = lags
                .iter()
                .zip(&pooled_c)
                .map(|(&lag, c)| (lag as f64 * dt_mean, c / pooled_var))
                .collect();
            fit_oscillator(&rho, b)
        } else {
            // Nothing stands out of the noise: the middle of the ranges.
            (
                (b.period_s.0 * b.period_s.1).sqrt(),
                (b.correlation_time_s.0 * b.correlation_time_s.1).sqrt(),
            )
        };
        // The motion's variance from its covariance at one step, through the fitted
        // oscillator's correlation over that step.
        let rho_step = oscillator_rho(
            1.0 / correlation_time_s,
            std::f64::consts::TAU / period_s,
            dt_mean,
        )
        .max(0.5);
        let sigma: [f64; 6] = std::array::from_fn(|i| (lag1_c[i] / rho_step).sqrt());
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
                correlation_time_s,
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

/// The autocorrelation of the model's oscillation at lag `tau_s`:
/// `rho(tau) = exp(-mu tau) (cos(lambda tau) + mu / lambda sin(lambda tau))`.
fn oscillator_rho(mu: f64, lambda: f64, tau_s: f64) -> f64 {
    (-mu * tau_s).exp() * ((lambda * tau_s).cos() + mu / lambda * (lambda * tau_s).sin())
}

/// `(period_s, correlation_time_s)` of the oscillator whose autocorrelation is nearest the
/// measured `(lag_s, rho)` pairs (least squares over a grid in the logarithms of both, within
/// the bounds).
fn fit_oscillator(rho: &[(f64, f64)], b: &Bounds) -> (f64, f64) {
    const STEPS: usize = 64;
    let log_grid = |(lo, hi): (f64, f64), k: usize| {
        (lo.ln() + (hi.ln() - lo.ln()) * k as f64 / (STEPS - 1) as f64).exp()
    };
    let mut best = (f64::INFINITY, 0.0, 0.0);
    for i in 0..STEPS {
        let period = log_grid(b.period_s, i);
        let lambda = std::f64::consts::TAU / period;
        for j in 0..STEPS {
            let tc = log_grid(b.correlation_time_s, j);
            let mu = 1.0 / tc;
            let err: f64 = rho
                .iter()
                .map(|&(tau, r)| (oscillator_rho(mu, lambda, tau) - r).powi(2))
                .sum();
            if err < best.0 {
                best = (err, period, tc);
            }
        }
    }
    (best.1, best.2)
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

    /// A randomly excited damped oscillation (the hull's wave-driven flexure) under noise
    /// larger than itself: its sigma, period and correlation time are recovered from the
    /// data, the noise's sigma not needed to be exact (it is given 10 % too large).
    #[test]
    fn a_damped_oscillation_under_noise_is_recovered() {
        let mut rng = StdRng::seed_from_u64(21);
        let (period, tc, sigma_as, noise_as, h): (f64, f64, f64, f64, f64) =
            (8.0, 12.7, 100.0, 117.0, 0.04);
        let (mu, lambda) = (1.0 / tc, std::f64::consts::TAU / period);
        // AR(2) with the continuous process's poles exp((-mu +- i lambda) h).
        let a1 = 2.0 * (-mu * h).exp() * (lambda * h).cos();
        let a2 = -(-2.0 * mu * h).exp();
        // Its stationary variance per unit driving variance.
        let gain = (1.0 - a2) / ((1.0 + a2) * ((1.0 - a2).powi(2) - a1 * a1));
        let drive = Normal::new(0.0, (sigma_as / ARCSEC_PER_RAD) / gain.sqrt()).unwrap();
        let noise = Normal::new(0.0, noise_as / ARCSEC_PER_RAD).unwrap();
        let r = (1.1 * noise_as / ARCSEC_PER_RAD).powi(2);
        let cov = Mat6::from_diagonal(&Twist::new(1.0, 1.0, 1.0, r, r, r));
        let mut est = MotionEstimator::new(Bounds::default());
        let mut state = [[0.0f64; 2]; 3];
        let mut fits = Vec::new();
        for k in 0..45_000 {
            let mut xi = Twist::zeros();
            for (i, s) in state.iter_mut().enumerate() {
                let x = a1 * s[0] + a2 * s[1] + drive.sample(&mut rng);
                *s = [x, s[0]];
                xi[3 + i] = x + noise.sample(&mut rng);
            }
            let z = PoseCov {
                pose: se3_exp(&xi),
                cov,
            };
            if let Some(f) = est.push((k as f64 * h * 1e9) as i64, &z) {
                fits.push(f);
            }
        }
        // Fits over the last 20 minutes, each of a 3-minute window.
        let late: Vec<&MotionFit> = fits.iter().skip(fits.len() / 3).collect();
        let mean = |f: &dyn Fn(&MotionFit) -> f64| {
            late.iter().map(|x| f(x)).sum::<f64>() / late.len() as f64
        };
        let sigma = mean(&|f| f.oscillation.rotation_arcsec.iter().sum::<f64>() / 3.0);
        let period_fit = mean(&|f| f.oscillation.period_s);
        let tc_fit = mean(&|f| f.oscillation.correlation_time_s);
        assert!(
            (sigma / sigma_as - 1.0).abs() < 0.1,
            "sigma {sigma} against {sigma_as}"
        );
        assert!(
            (period_fit / period - 1.0).abs() < 0.1,
            "period {period_fit} against {period}"
        );
        assert!(
            (tc_fit / tc - 1.0).abs() < 0.35,
            "correlation time {tc_fit} against {tc}"
        );
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
        // A fit sees 180 s (4500 samples): the covariance of neighbouring noise values
        // scatters by 1/sqrt(4500) of the noise variance, so an oscillation below
        // sqrt(4.5 / sqrt(4500)) of the noise (5.2 of 20 arc-seconds), the largest excess of
        // a few hundred fits, cannot be told from noise. Nothing above it is invented.
        let n = Bounds::default().window_s * 25.0;
        let limit = 20.0 * (4.5 / n.sqrt()).sqrt();
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
