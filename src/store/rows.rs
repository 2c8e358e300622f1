//! Rows as both backends return them, and their conversion to domain values.
//!
//! Both schemas give these columns the same names and the same Rust types (64-bit integers,
//! doubles, text, booleans, byte strings), so one row type decodes from either engine and the
//! conversions, with their checks of stored vocabularies, exist once.

use super::codec::{decode_mat6, pose_from_columns};
use super::{Quality, SampleValues, StoreError, StoreResult};
use crate::bank::MeasurementUncertainty;
use crate::deformation::{CalibrationStamp, MeasuredPose, ReferenceVersion};
use crate::geometry::PoseCov;
use crate::model::TargetId;

/// `sqlx::FromRow` for a row struct, on both backends: each named field read from the column of
/// its name, and the `flatten` one (a struct of columns itself) from the same row. It does what
/// sqlx's derive does, without the derive's proc-macro crate, which builds a second copy of sqlx
/// and both database drivers for the compiler's host; a field left out of the list fails to
/// compile.
macro_rules! from_columns {
    ($name:ident { $($field:ident),* $(,)? } $(flatten $flat:ident)?) => {
        impl sqlx::FromRow<'_, sqlx::sqlite::SqliteRow> for $name {
            fn from_row(row: &sqlx::sqlite::SqliteRow) -> Result<Self, sqlx::Error> {
                use sqlx::Row as _;
                Ok(Self {
                    $($flat: sqlx::FromRow::from_row(row)?,)?
                    $($field: row.try_get(stringify!($field))?,)*
                })
            }
        }
        impl sqlx::FromRow<'_, sqlx::postgres::PgRow> for $name {
            fn from_row(row: &sqlx::postgres::PgRow) -> Result<Self, sqlx::Error> {
                use sqlx::Row as _;
                Ok(Self {
                    $($flat: sqlx::FromRow::from_row(row)?,)?
                    $($field: row.try_get(stringify!($field))?,)*
                })
            }
        }
    };
}
pub(super) use from_columns;

/// The seven pose columns every row with a pose has.
pub(super) struct PoseColumns {
    tx_mm: f64,
    ty_mm: f64,
    tz_mm: f64,
    qw: f64,
    qx: f64,
    qy: f64,
    qz: f64,
}

from_columns!(PoseColumns {
    tx_mm,
    ty_mm,
    tz_mm,
    qw,
    qx,
    qy,
    qz
});

impl PoseColumns {
    /// The pose they hold.
    fn pose(&self) -> crate::geometry::Pose {
        pose_from_columns([
            self.tx_mm, self.ty_mm, self.tz_mm, self.qw, self.qx, self.qy, self.qz,
        ])
    }
}

/// The key of a rollup row (ordered as the table's primary key).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub(super) struct RollupKey {
    pub target_id: i64,
    /// The result source's column value.
    pub source: i64,
    pub width_s: i64,
    pub bucket_ns: i64,
}

/// A stored rollup row: its key, its counts and its statistics (encoded).
#[derive(Debug, Clone)]
pub(super) struct RollupRow {
    pub target_id: i64,
    pub source: i64,
    pub width_s: i64,
    pub bucket_ns: i64,
    /// Results in the bucket.
    pub n: i64,
    /// Of them, with a deformation (a reference was set).
    pub n_def: i64,
    pub stats: Vec<u8>,
}

from_columns!(RollupRow {
    target_id,
    source,
    width_s,
    bucket_ns,
    n,
    n_def,
    stats
});

impl RollupRow {
    /// Its key.
    pub(super) fn key(&self) -> RollupKey {
        RollupKey {
            target_id: self.target_id,
            source: self.source,
            width_s: self.width_s,
            bucket_ns: self.bucket_ns,
        }
    }
}

/// A sample row.
pub(super) struct SampleRow {
    pub time_ns: i64,
    pose: PoseColumns,
    uncertainty_kind: i64,
    uncertainty: Option<Vec<u8>>,
    reprojection_rms_px: Option<f64>,
    points: Option<i64>,
    disposition: String,
    outlier: bool,
    nis: Option<f64>,
    received_ns: i64,
}

from_columns!(SampleRow { time_ns, uncertainty_kind, uncertainty, reprojection_rms_px, points, disposition, outlier, nis, received_ns } flatten pose);

impl SampleRow {
    /// The sample's values as given.
    pub(super) fn values(&self) -> StoreResult<SampleValues> {
        Ok(SampleValues {
            pose: self.pose.pose(),
            uncertainty: MeasurementUncertainty::from_columns(
                self.uncertainty_kind,
                self.uncertainty.as_deref(),
            )?,
            quality: Quality {
                reprojection_rms_px: self.reprojection_rms_px,
                points: self.points.and_then(|p| u32::try_from(p).ok()),
            },
        })
    }

    /// The whole stored sample.
    pub(super) fn into_sample(self) -> StoreResult<StoredSample> {
        Ok(StoredSample {
            time_ns: self.time_ns,
            values: self.values()?,
            disposition: crate::filter::DispositionKind::parse(&self.disposition).ok_or_else(
                || {
                    StoreError::Malformed(format!(
                        "a sample at {} has the unknown disposition `{}`",
                        self.time_ns, self.disposition
                    ))
                },
            )?,
            outlier: self.outlier,
            nis: self.nis,
            received_ns: self.received_ns,
        })
    }
}

/// A stored raw sample.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredSample {
    /// Measurement time (ns).
    pub time_ns: i64,
    /// Its values as given.
    pub values: SampleValues,
    /// What the filter did with it.
    pub disposition: crate::filter::DispositionKind,
    /// Flagged as an outlier.
    pub outlier: bool,
    /// Normalised innovation squared.
    pub nis: Option<f64>,
    /// When it was received (ns).
    pub received_ns: i64,
}

/// A result row.
pub(super) struct ResultRow {
    pub time_ns: i64,
    pose: PoseColumns,
    cov: Vec<u8>,
    status: String,
    age_s: f64,
    chi2: Option<f64>,
    reference_version: Option<i64>,
    def_rx_arcsec: Option<f64>,
    def_ry_arcsec: Option<f64>,
    def_rz_arcsec: Option<f64>,
    def_tx_mm: Option<f64>,
    def_ty_mm: Option<f64>,
    def_tz_mm: Option<f64>,
    /// The systematic part of `cov`; null in rows written before it was kept (zero).
    cov_systematic: Option<Vec<u8>>,
    calibration_stamp: Option<i64>,
}

from_columns!(ResultRow { time_ns, cov, status, age_s, chi2, reference_version, def_rx_arcsec, def_ry_arcsec, def_rz_arcsec, def_tx_mm, def_ty_mm, def_tz_mm, cov_systematic, calibration_stamp } flatten pose);

impl ResultRow {
    /// The stored result.
    pub(super) fn into_result(self) -> StoreResult<StoredResult> {
        let deformation = match (
            self.reference_version,
            self.def_rx_arcsec,
            self.def_ry_arcsec,
            self.def_rz_arcsec,
            self.def_tx_mm,
            self.def_ty_mm,
            self.def_tz_mm,
        ) {
            (Some(v), Some(a), Some(b), Some(c), Some(x), Some(y), Some(z)) => {
                Some((v, [a, b, c], [x, y, z]))
            }
            _ => None,
        };
        Ok(StoredResult {
            time_ns: self.time_ns,
            estimate: measured_pose(
                &self.pose,
                &self.cov,
                self.cov_systematic.as_deref(),
                self.calibration_stamp,
            )?,
            status: crate::bank::TargetStatus::parse(&self.status).ok_or_else(|| {
                StoreError::Malformed(format!(
                    "a result at {} has the unknown status `{}`",
                    self.time_ns, self.status
                ))
            })?,
            age_s: self.age_s,
            chi2: self.chi2,
            deformation,
        })
    }
}

/// A stored pose as measured, from its columns: the systematic covariance is null in rows
/// written before it was kept (read as zero), and so is the calibrations' stamp (read as not
/// known).
fn measured_pose(
    pose: &PoseColumns,
    cov: &[u8],
    systematic: Option<&[u8]>,
    stamp: Option<i64>,
) -> StoreResult<MeasuredPose> {
    Ok(MeasuredPose {
        whole: PoseCov {
            pose: pose.pose(),
            cov: decode_mat6(cov)?,
        },
        systematic_cov: systematic.map_or(Ok(crate::geometry::Mat6::zeros()), decode_mat6)?,
        calibration: stamp.map(CalibrationStamp),
    })
}

/// A stored target result.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredResult {
    /// Its time (ns).
    pub time_ns: i64,
    /// `target_from_base` with its whole covariance, the systematic part (zero for rows stored
    /// before it was kept) and the calibrations (`None` for rows stored before they were kept).
    pub estimate: MeasuredPose,
    /// Its status.
    pub status: crate::bank::TargetStatus,
    /// Age of the newest sample behind it (s).
    pub age_s: f64,
    /// Chi-square of redundant paths.
    pub chi2: Option<f64>,
    /// `(reference version, rotation arcsec, translation mm)` of the deformation, if any.
    pub deformation: Option<(i64, [f64; 3], [f64; 3])>,
}

/// A reference row.
pub(super) struct ReferenceRow {
    version: i64,
    pose: PoseColumns,
    cov: Vec<u8>,
    origin: String,
    window_from_ns: Option<i64>,
    window_to_ns: Option<i64>,
    window_count: Option<i64>,
    created_ns: i64,
    cov_systematic: Option<Vec<u8>>,
    calibration_stamp: Option<i64>,
}

from_columns!(ReferenceRow { version, cov, origin, window_from_ns, window_to_ns, window_count, created_ns, cov_systematic, calibration_stamp } flatten pose);

impl ReferenceRow {
    /// The stored reference version.
    pub(super) fn into_reference(self) -> StoreResult<ReferenceVersion> {
        let origin = match (
            self.origin.as_str(),
            self.window_from_ns,
            self.window_to_ns,
            self.window_count,
        ) {
            ("window", Some(from_ns), Some(to_ns), Some(count)) => {
                crate::deformation::ReferenceOrigin::Window {
                    from_ns,
                    to_ns,
                    count: usize::try_from(count).unwrap_or(0),
                }
            }
            _ => crate::deformation::ReferenceOrigin::Explicit,
        };
        Ok(ReferenceVersion {
            version: self.version,
            reference: crate::deformation::Reference {
                g0_from_b: measured_pose(
                    &self.pose,
                    &self.cov,
                    self.cov_systematic.as_deref(),
                    self.calibration_stamp,
                )?,
                origin,
            },
            created_ns: self.created_ns,
        })
    }
}

/// A calibration row.
pub(super) struct CalibrationRow {
    version: i64,
    valid_from_ns: i64,
    pose: PoseColumns,
    cov: Vec<u8>,
    created_ns: i64,
}

from_columns!(CalibrationRow { version, valid_from_ns, cov, created_ns } flatten pose);

impl CalibrationRow {
    /// The stored calibration version.
    pub(super) fn into_calibration(self) -> StoreResult<StoredCalibration> {
        Ok(StoredCalibration {
            version: self.version,
            valid_from_ns: self.valid_from_ns,
            parent_from_child: PoseCov {
                pose: self.pose.pose(),
                cov: decode_mat6(&self.cov)?,
            },
            created_ns: self.created_ns,
        })
    }
}

/// A stored calibration version.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredCalibration {
    /// Its version (1, 2, ...).
    pub version: i64,
    /// From when it is valid (ns).
    pub valid_from_ns: i64,
    /// `parent_from_child` with covariance.
    pub parent_from_child: PoseCov,
    /// When it was stored (ns).
    pub created_ns: i64,
}

/// A stored alarm transition.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredAlarm {
    /// Its id.
    pub id: i64,
    /// Target index in the installation.
    pub target: TargetId,
    /// The transition.
    pub transition: crate::alarms::Transition,
    /// Its acknowledgement, once given.
    pub ack: Option<Acknowledgement>,
}

/// Someone's acknowledgement of an alarm transition.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Acknowledgement {
    /// Who, as they said.
    pub by: String,
    /// When (ns, server clock).
    pub at_ns: i64,
    /// Why or what was done, as they said.
    pub note: Option<String>,
}

/// An alarm row.
pub(super) struct AlarmRow {
    alarm_id: i64,
    target_id: i64,
    time_ns: i64,
    kind: String,
    from_level: String,
    to_level: String,
    value: f64,
    message: String,
    unit: Option<String>,
    acknowledged_by: Option<String>,
    acknowledged_ns: Option<i64>,
    ack_note: Option<String>,
}

from_columns!(AlarmRow {
    alarm_id,
    target_id,
    time_ns,
    kind,
    from_level,
    to_level,
    value,
    message,
    unit,
    acknowledged_by,
    acknowledged_ns,
    ack_note
});

/// The alarm of a row; `target_ids` maps the row's target id to the installation's index.
pub(super) fn alarm_of_row(row: AlarmRow, target_ids: &[i64]) -> StoreResult<StoredAlarm> {
    use crate::alarms::{AlarmKind, Level, ValueUnit};
    let AlarmRow {
        alarm_id: id,
        target_id: tid,
        time_ns,
        kind,
        from_level: from,
        to_level: to,
        value,
        message,
        unit,
        acknowledged_by: by,
        acknowledged_ns: at_ns,
        ack_note: note,
    } = row;
    let malformed = || StoreError::Malformed(format!("alarm {id} of kind `{kind}`"));
    let kind_ = AlarmKind::parse(&kind).ok_or_else(malformed)?;
    let unit = match unit {
        Some(u) => ValueUnit::parse(&u).ok_or_else(malformed)?,
        // Rows from before units were stored held the rotation.
        None => match kind_ {
            AlarmKind::Deformation => ValueUnit::Arcsec,
            AlarmKind::Rate => ValueUnit::ArcsecPerS,
            AlarmKind::Stale => ValueUnit::None,
        },
    };
    Ok(StoredAlarm {
        id,
        target: target_ids
            .iter()
            .position(|t| *t == tid)
            .map(TargetId)
            .ok_or_else(malformed)?,
        transition: crate::alarms::Transition {
            kind: kind_,
            time_ns,
            from: Level::parse(&from).ok_or_else(malformed)?,
            to: Level::parse(&to).ok_or_else(malformed)?,
            value,
            unit,
            message,
        },
        ack: match (by, at_ns) {
            (Some(by), Some(at_ns)) => Some(Acknowledgement { by, at_ns, note }),
            _ => None,
        },
    })
}

/// A sample as its row is written (values checked finite, ids resolved).
pub(super) struct SampleColumns {
    pub link_id: i64,
    pub time_ns: i64,
    /// `[tx, ty, tz, qw, qx, qy, qz]`.
    pub pose: [f64; 7],
    pub uncertainty_kind: i64,
    pub uncertainty: Option<Vec<u8>>,
    pub reprojection_rms_px: Option<f64>,
    pub points: Option<i64>,
    pub disposition: &'static str,
    pub outlier: bool,
    pub nis: Option<f64>,
    pub received_ns: i64,
}

/// A result as its row is written (values checked finite, ids resolved).
pub(super) struct ResultColumns {
    pub target_id: i64,
    pub source: i64,
    pub time_ns: i64,
    /// `[tx, ty, tz, qw, qx, qy, qz]`.
    pub pose: [f64; 7],
    pub cov: Vec<u8>,
    /// Reported sigmas: rotation x y z (arcsec), translation x y z (mm).
    pub sigmas: [f64; 6],
    pub status: &'static str,
    pub age_s: f64,
    pub chi2: Option<f64>,
    /// The reference version and the deformation: rotation (arcsec), translation (mm).
    pub deformation: Option<(i64, [f64; 6])>,
    pub cov_systematic: Vec<u8>,
    pub calibration_stamp: Option<i64>,
}

/// A reference or calibration version as its row is written.
pub(super) struct VersionColumns {
    /// `[tx, ty, tz, qw, qx, qy, qz]`.
    pub pose: [f64; 7],
    pub cov: Vec<u8>,
}

/// A recorded acceptance of the rig.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredAcceptance {
    /// Its id.
    pub id: i64,
    /// When it was recorded (ns, the server's clock).
    pub created_ns: i64,
    /// Who ran it.
    pub by: String,
    /// Their note.
    pub note: Option<String>,
    /// Whether it passed.
    pub passed: bool,
    /// Its record (JSON, as the service wrote it).
    pub record_json: String,
}

/// An acceptance's row, as read.
pub(super) type AcceptanceRow = (i64, i64, String, Option<String>, bool, String);

impl From<AcceptanceRow> for StoredAcceptance {
    fn from((id, created_ns, by, note, passed, record_json): AcceptanceRow) -> Self {
        Self {
            id,
            created_ns,
            by,
            note,
            passed,
            record_json,
        }
    }
}
