//! A second-order Gauss-Markov process, `x'' + 2 mu x' + (mu^2 + lambda^2) x = w`: a randomly
//! excited damped oscillator, the usual model of wave-driven hull flexure.

use rand::Rng;
use rand_distr::StandardNormal;

/// Integration step at most (s): a small fraction of any period used here.
const MAX_STEP_S: f64 = 0.005;

/// One component of a randomly excited oscillation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GaussMarkov2 {
    /// Damping `mu` (1/s).
    mu: f64,
    /// Squared natural frequency `mu^2 + lambda^2` (1/s^2).
    omega2: f64,
    /// White-noise intensity `q`, chosen for the requested standard deviation.
    q: f64,
    x: f64,
    v: f64,
}

impl GaussMarkov2 {
    /// A process of period `period_s` (`lambda = 2 pi / period`), damping ratio `zeta`
    /// (`mu = zeta lambda`) and stationary standard deviation `sigma`, started from its
    /// stationary distribution.
    pub fn new(period_s: f64, zeta: f64, sigma: f64, rng: &mut impl Rng) -> Self {
        let lambda = std::f64::consts::TAU / period_s;
        let mu = zeta * lambda;
        let omega2 = mu * mu + lambda * lambda;
        // Stationary variance of x is q / (4 mu omega2); of v, q / (4 mu).
        let q = sigma * sigma * 4.0 * mu * omega2;
        let x = sigma * rng.sample::<f64, _>(StandardNormal);
        let v = sigma * omega2.sqrt() * rng.sample::<f64, _>(StandardNormal);
        Self {
            mu,
            omega2,
            q,
            x,
            v,
        }
    }

    /// Advances by `dt_s` (semi-implicit Euler in steps of at most 5 ms) and returns `x`.
    pub fn advance(&mut self, dt_s: f64, rng: &mut impl Rng) -> f64 {
        if dt_s > 0.0 {
            let n = (dt_s / MAX_STEP_S).ceil().max(1.0);
            let h = dt_s / n;
            for _ in 0..n as usize {
                let w = (self.q / h).sqrt() * rng.sample::<f64, _>(StandardNormal);
                self.v += (-2.0 * self.mu * self.v - self.omega2 * self.x + w) * h;
                self.x += self.v * h;
            }
        }
        self.x
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn the_stationary_spread_and_the_period_are_those_asked_for() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let (period, sigma) = (8.0, 2.0);
        let mut p = GaussMarkov2::new(period, 0.1, sigma, &mut rng);
        let dt = 0.04;
        let xs: Vec<f64> = (0..250_000).map(|_| p.advance(dt, &mut rng)).collect();
        let var = xs.iter().map(|x| x * x).sum::<f64>() / xs.len() as f64;
        assert!((var.sqrt() / sigma - 1.0).abs() < 0.1, "std {}", var.sqrt());
        // The autocorrelation at half a period is strongly negative, at a full period positive.
        let corr = |lag: usize| {
            xs.iter().zip(&xs[lag..]).map(|(a, b)| a * b).sum::<f64>()
                / (xs.len() - lag) as f64
                / var
        };
        let half = (period / 2.0 / dt) as usize;
        assert!(
            corr(half) < -0.5 && corr(2 * half) > 0.3,
            "{} {}",
            corr(half),
            corr(2 * half)
        );
    }
}
