//! The Kalman update shared by every model, and the Van Loan discretisation.

use crate::geometry::{Mat6, Twist, symmetrize};
use nalgebra::{SMatrix, SVector};

/// The result of a gated update.
pub(crate) enum Update<const N: usize> {
    /// Fused: the error-state correction, the new covariance, the normalised innovation squared.
    Fused {
        delta: SVector<f64, N>,
        p: SMatrix<f64, N, N>,
        nis: f64,
    },
    /// Over the gate: not fused.
    Rejected { nis: f64 },
}

/// The chi-square test of an innovation `y` with covariance `s`: `Ok` with the factorisation,
/// `S^-1 y` and the normalised innovation squared when it passes the gate, `Err(nis)` when it
/// does not, `None` when `s` is not positive definite.
type Accepted = (nalgebra::Cholesky<f64, nalgebra::Const<6>>, Twist, f64);

fn innovation_test(s: &Mat6, y: &Twist, gate: f64) -> Option<Result<Accepted, f64>> {
    let chol = symmetrize(s).cholesky()?;
    let s_inv_y = chol.solve(y);
    let nis = y.dot(&s_inv_y);
    if !nis.is_finite() {
        return None;
    }
    Some(if nis > gate {
        Err(nis)
    } else {
        Ok((chol, s_inv_y, nis))
    })
}

/// A gated Kalman update of an `N`-dimensional error state with a 6-dimensional measurement
/// `y = H delta + v`, `v ~ N(0, r)`. Joseph form: `P+ = (I - K H) P (I - K H)^T + K R K^T`.
/// Returns `None` when the innovation covariance is not positive definite.
pub(crate) fn gated_update<const N: usize>(
    p: &SMatrix<f64, N, N>,
    h: &SMatrix<f64, 6, N>,
    y: &Twist,
    r: &Mat6,
    gate: f64,
) -> Option<Update<N>> {
    let ph_t = p * h.transpose();
    let (chol, s_inv_y, nis) = match innovation_test(&(h * ph_t + r), y, gate)? {
        Ok(accepted) => accepted,
        Err(nis) => return Some(Update::Rejected { nis }),
    };
    // K = P H^T S^-1, computed as (S^-1 (P H^T)^T)^T.
    let k: SMatrix<f64, N, 6> = chol.solve(&ph_t.transpose()).transpose();
    let delta = ph_t * s_inv_y;
    let i_kh = SMatrix::<f64, N, N>::identity() - k * h;
    let p_new = i_kh * p * i_kh.transpose() + k * r * k.transpose();
    Some(Update::Fused {
        delta,
        p: (p_new + p_new.transpose()) * 0.5,
        nis,
    })
}

/// [`gated_update`] for a measurement of the whole state (`H = I`, the static model), without
/// the products by the identity: about a third fewer flops on the hottest path.
pub(crate) fn gated_update_direct(p: &Mat6, y: &Twist, r: &Mat6, gate: f64) -> Option<Update<6>> {
    let (chol, s_inv_y, nis) = match innovation_test(&(p + r), y, gate)? {
        Ok(accepted) => accepted,
        Err(nis) => return Some(Update::Rejected { nis }),
    };
    // K = P S^-1 = (S^-1 P)^T (P and S symmetric); K y = P S^-1 y.
    let k = chol.solve(p).transpose();
    let delta = p * s_inv_y;
    let i_k = Mat6::identity() - k;
    let p_new = i_k * p * i_k.transpose() + k * r * k.transpose();
    Some(Update::Fused {
        delta,
        p: symmetrize(&p_new),
        nis,
    })
}

/// True when a symmetric matrix is positive definite (its Cholesky factorisation exists).
pub(crate) fn is_positive_definite<const N: usize>(p: &SMatrix<f64, N, N>) -> bool {
    let asym = (p - p.transpose()).amax();
    asym <= 1e-9 * p.amax().max(f64::MIN_POSITIVE) && p.cholesky().is_some()
}

/// Van Loan: for `x' = A x + w`, `w` white with spectral density `qc`, returns the transition
/// `Phi = exp(A dt)` and the discrete process noise `Q = int_0^dt exp(A s) qc exp(A s)^T ds`.
pub(crate) fn van_loan(
    a: &SMatrix<f64, 2, 2>,
    qc: &SMatrix<f64, 2, 2>,
    dt_s: f64,
) -> (SMatrix<f64, 2, 2>, SMatrix<f64, 2, 2>) {
    let mut m = SMatrix::<f64, 4, 4>::zeros();
    m.fixed_view_mut::<2, 2>(0, 0).copy_from(&(-a * dt_s));
    m.fixed_view_mut::<2, 2>(0, 2).copy_from(&(qc * dt_s));
    m.fixed_view_mut::<2, 2>(2, 2)
        .copy_from(&(a.transpose() * dt_s));
    let e = m.exp();
    let phi = e.fixed_view::<2, 2>(2, 2).transpose();
    let q = phi * e.fixed_view::<2, 2>(0, 2);
    (phi, (q + q.transpose()) * 0.5)
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn direct_update_equals_the_general_update_with_identity_h() {
        let a = Mat6::from_fn(|r, c| {
            ((r * 5 + c * 3) % 7) as f64 * 0.1 + if r == c { 1.0 } else { 0.0 }
        });
        let p = a * a.transpose();
        let r = Mat6::from_diagonal(&Twist::new(0.5, 0.4, 0.3, 0.2, 0.6, 0.7));
        let y = Twist::new(0.1, -0.2, 0.3, 0.05, -0.1, 0.2);
        let (
            Some(Update::Fused {
                delta: d1,
                p: p1,
                nis: n1,
            }),
            Some(Update::Fused {
                delta: d2,
                p: p2,
                nis: n2,
            }),
        ) = (
            gated_update(&p, &Mat6::identity(), &y, &r, 100.0),
            gated_update_direct(&p, &y, &r, 100.0),
        )
        else {
            panic!("both fuse");
        };
        assert_relative_eq!(d1, d2, epsilon = 1e-12);
        assert_relative_eq!(p1, p2, epsilon = 1e-12);
        assert_relative_eq!(n1, n2, epsilon = 1e-12);
    }

    #[test]
    fn van_loan_of_a_random_walk_is_q_dt() {
        let a = SMatrix::<f64, 2, 2>::zeros();
        let qc = SMatrix::<f64, 2, 2>::new(0.0, 0.0, 0.0, 3.0);
        let (phi, q) = van_loan(&a, &qc, 0.5);
        assert_relative_eq!(phi, SMatrix::<f64, 2, 2>::identity(), epsilon = 1e-14);
        assert_relative_eq!(q[(1, 1)], 1.5, epsilon = 1e-12);
    }

    #[test]
    fn van_loan_of_white_noise_acceleration_matches_the_closed_form() {
        let a = SMatrix::<f64, 2, 2>::new(0.0, 1.0, 0.0, 0.0);
        let qc = SMatrix::<f64, 2, 2>::new(0.0, 0.0, 0.0, 2.0);
        let dt: f64 = 0.37;
        let (phi, q) = van_loan(&a, &qc, dt);
        assert_relative_eq!(
            phi,
            SMatrix::<f64, 2, 2>::new(1.0, dt, 0.0, 1.0),
            epsilon = 1e-13
        );
        let expected = SMatrix::<f64, 2, 2>::new(
            2.0 * dt.powi(3) / 3.0,
            2.0 * dt * dt / 2.0,
            2.0 * dt * dt / 2.0,
            2.0 * dt,
        );
        assert_relative_eq!(q, expected, epsilon = 1e-12);
    }

    #[test]
    fn oscillator_noise_approaches_the_stationary_variance() {
        // x'' + 2 mu x' + w0^2 x = w: var(x) = q / (4 mu w0^2), var(v) = q / (4 mu).
        let (mu, lambda, qd) = (0.2_f64, 0.8_f64, 1.7);
        let w0_sq = mu * mu + lambda * lambda;
        let a = SMatrix::<f64, 2, 2>::new(0.0, 1.0, -w0_sq, -2.0 * mu);
        let qc = SMatrix::<f64, 2, 2>::new(0.0, 0.0, 0.0, qd);
        let (_, q) = van_loan(&a, &qc, 200.0);
        assert_relative_eq!(q[(0, 0)], qd / (4.0 * mu * w0_sq), max_relative = 1e-6);
        assert_relative_eq!(q[(1, 1)], qd / (4.0 * mu), max_relative = 1e-6);
        assert!(q[(0, 1)].abs() < 1e-6);
    }
}
