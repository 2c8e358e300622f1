//! Queries of the read side.

use super::codec::{decode_mat6, pose_from_columns};
use super::{Quality, SampleValues, Store, StoreResult, StoredUncertainty};
use crate::chain::LinkId;
use crate::geometry::{Pose, PoseCov};

pub(super) const SAMPLE_SELECT_BY_RANGE: &str = "select time_ns, tx_mm, ty_mm, tz_mm, qw, qx, qy, qz, uncertainty_kind, uncertainty, \
     reprojection_rms_px, points, disposition, outlier, nis, received_ns \
     from samples where link_id = ? and time_ns >= ? and time_ns <= ? order by time_ns limit ?";

pub(super) const RESULT_SELECT_BY_RANGE: &str = "select time_ns, tx_mm, ty_mm, tz_mm, qw, qx, qy, qz, cov, status, age_s, chi2, \
     reference_version, def_rx_arcsec, def_ry_arcsec, def_rz_arcsec, def_tx_mm, def_ty_mm, def_tz_mm \
     from results where target_id = ? and source = ? and time_ns >= ? and time_ns <= ? order by time_ns limit ?";

#[derive(sqlx::FromRow)]
pub(super) struct SampleRow {
    pub time_ns: i64,
    tx_mm: f64,
    ty_mm: f64,
    tz_mm: f64,
    qw: f64,
    qx: f64,
    qy: f64,
    qz: f64,
    uncertainty_kind: i64,
    uncertainty: Option<Vec<u8>>,
    reprojection_rms_px: Option<f64>,
    points: Option<i64>,
    disposition: String,
    outlier: bool,
    nis: Option<f64>,
    received_ns: i64,
}

impl SampleRow {
    pub(super) fn values(&self) -> StoreResult<SampleValues> {
        Ok(SampleValues {
            pose: pose_from_columns([
                self.tx_mm, self.ty_mm, self.tz_mm, self.qw, self.qx, self.qy, self.qz,
            ]),
            uncertainty: StoredUncertainty::from_columns(
                self.uncertainty_kind,
                self.uncertainty.as_deref(),
            )?,
            quality: Quality {
                reprojection_rms_px: self.reprojection_rms_px,
                points: self.points.and_then(|p| u32::try_from(p).ok()),
            },
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

#[derive(sqlx::FromRow)]
pub(super) struct ResultRow {
    time_ns: i64,
    tx_mm: f64,
    ty_mm: f64,
    tz_mm: f64,
    qw: f64,
    qx: f64,
    qy: f64,
    qz: f64,
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
}

impl ResultRow {
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
            estimate: PoseCov {
                pose: pose_from_columns([
                    self.tx_mm, self.ty_mm, self.tz_mm, self.qw, self.qx, self.qy, self.qz,
                ]),
                cov: decode_mat6(&self.cov)?,
            },
            status: crate::bank::TargetStatus::parse(&self.status).ok_or_else(|| {
                super::StoreError::Malformed(format!(
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

/// A stored target result.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredResult {
    /// Its time (ns).
    pub time_ns: i64,
    /// `target_from_base` with covariance.
    pub estimate: PoseCov,
    /// Its status.
    pub status: crate::bank::TargetStatus,
    /// Age of the newest sample behind it (s).
    pub age_s: f64,
    /// Chi-square of redundant paths.
    pub chi2: Option<f64>,
    /// `(reference version, rotation arcsec, translation mm)` of the deformation, if any.
    pub deformation: Option<(i64, [f64; 3], [f64; 3])>,
}

#[derive(sqlx::FromRow)]
struct ReferenceRow {
    version: i64,
    tx_mm: f64,
    ty_mm: f64,
    tz_mm: f64,
    qw: f64,
    qx: f64,
    qy: f64,
    qz: f64,
    cov: Vec<u8>,
    origin: String,
    window_from_ns: Option<i64>,
    window_to_ns: Option<i64>,
    window_count: Option<i64>,
    created_ns: i64,
}

/// A stored reference version.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredReference {
    /// Its version (1, 2, ...).
    pub version: i64,
    /// The reference.
    pub reference: crate::deformation::Reference,
    /// When it was set (ns).
    pub created_ns: i64,
}

#[derive(sqlx::FromRow)]
struct CalibrationRow {
    version: i64,
    valid_from_ns: i64,
    tx_mm: f64,
    ty_mm: f64,
    tz_mm: f64,
    qw: f64,
    qx: f64,
    qy: f64,
    qz: f64,
    cov: Vec<u8>,
    created_ns: i64,
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

fn pose7(r: [f64; 7]) -> Pose {
    pose_from_columns(r)
}

impl Store {
    /// Stored samples of a link in `[from_ns, to_ns]`, oldest first, at most `limit`.
    pub async fn samples(
        &self,
        link: LinkId,
        from_ns: i64,
        to_ns: i64,
        limit: i64,
    ) -> StoreResult<Vec<StoredSample>> {
        let rows: Vec<SampleRow> = sqlx::query_as(SAMPLE_SELECT_BY_RANGE)
            .bind(self.link_ids[link.0])
            .bind(from_ns)
            .bind(to_ns)
            .bind(limit)
            .fetch_all(&self.pool)
            .await?;
        rows.into_iter()
            .map(|r| {
                Ok(StoredSample {
                    time_ns: r.time_ns,
                    values: r.values()?,
                    disposition: crate::filter::DispositionKind::parse(&r.disposition).ok_or_else(
                        || {
                            super::StoreError::Malformed(format!(
                                "a sample at {} has the unknown disposition `{}`",
                                r.time_ns, r.disposition
                            ))
                        },
                    )?,
                    outlier: r.outlier,
                    nis: r.nis,
                    received_ns: r.received_ns,
                })
            })
            .collect()
    }

    /// Stored results of a target in `[from_ns, to_ns]`, oldest first, at most `limit`.
    pub async fn results(
        &self,
        target: usize,
        filtered: bool,
        from_ns: i64,
        to_ns: i64,
        limit: i64,
    ) -> StoreResult<Vec<StoredResult>> {
        let rows: Vec<ResultRow> = sqlx::query_as(RESULT_SELECT_BY_RANGE)
            .bind(self.target_ids[target])
            .bind(i64::from(filtered))
            .bind(from_ns)
            .bind(to_ns)
            .bind(limit)
            .fetch_all(&self.pool)
            .await?;
        rows.into_iter().map(ResultRow::into_result).collect()
    }

    /// The paper's statistics (Table 4/5) of a target's results in `[from_ns, to_ns]`, with the
    /// times of the first and last result. The rows are streamed and folded one by one on a
    /// blocking thread, through a read-only rusqlite connection of its own (the pool's driver
    /// costs several microseconds a row, which over millions of results is many seconds):
    /// memory does not grow with the window.
    pub async fn pose_stats(
        &self,
        target: usize,
        filtered: bool,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<(Option<crate::stats::PoseStats>, Option<(i64, i64)>)> {
        let path = self.path.clone();
        let target_id = self.target_ids[target];
        let scan = move || -> rusqlite::Result<_> {
            use rusqlite::OpenFlags;
            let conn = rusqlite::Connection::open_with_flags(
                &path,
                OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
            )?;
            conn.busy_timeout(std::time::Duration::from_secs(10))?;
            let mut stmt = conn.prepare(
                "select time_ns, tx_mm, ty_mm, tz_mm, qw, qx, qy, qz from results \
                 where target_id = ?1 and source = ?2 and time_ns >= ?3 and time_ns <= ?4 \
                 order by time_ns",
            )?;
            let mut rows = stmt.query(rusqlite::params![
                target_id,
                i64::from(filtered),
                from_ns,
                to_ns
            ])?;
            let mut acc = crate::stats::PoseStatsAccumulator::default();
            let mut span: Option<(i64, i64)> = None;
            while let Some(row) = rows.next()? {
                let t: i64 = row.get(0)?;
                let mut c = [0.0; 7];
                for (i, v) in c.iter_mut().enumerate() {
                    *v = row.get(i + 1)?;
                }
                acc.push(&pose_from_columns(c));
                span = Some((span.map_or(t, |(first, _)| first), t));
            }
            Ok((acc.finish(), span))
        };
        tokio::task::spawn_blocking(scan)
            .await
            .map_err(|e| super::StoreError::Scan(e.to_string()))?
            .map_err(|e| super::StoreError::Scan(e.to_string()))
    }

    /// How many results of a target are stored in `[from_ns, to_ns]`.
    pub async fn count_results(
        &self,
        target: usize,
        filtered: bool,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<u64> {
        let (n,): (i64,) = sqlx::query_as(
            "select count(*) from results where target_id = ? and source = ? and time_ns >= ? and time_ns <= ?",
        )
        .bind(self.target_ids[target])
        .bind(i64::from(filtered))
        .bind(from_ns)
        .bind(to_ns)
        .fetch_one(&self.pool)
        .await?;
        Ok(u64::try_from(n).unwrap_or(0))
    }

    /// How many samples of a link are stored in `[from_ns, to_ns]`.
    pub async fn count_samples(&self, link: LinkId, from_ns: i64, to_ns: i64) -> StoreResult<u64> {
        let (n,): (i64,) = sqlx::query_as(
            "select count(*) from samples where link_id = ? and time_ns >= ? and time_ns <= ?",
        )
        .bind(self.link_ids[link.0])
        .bind(from_ns)
        .bind(to_ns)
        .fetch_one(&self.pool)
        .await?;
        Ok(u64::try_from(n).unwrap_or(0))
    }

    /// The stored results of a target nearest to `at_ns`: the newest at or before it and the
    /// oldest after it.
    pub async fn results_around(
        &self,
        target: usize,
        filtered: bool,
        at_ns: i64,
    ) -> StoreResult<(Option<StoredResult>, Option<StoredResult>)> {
        const COLUMNS: &str = "time_ns, tx_mm, ty_mm, tz_mm, qw, qx, qy, qz, cov, status, age_s, chi2, \
             reference_version, def_rx_arcsec, def_ry_arcsec, def_rz_arcsec, def_tx_mm, def_ty_mm, def_tz_mm";
        let before: Option<ResultRow> = sqlx::query_as(&format!(
            "select {COLUMNS} from results where target_id = ? and source = ? and time_ns <= ? order by time_ns desc limit 1"
        ))
        .bind(self.target_ids[target])
        .bind(i64::from(filtered))
        .bind(at_ns)
        .fetch_optional(&self.pool)
        .await?;
        let after: Option<ResultRow> = sqlx::query_as(&format!(
            "select {COLUMNS} from results where target_id = ? and source = ? and time_ns > ? order by time_ns asc limit 1"
        ))
        .bind(self.target_ids[target])
        .bind(i64::from(filtered))
        .bind(at_ns)
        .fetch_optional(&self.pool)
        .await?;
        Ok((
            before.map(ResultRow::into_result).transpose()?,
            after.map(ResultRow::into_result).transpose()?,
        ))
    }

    /// The newest stored result of a target.
    pub async fn latest_result(
        &self,
        target: usize,
        filtered: bool,
    ) -> StoreResult<Option<StoredResult>> {
        Ok(self.results_around(target, filtered, i64::MAX).await?.0)
    }

    /// Every reference version of a target, oldest first.
    pub async fn references(&self, target: usize) -> StoreResult<Vec<StoredReference>> {
        let rows: Vec<ReferenceRow> = sqlx::query_as(
            "select version, tx_mm, ty_mm, tz_mm, qw, qx, qy, qz, cov, origin, window_from_ns, window_to_ns, \
             window_count, created_ns from target_references where target_id = ? order by version",
        )
        .bind(self.target_ids[target])
        .fetch_all(&self.pool)
        .await?;
        rows.into_iter()
            .map(|r| {
                let origin = match (
                    r.origin.as_str(),
                    r.window_from_ns,
                    r.window_to_ns,
                    r.window_count,
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
                Ok(StoredReference {
                    version: r.version,
                    reference: crate::deformation::Reference {
                        g0_from_b: PoseCov {
                            pose: pose7([r.tx_mm, r.ty_mm, r.tz_mm, r.qw, r.qx, r.qy, r.qz]),
                            cov: decode_mat6(&r.cov)?,
                        },
                        origin,
                    },
                    created_ns: r.created_ns,
                })
            })
            .collect()
    }

    /// Every calibration version of a link, oldest first.
    pub async fn calibrations(&self, link: LinkId) -> StoreResult<Vec<StoredCalibration>> {
        let rows: Vec<CalibrationRow> = sqlx::query_as(
            "select version, valid_from_ns, tx_mm, ty_mm, tz_mm, qw, qx, qy, qz, cov, created_ns \
             from calibrations where link_id = ? order by version",
        )
        .bind(self.link_ids[link.0])
        .fetch_all(&self.pool)
        .await?;
        rows.into_iter()
            .map(|r| {
                Ok(StoredCalibration {
                    version: r.version,
                    valid_from_ns: r.valid_from_ns,
                    parent_from_child: PoseCov {
                        pose: pose7([r.tx_mm, r.ty_mm, r.tz_mm, r.qw, r.qx, r.qy, r.qz]),
                        cov: decode_mat6(&r.cov)?,
                    },
                    created_ns: r.created_ns,
                })
            })
            .collect()
    }

    /// The newest manual restart of each link's filter: when (ns, wall clock), who, why.
    pub async fn last_link_resets(
        &self,
    ) -> StoreResult<Vec<(LinkId, i64, Option<String>, Option<String>)>> {
        let rows: Vec<(i64, i64, Option<String>, Option<String>)> = sqlx::query_as(
            "select r.link_id, r.created_ns, r.by_name, r.note from link_resets r \
             where r.created_ns = (select max(created_ns) from link_resets where link_id = r.link_id)",
        )
        .fetch_all(&self.pool)
        .await?;
        Ok(rows
            .into_iter()
            .filter_map(|(id, t, by, note)| {
                self.link_ids
                    .iter()
                    .position(|l| *l == id)
                    .map(|i| (LinkId(i), t, by, note))
            })
            .collect())
    }

    /// The persisted filter state: `(installation digest, state)`.
    pub async fn filter_state(&self) -> StoreResult<Option<(String, String)>> {
        Ok(
            sqlx::query_as("select installation_digest, state from filter_state where id = 1")
                .fetch_optional(&self.pool)
                .await?,
        )
    }
}

/// A stored alarm transition.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredAlarm {
    /// Its id.
    pub id: i64,
    /// Target index in the installation.
    pub target: usize,
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

/// The columns of an alarm row, in [`ALARM_COLUMNS`] order.
type AlarmRow = (
    i64,
    i64,
    i64,
    String,
    String,
    String,
    f64,
    String,
    Option<String>,
    Option<String>,
    Option<i64>,
    Option<String>,
);

/// What an alarm read selects.
const ALARM_COLUMNS: &str = "alarm_id, target_id, time_ns, kind, from_level, to_level, value, \
     message, unit, acknowledged_by, acknowledged_ns, ack_note";

impl Store {
    fn alarm_of_row(&self, row: AlarmRow) -> StoreResult<StoredAlarm> {
        use crate::alarms::{AlarmKind, Level, ValueUnit};
        let (id, tid, time_ns, kind, from, to, value, message, unit, by, at_ns, note) = row;
        let malformed = || super::StoreError::Malformed(format!("alarm {id} of kind `{kind}`"));
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
            target: self
                .target_ids
                .iter()
                .position(|t| *t == tid)
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

    /// One alarm transition by id.
    pub async fn alarm(&self, id: i64) -> StoreResult<Option<StoredAlarm>> {
        let row: Option<AlarmRow> = sqlx::query_as(&format!(
            "select {ALARM_COLUMNS} from alarms where alarm_id = ?"
        ))
        .bind(id)
        .fetch_optional(&self.pool)
        .await?;
        row.map(|r| self.alarm_of_row(r)).transpose()
    }
}

impl Store {
    /// Alarm transitions in `[from_ns, to_ns]`, of one target or all, at most `limit`: the
    /// oldest first, or with `newest_first` the newest (so a limit keeps the latest ones).
    pub async fn alarms(
        &self,
        target: Option<usize>,
        from_ns: i64,
        to_ns: i64,
        limit: i64,
        newest_first: bool,
    ) -> StoreResult<Vec<StoredAlarm>> {
        let order = if newest_first {
            "time_ns desc, target_id desc, kind desc"
        } else {
            "time_ns, target_id, kind"
        };
        let rows: Vec<AlarmRow> = sqlx::query_as(&format!(
            "select {ALARM_COLUMNS} from alarms \
             where (? is null or target_id = ?) and time_ns >= ? and time_ns <= ? \
             order by {order} limit ?"
        ))
        .bind(target.map(|t| self.target_ids[t]))
        .bind(target.map(|t| self.target_ids[t]))
        .bind(from_ns)
        .bind(to_ns)
        .bind(limit)
        .fetch_all(&self.pool)
        .await?;
        rows.into_iter().map(|r| self.alarm_of_row(r)).collect()
    }

    /// The level each alarm kind of a target was last left at (`none` when never raised).
    pub async fn alarm_levels(&self, target: usize) -> StoreResult<[crate::alarms::Level; 3]> {
        use crate::alarms::{AlarmKind, Level};
        let mut out = [Level::None; 3];
        for (i, kind) in [AlarmKind::Deformation, AlarmKind::Rate, AlarmKind::Stale]
            .iter()
            .enumerate()
        {
            let row: Option<(String,)> = sqlx::query_as(
                "select to_level from alarms where target_id = ? and kind = ? order by time_ns desc limit 1",
            )
            .bind(self.target_ids[target])
            .bind(kind.name())
            .fetch_optional(&self.pool)
            .await?;
            if let Some((level,)) = row {
                out[i] = Level::parse(&level).unwrap_or(Level::None);
            }
        }
        Ok(out)
    }
}
