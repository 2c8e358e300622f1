//! References, deformation and correction (`docs/interface.md`, "HTTP API": compensation and references).
//!
//! A target has a reference pose `G0_from_B` (its zero reading): set explicitly, or the mean of
//! the filtered poses over a window (chordal L2 mean of the rotations, arithmetic mean of the
//! translations) with the covariance of that mean.
//!
//! * Deformation at t: `G0_from_G(t) = G0_from_B * G_from_B(t)^-1`, reported as the rotation
//!   vector (arc-seconds, about the reference target axes) and the translation (mm, where the
//!   target origin is now in reference target coordinates).
//! * Correction at t: `G_from_G0(t)`, the inverse. A device on G that maps base coordinates with
//!   the nominal alignment (`p_g0 = G0_from_B * p_b`) gets the true coordinates with
//!   `p_g = G_from_G0 * p_g0`; directions use only the rotation.
//!
//! Both carry the uncertainty of the filtered pose; an estimated reference adds its own (the
//! two are treated as independent), an explicit one is exact.

use crate::geometry::{
    ARCSEC_PER_RAD, GeometryError, Pose, PoseCov, ReportedSigmas, Vec3, mean_pose, so3_log,
};

/// How a reference was set.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReferenceOrigin {
    /// Given explicitly: exact.
    Explicit,
    /// The mean of filtered poses in `[from_ns, to_ns]`.
    Window {
        /// Window start (ns).
        from_ns: i64,
        /// Window end (ns).
        to_ns: i64,
        /// How many poses were averaged.
        count: usize,
    },
}

/// A version of a target's reference: its number (1, 2, ...) and when it was set (ns, the
/// server's clock).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReferenceVersion {
    /// Its version.
    pub version: i64,
    /// The reference.
    pub reference: Reference,
    /// When it was set (ns).
    pub created_ns: i64,
}

/// A target's zero reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reference {
    /// `G0_from_B`, with the covariance of its estimate (zero when explicit).
    pub g0_from_b: PoseCov,
    /// How it was set.
    pub origin: ReferenceOrigin,
}

/// The covariance of a window's mean: the filter's own (time-correlated) uncertainty, which
/// averaging correlated poses does not reduce, widened on each axis where the scatter of the
/// mean is larger. Each axis is compared in its own units (mm^2 or rad^2; adding the two, as a
/// trace does, lets the translation decide alone): the own covariance is scaled by
/// `D = diag(d_i)` with `d_i^2 = max(1, scatter_ii / own_ii)`, so the result is positive
/// semi-definite, keeps the own correlations, and no axis reports less than either source.
pub fn window_covariance(
    scatter: &crate::geometry::Mat6,
    own: &crate::geometry::Mat6,
) -> crate::geometry::Mat6 {
    if (0..6).any(|i| own[(i, i)] <= 0.0) {
        // No own uncertainty to scale on some axis: the sum holds both sources.
        return scatter + own;
    }
    let d = nalgebra::Vector6::from_fn(|i, _| (scatter[(i, i)] / own[(i, i)]).max(1.0).sqrt());
    let d = crate::geometry::Mat6::from_diagonal(&d);
    d * own * d
}

impl Reference {
    /// An explicit reference pose (exact).
    pub fn explicit(g0_from_b: Pose) -> Self {
        Self {
            g0_from_b: PoseCov::exact(g0_from_b),
            origin: ReferenceOrigin::Explicit,
        }
    }

    /// The mean of the filtered poses of a window, with the covariance of the mean (the
    /// scatter of the poses over their count, never less than the mean of their own
    /// covariances over the count: filtered poses are correlated in time, so their scatter
    /// alone would claim too much).
    pub fn from_window(poses: &[PoseCov], from_ns: i64, to_ns: i64) -> Result<Self, GeometryError> {
        let plain: Vec<Pose> = poses.iter().map(|p| p.pose).collect();
        let mean = mean_pose(&plain)?;
        let n = poses.len() as f64;
        let mean_own_cov = poses
            .iter()
            .fold(crate::geometry::Mat6::zeros(), |acc, p| acc + p.cov)
            / n;
        let cov = window_covariance(&mean.mean.cov, &mean_own_cov);
        Ok(Self {
            g0_from_b: PoseCov {
                pose: mean.mean.pose,
                cov,
            },
            origin: ReferenceOrigin::Window {
                from_ns,
                to_ns,
                count: mean.count,
            },
        })
    }
}

/// Deformation and correction of a target at one time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Deformation {
    /// `G0_from_G` with covariance.
    pub g0_from_g: PoseCov,
    /// `G_from_G0` with covariance: the correction.
    pub g_from_g0: PoseCov,
}

/// A rotation vector in arc-seconds and a translation in mm, with their sigmas.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SmallMotion {
    /// Rotation vector (arc-seconds).
    pub rotation_arcsec: [f64; 3],
    /// Translation (mm).
    pub translation_mm: [f64; 3],
    /// Their standard deviations.
    pub sigmas: ReportedSigmas,
}

impl SmallMotion {
    /// The magnitude of the rotation (arc-seconds).
    pub fn rotation_magnitude_arcsec(&self) -> f64 {
        Vec3::from(self.rotation_arcsec).norm()
    }

    /// The magnitude of the translation (mm).
    pub fn translation_magnitude_mm(&self) -> f64 {
        Vec3::from(self.translation_mm).norm()
    }
}

fn small_motion(p: &PoseCov) -> SmallMotion {
    let phi = so3_log(&p.pose.rotation) * ARCSEC_PER_RAD;
    SmallMotion {
        rotation_arcsec: [phi.x, phi.y, phi.z],
        translation_mm: p.pose.translation.vector.into(),
        sigmas: p.reported_sigmas(),
    }
}

impl Deformation {
    /// The deformation of `g_from_b` against a reference.
    pub fn new(reference: &Reference, g_from_b: &PoseCov) -> Self {
        let g0_from_g = reference.g0_from_b.compose(&g_from_b.inverse());
        Self {
            g0_from_g,
            g_from_g0: g0_from_g.inverse(),
        }
    }

    /// The deformation as users read it (`G0_from_G`).
    pub fn deformation(&self) -> SmallMotion {
        small_motion(&self.g0_from_g)
    }

    /// The correction as users read it (`G_from_G0`).
    pub fn correction(&self) -> SmallMotion {
        small_motion(&self.g_from_g0)
    }

    /// Corrects a point computed with the nominal alignment: `p_g = G_from_G0 * p_g0` (mm).
    pub fn correct_point(&self, p_g0_mm: &Vec3) -> Vec3 {
        self.g_from_g0
            .pose
            .transform_point(&(*p_g0_mm).into())
            .coords
    }

    /// Corrects a direction (a line of sight): only the rotation applies.
    pub fn correct_direction(&self, d_g0: &Vec3) -> Vec3 {
        self.g_from_g0.pose.rotation * d_g0
    }
}
