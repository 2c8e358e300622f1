//! Conversions between domain values and columns.

use super::StoreError;
use crate::bank::MeasurementUncertainty;
use crate::geometry::{Mat6, Pose, ReportedSigmas};
use nalgebra::{Quaternion, Translation3, UnitQuaternion};

/// A 6x6 matrix as 36 little-endian f64, column-major.
pub(crate) fn encode_mat6(m: &Mat6) -> Vec<u8> {
    let mut out = Vec::with_capacity(36 * 8);
    for v in m.iter() {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

pub(crate) fn decode_f64s(bytes: &[u8], n: usize) -> Result<Vec<f64>, StoreError> {
    if bytes.len() != n * 8 {
        return Err(StoreError::Malformed(format!(
            "a blob of {} bytes where {} numbers were expected",
            bytes.len(),
            n
        )));
    }
    Ok(bytes
        .chunks_exact(8)
        .map(|c| {
            let mut a = [0u8; 8];
            a.copy_from_slice(c);
            f64::from_le_bytes(a)
        })
        .collect())
}

/// Numbers in a covariance kept as its upper triangle.
const SYM6_LEN: usize = 21;

/// A covariance as the 21 little-endian f64 of its upper triangle, column by column: its
/// symmetric part, so exact for a symmetric matrix (each off-diagonal pair is averaged, which
/// changes nothing when the two agree). 168 bytes against [`encode_mat6`]'s 288: the results'
/// two covariances are most of a result row, and a result row most of what a sample brings
/// to the history.
pub(crate) fn encode_sym6(m: &Mat6) -> Vec<u8> {
    let mut out = Vec::with_capacity(SYM6_LEN * 8);
    for j in 0..6 {
        for i in 0..=j {
            let (upper, lower) = (m[(i, j)], m[(j, i)]);
            let v = if upper.to_bits() == lower.to_bits() {
                upper
            } else {
                0.5 * upper + 0.5 * lower
            };
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// A 6x6 matrix from either form: 36 numbers ([`encode_mat6`]) or a symmetric matrix's 21
/// ([`encode_sym6`]).
pub(crate) fn decode_mat6(bytes: &[u8]) -> Result<Mat6, StoreError> {
    if bytes.len() == SYM6_LEN * 8 {
        let v = decode_f64s(bytes, SYM6_LEN)?;
        let mut m = Mat6::zeros();
        let mut k = 0;
        for j in 0..6 {
            for i in 0..=j {
                m[(i, j)] = v[k];
                m[(j, i)] = v[k];
                k += 1;
            }
        }
        Ok(m)
    } else {
        Ok(Mat6::from_column_slice(&decode_f64s(bytes, 36)?))
    }
}

/// A pose as `[tx, ty, tz, qw, qx, qy, qz]`.
pub(crate) fn pose_columns(p: &Pose) -> [f64; 7] {
    let t = p.translation.vector;
    let q = p.rotation.quaternion();
    [t.x, t.y, t.z, q.w, q.i, q.j, q.k]
}

pub(crate) fn pose_from_columns(c: [f64; 7]) -> Pose {
    Pose::from_parts(
        Translation3::new(c[0], c[1], c[2]),
        UnitQuaternion::new_unchecked(Quaternion::new(c[3], c[4], c[5], c[6])),
    )
}

/// A sample's uncertainty as stored: a kind (0 the link's default, 1 sigmas, 2 a covariance)
/// and its bytes.
impl MeasurementUncertainty {
    pub(crate) fn columns(&self) -> (i64, Option<Vec<u8>>) {
        match self {
            MeasurementUncertainty::Default => (0, None),
            MeasurementUncertainty::Sigmas(s) => {
                let mut out = Vec::with_capacity(48);
                for v in s.rotation_arcsec.iter().chain(&s.translation_mm) {
                    out.extend_from_slice(&v.to_le_bytes());
                }
                (1, Some(out))
            }
            MeasurementUncertainty::Covariance(c) => (2, Some(encode_mat6(c))),
        }
    }

    pub(crate) fn from_columns(kind: i64, blob: Option<&[u8]>) -> Result<Self, StoreError> {
        match (kind, blob) {
            (0, _) => Ok(MeasurementUncertainty::Default),
            (1, Some(b)) => {
                let v = decode_f64s(b, 6)?;
                Ok(MeasurementUncertainty::Sigmas(ReportedSigmas {
                    rotation_arcsec: [v[0], v[1], v[2]],
                    translation_mm: [v[3], v[4], v[5]],
                }))
            }
            (2, Some(b)) => Ok(MeasurementUncertainty::Covariance(decode_mat6(b)?)),
            _ => Err(StoreError::Malformed(format!("uncertainty kind {kind}"))),
        }
    }
}

/// Pose-estimation quality reported with a sample.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Quality {
    /// Reprojection RMS (px).
    pub reprojection_rms_px: Option<f64>,
    /// Number of points used.
    pub points: Option<u32>,
}

/// What makes two samples of one link and time the same: their values as given.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SampleValues {
    /// The measured pose.
    pub pose: Pose,
    /// Its uncertainty as given.
    pub uncertainty: MeasurementUncertainty,
    /// Its quality as given.
    pub quality: Quality,
}

impl SampleValues {
    /// Equality of the stored numbers, bit for bit (a retry sends the same text, so parses to
    /// the same numbers).
    pub fn same_as(&self, other: &SampleValues) -> bool {
        pose_columns(&self.pose)
            .iter()
            .zip(pose_columns(&other.pose).iter())
            .all(|(a, b)| a.to_bits() == b.to_bits())
            && self.uncertainty.columns() == other.uncertainty.columns()
            && self.quality.points == other.quality.points
            && self.quality.reprojection_rms_px.map(f64::to_bits)
                == other.quality.reprojection_rms_px.map(f64::to_bits)
    }
}

/// The `source` column of a result: 0 raw, 1 filtered.
pub(crate) fn source_column(source: crate::bank::ResultSource) -> i64 {
    match source {
        crate::bank::ResultSource::Raw => 0,
        crate::bank::ResultSource::Filtered => 1,
    }
}

/// A result's random covariance from its stored `cov` and `cov_systematic` (null in rows
/// written before it was kept: all of `cov`); `None` when a blob does not decode.
pub(crate) fn random_covariance(cov: &[u8], systematic: Option<&[u8]>) -> Option<Mat6> {
    let whole = decode_mat6(cov).ok()?;
    match systematic {
        Some(s) => Some(crate::deformation::MeasuredPose::random_of(
            &whole,
            &decode_mat6(s).ok()?,
        )),
        None => Some(whole),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A covariance from a 6x6 factor: `a aᵀ`, symmetric by construction (each entry's two
    /// sums run in the same order).
    fn covariance(a: &[f64]) -> Mat6 {
        let a = Mat6::from_column_slice(a);
        let mut c = Mat6::zeros();
        for i in 0..6 {
            for j in 0..6 {
                c[(i, j)] = (0..6).map(|k| a[(i, k)] * a[(j, k)]).sum();
            }
        }
        c
    }

    proptest! {
        /// A symmetric matrix comes back bit for bit from its 21 numbers.
        #[test]
        fn a_symmetric_matrix_survives_its_upper_triangle(
            a in proptest::collection::vec(-1e3f64..1e3, 36),
        ) {
            let c = covariance(&a);
            prop_assert_eq!(c, c.transpose());
            let bytes = encode_sym6(&c);
            prop_assert_eq!(bytes.len(), 168);
            let back = decode_mat6(&bytes).map_err(|e| TestCaseError::fail(e.to_string()))?;
            for (x, y) in c.iter().zip(back.iter()) {
                prop_assert_eq!(x.to_bits(), y.to_bits());
            }
        }

        /// A matrix whose two triangles disagree (rounding in a product) is kept as its
        /// symmetric part, `(m + mᵀ) / 2`.
        #[test]
        fn an_asymmetric_matrix_is_kept_as_its_symmetric_part(
            a in proptest::collection::vec(-1e3f64..1e3, 36),
        ) {
            let m = Mat6::from_column_slice(&a);
            let back = decode_mat6(&encode_sym6(&m))
                .map_err(|e| TestCaseError::fail(e.to_string()))?;
            let expected = (m + m.transpose()) * 0.5;
            for (x, y) in expected.iter().zip(back.iter()) {
                prop_assert!((x - y).abs() <= 1e-12 * x.abs().max(1.0), "{} against {}", x, y);
            }
            prop_assert_eq!(back, back.transpose());
        }
    }

    #[test]
    fn the_full_form_still_reads_and_other_lengths_are_refused() {
        let m = Mat6::from_fn(|i, j| (10 * i + j) as f64);
        let full = encode_mat6(&m);
        assert_eq!(full.len(), 288);
        assert_eq!(decode_mat6(&full).ok(), Some(m));
        let Err(e) = decode_mat6(&full[..160]) else {
            unreachable!("160 bytes decoded")
        };
        assert!(e.to_string().contains("160 bytes"), "{e}");
    }
}
