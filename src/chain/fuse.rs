//! Information-weighted fusion of independent estimates of one pose, with a consistency test.
//!
//! Gauss-Newton on `sum_k ||Log(T * T_k^-1)||^2_{Sigma_k^-1}` (Barfoot and Furgale 2014): with
//! `T = Exp(d) T0`, each residual is `e_k ~= e_k0 + J_l(e_k0)^-1 d`. The fused covariance is the
//! inverse of the summed (Jacobian-weighted) information. At the optimum the cost is a
//! chi-square variable with `6 (K - 1)` degrees of freedom when the estimates agree within their
//! covariances: a bumped relay station shows up as a statistic far above its quantile.

use super::ChainError;
use crate::geometry::{Mat6, PoseCov, Twist, se3_exp, se3_left_jacobian_inv, se3_log, symmetrize};
use statrs::distribution::{ChiSquared, ContinuousCDF};

/// The default probability of the consistency quantile (99.9 %).
pub const DEFAULT_CONSISTENCY_PROBABILITY: f64 = 0.999;

const MAX_ITERATIONS: usize = 20;
/// Stop when the update is below this (mm or rad), far under any measurable change.
const CONVERGED_STEP: f64 = 1e-12;

/// The disagreement of the fused estimates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Consistency {
    /// The minimised cost, `sum_k e_k^T Sigma_k^-1 e_k`.
    pub chi2: f64,
    /// Degrees of freedom, `6 (K - 1)`.
    pub dof: usize,
    /// The chi-square quantile at the requested probability.
    pub threshold: f64,
}

impl Consistency {
    /// True when the estimates agree within their covariances.
    pub fn is_consistent(&self) -> bool {
        self.chi2 <= self.threshold
    }
}

/// The fused estimate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fused {
    /// The fused pose and its covariance.
    pub estimate: PoseCov,
    /// `None` for a single estimate (nothing to disagree with).
    pub consistency: Option<Consistency>,
}

/// The chi-square quantile with `dof` degrees of freedom at `probability`.
pub fn chi_square_quantile(dof: usize, probability: f64) -> f64 {
    match ChiSquared::new(dof as f64) {
        Ok(dist) => dist.inverse_cdf(probability),
        Err(_) => f64::INFINITY,
    }
}

/// Fuses independent estimates of the same pose. `probability` sets the consistency quantile.
pub fn fuse(estimates: &[PoseCov], probability: f64) -> Result<Fused, ChainError> {
    match estimates {
        [] => return Err(ChainError::NothingToFuse),
        [single] => {
            return Ok(Fused {
                estimate: *single,
                consistency: None,
            });
        }
        _ => {}
    }
    let mut information = Vec::with_capacity(estimates.len());
    for (index, e) in estimates.iter().enumerate() {
        let info = symmetrize(&e.cov)
            .cholesky()
            .ok_or(ChainError::SingularCovariance { index })?
            .inverse();
        information.push(info);
    }
    // Start from the most certain estimate.
    let start = (0..estimates.len())
        .max_by(|&a, &b| information[a].trace().total_cmp(&information[b].trace()))
        .unwrap_or(0);
    let mut pose = estimates[start].pose;
    let mut hessian = Mat6::zeros();
    for _ in 0..MAX_ITERATIONS {
        hessian = Mat6::zeros();
        let mut gradient = Twist::zeros();
        for (e, info) in estimates.iter().zip(&information) {
            let residual = se3_log(&(pose * e.pose.inverse()));
            let jac = se3_left_jacobian_inv(&residual);
            let jt_info = jac.transpose() * info;
            hessian += jt_info * jac;
            gradient += jt_info * residual;
        }
        let Some(chol) = symmetrize(&hessian).cholesky() else {
            return Err(ChainError::SingularCovariance { index: start });
        };
        let step = -chol.solve(&gradient);
        pose = se3_exp(&step) * pose;
        if step.amax() < CONVERGED_STEP {
            break;
        }
    }
    let chi2: f64 = estimates
        .iter()
        .zip(&information)
        .map(|(e, info)| {
            let r = se3_log(&(pose * e.pose.inverse()));
            (r.transpose() * info * r)[(0, 0)]
        })
        .sum();
    let cov = symmetrize(
        &symmetrize(&hessian)
            .cholesky()
            .ok_or(ChainError::SingularCovariance { index: start })?
            .inverse(),
    );
    let dof = 6 * (estimates.len() - 1);
    Ok(Fused {
        estimate: PoseCov { pose, cov },
        consistency: Some(Consistency {
            chi2,
            dof,
            threshold: chi_square_quantile(dof, probability),
        }),
    })
}
