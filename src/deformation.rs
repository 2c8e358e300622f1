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
//! Both carry the uncertainty of the filtered pose; an estimated reference adds its own, an
//! explicit one is exact. The random parts (noise, averaged by the filter) are independent and
//! add. The systematic parts (cameras' intrinsics, calibrated links) are the same error in the
//! reference and in the result when both were measured with the same calibrations (the same
//! [`CalibrationStamp`]): to first order it cancels in `G0_from_B * G_from_B^-1` and the
//! deformation carries the random parts alone. After a calibration changed, both systematic
//! parts add.

use crate::geometry::{
    ARCSEC_PER_RAD, GeometryError, Mat6, Pose, PoseCov, ReportedSigmas, Vec3, mean_pose, so3_log,
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

/// The calibrations a result was measured with, as one number: equal stamps mean the same
/// cameras' intrinsics (and their covariances) and the same calibration of every calibrated
/// link on the target's paths.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct CalibrationStamp(pub i64);

impl CalibrationStamp {
    /// The stamp of a sequence of numbers (FNV-1a over their bits: the same on every platform
    /// and in every version, so stored stamps compare with new ones).
    pub fn of(values: impl IntoIterator<Item = f64>) -> Self {
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        for v in values {
            for b in v.to_bits().to_le_bytes() {
                h ^= u64::from(b);
                h = h.wrapping_mul(0x0000_0100_0000_01b3);
            }
        }
        Self(h as i64)
    }
}

/// A target's zero reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reference {
    /// `G0_from_B`, with the whole covariance of its estimate (zero when explicit).
    pub g0_from_b: PoseCov,
    /// How it was set.
    pub origin: ReferenceOrigin,
    /// The systematic part of `g0_from_b`'s covariance (zero when explicit).
    pub systematic_cov: Mat6,
    /// The calibrations its results were measured with (`None`: explicit, or not known).
    pub calibration: Option<CalibrationStamp>,
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
            systematic_cov: Mat6::zeros(),
            calibration: None,
        }
    }

    /// The mean of the filtered poses of a window, with the covariance of the mean: its random
    /// part the scatter of the poses over their count, never less than the mean of their own
    /// random covariances (filtered poses are correlated in time, so their scatter alone would
    /// claim too much); its systematic part their mean systematic covariance, which averaging
    /// does not reduce. `systematic` gives each pose's systematic part (as many as `poses`, or
    /// none: zero), `calibration` the calibrations the window was measured with when they were
    /// the same throughout.
    pub fn from_window(
        poses: &[PoseCov],
        systematic: &[Mat6],
        calibration: Option<CalibrationStamp>,
        from_ns: i64,
        to_ns: i64,
    ) -> Result<Self, GeometryError> {
        let plain: Vec<Pose> = poses.iter().map(|p| p.pose).collect();
        let mean = mean_pose(&plain)?;
        let n = poses.len() as f64;
        let systematic_cov = systematic.iter().fold(Mat6::zeros(), |acc, s| acc + s) / n;
        let mean_own_random =
            poses.iter().fold(Mat6::zeros(), |acc, p| acc + p.cov) / n - systematic_cov;
        let cov = window_covariance(&mean.mean.cov, &mean_own_random) + systematic_cov;
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
            systematic_cov,
            calibration,
        })
    }
}

/// Deformation and correction of a target at one time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Deformation {
    /// `G0_from_G` with its whole covariance.
    pub g0_from_g: PoseCov,
    /// `G_from_G0` with its whole covariance: the correction.
    pub g_from_g0: PoseCov,
    /// The systematic part of `g0_from_g`'s covariance: zero when the reference and the result
    /// share their calibrations (it cancels), both parts otherwise.
    pub systematic_cov: Mat6,
}

/// A result to compare with a reference: `G_from_B` with its whole covariance, the systematic
/// part of it, and the calibrations it was measured with.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measured<'a> {
    /// `G_from_B` with its whole covariance.
    pub g_from_b: &'a PoseCov,
    /// The systematic part of that covariance.
    pub systematic_cov: &'a Mat6,
    /// Its calibrations, when known.
    pub calibration: Option<CalibrationStamp>,
}

impl Measured<'_> {
    /// The random part: the whole covariance less the systematic part (the noise, what
    /// averaging and filtering bring down). The one place the split is computed.
    pub fn random(&self) -> PoseCov {
        PoseCov {
            pose: self.g_from_b.pose,
            cov: self.g_from_b.cov - self.systematic_cov,
        }
    }

    /// The systematic part alone (the calibrations' error, the same in every result of that
    /// geometry).
    pub fn systematic(&self) -> PoseCov {
        PoseCov {
            pose: self.g_from_b.pose,
            cov: *self.systematic_cov,
        }
    }
}

impl Reference {
    /// The reference's pose with its covariance told apart, as a result's is.
    pub fn measured(&self) -> Measured<'_> {
        Measured {
            g_from_b: &self.g0_from_b,
            systematic_cov: &self.systematic_cov,
            calibration: self.calibration,
        }
    }
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
    let d = Displacement::of(&p.pose);
    SmallMotion {
        rotation_arcsec: d.rotation_arcsec,
        translation_mm: d.translation_mm,
        sigmas: p.reported_sigmas(),
    }
}

/// A rigid displacement `G0_from_G` as users state and read it (a deformation's, or a known
/// move's): the rotation vector (arc-seconds, about `G0`'s axes) and the translation (mm, where
/// `G`'s origin is in `G0`'s coordinates).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Displacement {
    /// The rotation vector (arc-seconds).
    pub rotation_arcsec: [f64; 3],
    /// The translation (mm).
    pub translation_mm: [f64; 3],
}

impl Displacement {
    /// No displacement.
    pub const ZERO: Self = Self {
        rotation_arcsec: [0.0; 3],
        translation_mm: [0.0; 3],
    };

    /// The six axes: rotation x, y, z (arc-seconds), then translation x, y, z (mm).
    pub fn axes(&self) -> [f64; 6] {
        let (r, t) = (self.rotation_arcsec, self.translation_mm);
        [r[0], r[1], r[2], t[0], t[1], t[2]]
    }

    /// The pose `G0_from_G` it states.
    pub fn g0_from_g(&self) -> Pose {
        let phi = Vec3::from(self.rotation_arcsec) / ARCSEC_PER_RAD;
        Pose::from_parts(
            Vec3::from(self.translation_mm).into(),
            crate::geometry::so3_exp(&phi),
        )
    }

    /// The displacement of a pose `G0_from_G`.
    pub fn of(g0_from_g: &Pose) -> Self {
        let phi = so3_log(&g0_from_g.rotation) * ARCSEC_PER_RAD;
        Self {
            rotation_arcsec: [phi.x, phi.y, phi.z],
            translation_mm: g0_from_g.translation.vector.into(),
        }
    }
}

impl Deformation {
    /// `G0_from_G` with its covariance told apart, as a result's is.
    pub fn measured(&self) -> Measured<'_> {
        Measured {
            g_from_b: &self.g0_from_g,
            systematic_cov: &self.systematic_cov,
            calibration: None,
        }
    }

    /// The deformation of a result against a reference (see the module docs for which
    /// uncertainty it carries).
    pub fn new(reference: &Reference, measured: Measured<'_>) -> Self {
        let g = measured.g_from_b;
        let shared =
            reference.calibration.is_some() && reference.calibration == measured.calibration;
        let (r, m) = if shared {
            (reference.measured().random(), measured.random())
        } else {
            (reference.g0_from_b, *g)
        };
        let g0_from_g = r.compose(&m.inverse());
        let systematic_cov = if shared {
            Mat6::zeros()
        } else {
            reference
                .measured()
                .systematic()
                .compose(&measured.systematic().inverse())
                .cov
        };
        Self {
            g0_from_g,
            g_from_g0: g0_from_g.inverse(),
            systematic_cov,
        }
    }

    /// The deformation of a pose known with its whole covariance alone (no systematic part
    /// told apart, no calibrations known).
    pub fn of_pose(reference: &Reference, g_from_b: &PoseCov) -> Self {
        Self::new(
            reference,
            Measured {
                g_from_b,
                systematic_cov: &Mat6::zeros(),
                calibration: None,
            },
        )
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
