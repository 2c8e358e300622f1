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
    /// `G0_from_B` as measured: its whole covariance (zero when explicit), the systematic part
    /// and the calibrations its results were measured with (`None`: explicit, or not known).
    pub g0_from_b: MeasuredPose,
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
            g0_from_b: MeasuredPose::exact(g0_from_b),
            origin: ReferenceOrigin::Explicit,
        }
    }

    /// The mean of the filtered poses of a window, with the covariance of the mean: its random
    /// part the scatter of the poses over their count, never less than the mean of their own
    /// random covariances (filtered poses are correlated in time, so their scatter alone would
    /// claim too much); its systematic part their mean systematic covariance, which averaging
    /// does not reduce; its calibrations the window's when they were the same throughout.
    pub fn from_window(
        poses: &[MeasuredPose],
        from_ns: i64,
        to_ns: i64,
    ) -> Result<Self, GeometryError> {
        let plain: Vec<Pose> = poses.iter().map(|p| p.whole.pose).collect();
        let mean = mean_pose(&plain)?;
        let n = poses.len() as f64;
        let systematic_cov = poses
            .iter()
            .fold(Mat6::zeros(), |acc, p| acc + p.systematic_cov)
            / n;
        let mean_own_random = poses
            .iter()
            .fold(Mat6::zeros(), |acc, p| acc + p.random().cov)
            / n;
        let cov = window_covariance(&mean.mean.cov, &mean_own_random) + systematic_cov;
        let calibration = poses
            .first()
            .and_then(|p| p.calibration)
            .filter(|c| poses.iter().all(|p| p.calibration == Some(*c)));
        Ok(Self {
            g0_from_b: MeasuredPose {
                whole: PoseCov {
                    pose: mean.mean.pose,
                    cov,
                },
                systematic_cov,
                calibration,
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
    /// `G0_from_G` with its whole covariance and its systematic part: zero when the reference
    /// and the result share their calibrations (it cancels), both parts otherwise. No
    /// calibrations of its own (it is a difference of two measurements).
    pub g0_from_g: MeasuredPose,
    /// `G_from_G0` with its whole covariance: the correction.
    pub g_from_g0: PoseCov,
}

/// A pose as measured: its whole covariance, the systematic part of it told apart, and the
/// calibrations it was measured with. The one type every result, estimate, reference and
/// deformation carries its uncertainty in, and the one place the random part is computed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeasuredPose {
    /// The pose with its whole covariance (random and systematic).
    pub whole: PoseCov,
    /// The systematic part of that covariance: cameras' intrinsics and calibrated links, the
    /// same error in every result of that geometry.
    pub systematic_cov: Mat6,
    /// The calibrations it was measured with, when known.
    pub calibration: Option<CalibrationStamp>,
}

impl MeasuredPose {
    /// An exact pose (no uncertainty, no calibrations).
    pub fn exact(pose: Pose) -> Self {
        Self::whole(PoseCov::exact(pose))
    }

    /// A pose known with its whole covariance alone (no systematic part told apart, no
    /// calibrations known).
    pub fn whole(whole: PoseCov) -> Self {
        Self {
            whole,
            systematic_cov: Mat6::zeros(),
            calibration: None,
        }
    }

    /// The pose.
    pub fn pose(&self) -> &Pose {
        &self.whole.pose
    }

    /// The random part: the whole covariance less the systematic part (the noise, what
    /// averaging and filtering bring down).
    pub fn random(&self) -> PoseCov {
        PoseCov {
            pose: self.whole.pose,
            cov: Self::random_of(&self.whole.cov, &self.systematic_cov),
        }
    }

    /// The random part of a whole covariance with its systematic part: the one place the
    /// split is computed (also for stored covariances read without their pose).
    pub fn random_of(whole_cov: &Mat6, systematic_cov: &Mat6) -> Mat6 {
        whole_cov - systematic_cov
    }

    /// The systematic part alone (the calibrations' error, the same in every result of that
    /// geometry).
    pub fn systematic(&self) -> PoseCov {
        PoseCov {
            pose: self.whole.pose,
            cov: self.systematic_cov,
        }
    }

    /// The standard deviations of the whole, random and systematic covariances.
    pub fn sigmas(&self) -> PartSigmas {
        PartSigmas {
            whole: self.whole.reported_sigmas(),
            random: self.random().reported_sigmas(),
            systematic: self.systematic().reported_sigmas(),
        }
    }
}

/// The sigmas of a measured pose: whole, and its random and systematic parts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PartSigmas {
    /// Of the whole covariance.
    pub whole: ReportedSigmas,
    /// Of its random part.
    pub random: ReportedSigmas,
    /// Of its systematic part.
    pub systematic: ReportedSigmas,
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
    /// The deformation of a result against a reference (see the module docs for which
    /// uncertainty it carries).
    pub fn new(reference: &Reference, measured: &MeasuredPose) -> Self {
        let r = &reference.g0_from_b;
        let shared = r.calibration.is_some() && r.calibration == measured.calibration;
        let (rp, mp) = if shared {
            (r.random(), measured.random())
        } else {
            (r.whole, measured.whole)
        };
        let whole = rp.compose(&mp.inverse());
        let systematic_cov = if shared {
            Mat6::zeros()
        } else {
            r.systematic().compose(&measured.systematic().inverse()).cov
        };
        Self {
            g0_from_g: MeasuredPose {
                whole,
                systematic_cov,
                calibration: None,
            },
            g_from_g0: whole.inverse(),
        }
    }

    /// The deformation as users read it (`G0_from_G`).
    pub fn deformation(&self) -> SmallMotion {
        small_motion(&self.g0_from_g.whole)
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
