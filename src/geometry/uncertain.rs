//! Poses with uncertainty: composition, inversion and the sigmas users see.
//!
//! A [`PoseCov`] is a mean pose with the 6x6 covariance of a left perturbation,
//! `T = Exp(xi) * T_mean`, `xi = [rho (mm); phi (rad)]` (`docs/interface.md`, "Conventions"):
//!
//! * compose independent `T1 * T2`: `Sigma = Sigma1 + Ad(T1) Sigma2 Ad(T1)^T`;
//! * invert: `Sigma_inv = Ad(T^-1) Sigma Ad(T^-1)^T`.
//!
//! The sigmas reported to users ([`ReportedSigmas`]) describe the numbers they see: rotation
//! about the axes of the pose's left frame, and the standard deviations of the translation
//! components, whose covariance is `J Sigma J^T` with `J = [I, -[t]x]` (to first order
//! `t = t_mean + rho + phi x t_mean`). Sigmas given as input are read with the same meaning.

use super::{ARCSEC_PER_RAD, GeometryError, Mat3, Mat6, Pose, Vec3, skew};
use nalgebra::Matrix3x6;

/// A 6x6 covariance on `[rho (mm^2); phi (rad^2)]`.
pub type Covariance6 = Mat6;

/// A pose `a_from_b` with the covariance of its left perturbation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseCov {
    /// The mean pose.
    pub pose: Pose,
    /// Covariance of `xi` in `T = Exp(xi) * pose`.
    pub cov: Covariance6,
}

/// Standard deviations as users read them: rotation in arc-seconds about the left frame's axes,
/// translation components in millimetres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReportedSigmas {
    /// Per-axis rotation standard deviation (arc-seconds).
    pub rotation_arcsec: [f64; 3],
    /// Standard deviation of each translation component (mm).
    pub translation_mm: [f64; 3],
}

impl ReportedSigmas {
    /// The six, rotation about x, y, z (arc-seconds) then translation x, y, z (mm).
    pub fn axes(&self) -> [f64; 6] {
        let (r, t) = (self.rotation_arcsec, self.translation_mm);
        [r[0], r[1], r[2], t[0], t[1], t[2]]
    }
}

/// `Ad(T) S Ad(T)^T` without forming the 6x6 adjoint: rotate the four 3x3 blocks, then apply
/// the shear `[[I, [t]x], [0, I]]`. About three times fewer flops than two 6x6 products.
#[inline]
pub fn transform_covariance(pose: &Pose, cov: &Mat6) -> Mat6 {
    let r = pose.rotation.to_rotation_matrix().into_inner();
    let rt = r.transpose();
    let a = r * cov.fixed_view::<3, 3>(0, 0) * rt;
    let b = r * cov.fixed_view::<3, 3>(0, 3) * rt;
    let d = r * cov.fixed_view::<3, 3>(3, 3) * rt;
    let tx = skew(&pose.translation.vector);
    // [[I, tx], [0, I]] [[a, b], [b^T, d]] [[I, 0], [-tx, I]]  (tx^T = -tx)
    let tx_d = tx * d;
    let b_new = b + tx_d;
    let tx_bt = tx * b.transpose();
    let a_new = a + tx_bt + tx_bt.transpose() - tx_d * tx;
    let mut out = Mat6::zeros();
    out.fixed_view_mut::<3, 3>(0, 0).copy_from(&a_new);
    out.fixed_view_mut::<3, 3>(0, 3).copy_from(&b_new);
    out.fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&b_new.transpose());
    out.fixed_view_mut::<3, 3>(3, 3).copy_from(&d);
    symmetrize(&out)
}

/// `(S + S^T) / 2`: removes the rounding asymmetry that repeated products accumulate.
#[inline]
pub fn symmetrize(cov: &Mat6) -> Mat6 {
    (cov + cov.transpose()) * 0.5
}

impl PoseCov {
    /// A pose known exactly (zero covariance).
    pub fn exact(pose: Pose) -> Self {
        Self {
            pose,
            cov: Mat6::zeros(),
        }
    }

    /// The identity pose, exactly.
    pub fn identity() -> Self {
        Self::exact(Pose::identity())
    }

    /// A pose with a covariance, checked symmetric positive semi-definite.
    pub fn new(pose: Pose, cov: Covariance6) -> Result<Self, GeometryError> {
        check_covariance(&cov)?;
        Ok(Self { pose, cov })
    }

    /// A pose whose uncertainty is given as the sigmas users read (see the module docs):
    /// independent per-axis rotation sigmas (arc-seconds) and translation-component sigmas (mm).
    pub fn from_reported_sigmas(pose: Pose, sigmas: &ReportedSigmas) -> Self {
        let rot_var = Vec3::from(sigmas.rotation_arcsec.map(|s| (s / ARCSEC_PER_RAD).powi(2)));
        let t_var = Vec3::from(sigmas.translation_mm.map(|s| s * s));
        let s_phi = Mat3::from_diagonal(&rot_var);
        // rho = dt + [t]x phi, with dt and phi independent.
        let tx = skew(&pose.translation.vector);
        let cross = tx * s_phi;
        let s_rho = Mat3::from_diagonal(&t_var) + cross * tx.transpose();
        let mut cov = Mat6::zeros();
        cov.fixed_view_mut::<3, 3>(0, 0).copy_from(&s_rho);
        cov.fixed_view_mut::<3, 3>(0, 3).copy_from(&cross);
        cov.fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&cross.transpose());
        cov.fixed_view_mut::<3, 3>(3, 3).copy_from(&s_phi);
        Self { pose, cov }
    }

    /// `self * other` for independent poses: `Sigma = S1 + Ad(T1) S2 Ad(T1)^T`.
    pub fn compose(&self, other: &PoseCov) -> PoseCov {
        PoseCov {
            pose: self.pose * other.pose,
            cov: symmetrize(&(self.cov + transform_covariance(&self.pose, &other.cov))),
        }
    }

    /// The pose a fraction `a` of the way from `self` (at 0) to `later` (at 1) along the
    /// geodesic of SE(3), `T = Exp(a Log(T1 T0^-1)) T0`, with the covariance interpolated
    /// linearly (both are left perturbations, so they add in the same tangent space).
    pub fn interpolate(&self, later: &PoseCov, a: f64) -> PoseCov {
        let d = super::se3_log(&(later.pose * self.pose.inverse()));
        PoseCov {
            pose: super::se3_exp(&(d * a)) * self.pose,
            cov: symmetrize(&(self.cov * (1.0 - a) + later.cov * a)),
        }
    }

    /// `self^-1`: `Sigma_inv = Ad(T^-1) Sigma Ad(T^-1)^T`.
    pub fn inverse(&self) -> PoseCov {
        let inv = self.pose.inverse();
        PoseCov {
            pose: inv,
            cov: transform_covariance(&inv, &self.cov),
        }
    }

    /// The covariance of the translation components, `J Sigma J^T` with `J = [I, -[t]x]` (mm^2).
    pub fn translation_covariance(&self) -> Mat3 {
        let mut j = Matrix3x6::zeros();
        j.fixed_view_mut::<3, 3>(0, 0).copy_from(&Mat3::identity());
        j.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(-skew(&self.pose.translation.vector)));
        j * self.cov * j.transpose()
    }

    /// The sigmas users read (see the module docs).
    pub fn reported_sigmas(&self) -> ReportedSigmas {
        let t_cov = self.translation_covariance();
        ReportedSigmas {
            rotation_arcsec: [3, 4, 5].map(|i| self.cov[(i, i)].max(0.0).sqrt() * ARCSEC_PER_RAD),
            translation_mm: [0, 1, 2].map(|i| t_cov[(i, i)].max(0.0).sqrt()),
        }
    }
}

/// Checks that a covariance is finite, symmetric (relative 1e-9) and positive semi-definite.
pub fn check_covariance(cov: &Mat6) -> Result<(), GeometryError> {
    if cov.iter().any(|v| !v.is_finite()) {
        return Err(GeometryError::BadCovariance {
            reason: "it has a non-finite entry".into(),
        });
    }
    let scale = cov.amax().max(f64::MIN_POSITIVE);
    let asymmetry = (cov - cov.transpose()).amax();
    if asymmetry > 1e-9 * scale {
        return Err(GeometryError::BadCovariance {
            reason: format!("it is not symmetric (largest difference {asymmetry:.3e})"),
        });
    }
    let min_eig = symmetrize(cov).symmetric_eigenvalues().min();
    if min_eig < -1e-9 * scale {
        return Err(GeometryError::BadCovariance {
            reason: format!("it has a negative eigenvalue ({min_eig:.3e})"),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{Twist, adjoint, rotation_from_euler, se3_exp};
    use approx::assert_relative_eq;
    use nalgebra::Translation3;

    fn sample_pose() -> Pose {
        Pose::from_parts(
            Translation3::new(120.0, -300.0, 2900.0),
            rotation_from_euler([0.2, -0.4, 2.5]).unwrap(),
        )
    }

    fn sample_cov() -> Mat6 {
        let a = Mat6::from_fn(|r, c| {
            ((r * 7 + c * 3) % 5) as f64 * 0.1 + if r == c { 1.0 } else { 0.0 }
        });
        a * a.transpose() * 1e-3
    }

    #[test]
    fn fast_covariance_transform_equals_adjoint_product() {
        let pose = sample_pose();
        let cov = sample_cov();
        let ad = adjoint(&pose);
        assert_relative_eq!(
            transform_covariance(&pose, &cov),
            ad * cov * ad.transpose(),
            max_relative = 1e-12,
            epsilon = 1e-9
        );
    }

    #[test]
    fn reported_sigmas_round_trip_through_input_sigmas() {
        let sigmas = ReportedSigmas {
            rotation_arcsec: [20.0, 25.0, 40.0],
            translation_mm: [0.3, 0.4, 1.0],
        };
        let pc = PoseCov::from_reported_sigmas(sample_pose(), &sigmas);
        check_covariance(&pc.cov).unwrap();
        let back = pc.reported_sigmas();
        for i in 0..3 {
            assert_relative_eq!(
                back.rotation_arcsec[i],
                sigmas.rotation_arcsec[i],
                epsilon = 1e-9
            );
            assert_relative_eq!(
                back.translation_mm[i],
                sigmas.translation_mm[i],
                epsilon = 1e-9
            );
        }
    }

    #[test]
    fn inverse_twice_restores_the_covariance() {
        let pc = PoseCov::new(sample_pose(), sample_cov()).unwrap();
        let back = pc.inverse().inverse();
        // Lever-arm terms of order |t|^2 Sigma ~ 1e4 cancel back to ~1e-3: rounding leaves
        // absolute errors near 1e-9, far below any sigma of interest.
        assert_relative_eq!(back.cov, pc.cov, epsilon = 1e-8);
    }

    #[test]
    fn negative_definite_covariance_is_refused() {
        let mut cov = Mat6::identity();
        cov[(2, 2)] = -1.0;
        assert!(PoseCov::new(Pose::identity(), cov).is_err());
    }

    #[test]
    fn perturbation_is_on_the_left() {
        // A pure rotation perturbation about the left frame's origin moves the translation.
        let pose = sample_pose();
        let xi = Twist::new(0.0, 0.0, 0.0, 0.0, 0.0, 1e-6);
        let perturbed = se3_exp(&xi) * pose;
        let expected =
            pose.translation.vector + Vec3::new(0.0, 0.0, 1e-6).cross(&pose.translation.vector);
        assert_relative_eq!(perturbed.translation.vector, expected, epsilon = 1e-9);
    }
}
