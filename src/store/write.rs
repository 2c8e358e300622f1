//! The write connection and the statements of one transaction.

//!
//! Transactions are plain `BEGIN` / `COMMIT` statements, not the driver's nested
//! transaction objects: SQLite rolls a transaction back by itself when a commit fails on a
//! full disk or an I/O error, and the driver's bookkeeping does not follow, so later "commits"
//! would only release savepoints of a transaction that never commits. Instead, any transaction
//! that did not commit (a failed statement, a failed commit, a cancelled task) leaves the
//! connection marked unclean, and the next [`WriteConn::begin`] replaces it with a fresh one:
//! whatever happened, the writer starts from a known state. When it begins and after it
//! commits, the writer checks that the configured file is still the one open (device and
//! inode), so a deleted or replaced file is never written to in silence.

use super::codec::{encode_mat6, pose_columns};
use super::{FileIdentity, SampleValues, StoreError, StoreResult, WriterHealth, check_identity};
use crate::chain::LinkId;
use crate::deformation::SmallMotion;
use crate::geometry::{PoseCov, ReportedSigmas};
use sqlx::{ConnectOptions, Connection, QueryBuilder, Sqlite, SqliteConnection};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// A stored rollup row: key, counts, statistics blob.
type RollupRow = (i64, i64, i64, i64, i64, i64, Vec<u8>);

/// Rows per multi-row insert: well under SQLite's limit on bound parameters.
const ROWS_PER_STATEMENT: usize = 400;

/// A raw sample to store.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NewSample {
    /// The link.
    pub link: LinkId,
    /// Measurement time (ns).
    pub time_ns: i64,
    /// Its values as given.
    pub values: SampleValues,
    /// What the filter did with it (`fused`, `outlier`, ...).
    pub disposition: crate::filter::DispositionKind,
    /// True when flagged as an outlier.
    pub outlier: bool,
    /// Normalised innovation squared, where the filter computed one.
    pub nis: Option<f64>,
    /// When the service received it (ns, wall clock).
    pub received_ns: i64,
}

/// A target result to store.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NewResult {
    /// Target index in the installation.
    pub target: usize,
    /// False for a raw result, true for a filtered one.
    pub filtered: bool,
    /// Its time (ns).
    pub time_ns: i64,
    /// `target_from_base` with covariance.
    pub estimate: PoseCov,
    /// Its status.
    pub status: crate::bank::TargetStatus,
    /// Age of the newest sample behind it (s).
    pub age_s: f64,
    /// Chi-square of redundant paths, where there were several.
    pub chi2: Option<f64>,
    /// The reference version and the deformation against it.
    pub deformation: Option<(i64, SmallMotion)>,
}

/// The one connection that writes.
#[derive(Debug)]
pub struct WriteConn {
    /// `None` after a failure until the next [`WriteConn::begin`] reconnects.
    conn: Option<SqliteConnection>,
    /// False from `BEGIN` until a successful `COMMIT`: the connection's state is then unknown.
    clean: bool,
    path: PathBuf,
    identity: FileIdentity,
    health: Arc<WriterHealth>,
    link_ids: Vec<i64>,
    target_ids: Vec<i64>,
}

/// One write transaction. Dropped without [`WriteTx::commit`], it is rolled back (the next
/// transaction starts on a fresh connection).
pub struct WriteTx<'c> {
    conn: &'c mut SqliteConnection,
    clean: &'c mut bool,
    path: &'c Path,
    identity: FileIdentity,
    link_ids: &'c [i64],
    target_ids: &'c [i64],
}

/// Refuses a value that is not finite before it reaches a row.
fn finite(what: &str, values: &[f64]) -> StoreResult<()> {
    if values.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(StoreError::NonFinite {
            what: what.to_owned(),
        })
    }
}

impl WriteConn {
    pub(super) fn new(
        conn: SqliteConnection,
        path: &Path,
        identity: FileIdentity,
        health: Arc<WriterHealth>,
        link_ids: Vec<i64>,
        target_ids: Vec<i64>,
    ) -> Self {
        Self {
            conn: Some(conn),
            clean: true,
            path: path.to_owned(),
            identity,
            health,
            link_ids,
            target_ids,
        }
    }

    /// What the health check sees of this writer; the service records each commit's outcome.
    pub fn health(&self) -> &WriterHealth {
        &self.health
    }

    /// Starts a transaction (`BEGIN`), on a fresh connection when the last one did
    /// not commit. Fails when the configured file is no longer the one opened at start.
    pub async fn begin(&mut self) -> StoreResult<WriteTx<'_>> {
        check_identity(&self.path, self.identity)?;
        if !self.clean || self.conn.is_none() {
            if let Some(old) = self.conn.take() {
                // Closing rolls back whatever transaction the connection still had.
                if let Err(e) = old.close().await {
                    tracing::warn!(error = %e, "closing the failed write connection");
                }
            }
            let fresh = super::options(&self.path)
                .create_if_missing(false)
                .connect()
                .await?;
            self.conn = Some(fresh);
            self.clean = true;
            tracing::info!("the writer reconnected to the database after a failed transaction");
        }
        let Some(conn) = self.conn.as_mut() else {
            unreachable!("connected above")
        };
        self.clean = false;
        sqlx::query("begin").execute(&mut *conn).await?;
        Ok(WriteTx {
            conn,
            clean: &mut self.clean,
            path: &self.path,
            identity: self.identity,
            link_ids: &self.link_ids,
            target_ids: &self.target_ids,
        })
    }

    /// Checkpoints the WAL into the database file (so that the file alone is complete) and
    /// closes the connection.
    pub async fn close(self) -> StoreResult<()> {
        let Some(mut conn) = self.conn else {
            return Ok(());
        };
        if !self.clean {
            let _ = sqlx::query("rollback").execute(&mut conn).await;
        }
        let (busy, _, _): (i64, i64, i64) = sqlx::query_as("pragma wal_checkpoint(truncate)")
            .fetch_one(&mut conn)
            .await?;
        if busy != 0 {
            tracing::warn!(
                "a reader kept the WAL checkpoint from completing; the -wal file is still needed"
            );
        }
        conn.close().await?;
        Ok(())
    }
}

impl WriteTx<'_> {
    /// Commits: everything written in this transaction is on disk, in the configured file,
    /// when this returns `Ok`. On an error nothing of it is committed (or, when the file was
    /// replaced meanwhile, it went to a file that is no longer the configured one): the caller
    /// must not acknowledge it.
    pub async fn commit(self) -> StoreResult<()> {
        sqlx::query("commit").execute(&mut *self.conn).await?;
        *self.clean = true;
        check_identity(self.path, self.identity)
    }

    /// The stored samples of a link with times in `[from_ns, to_ns]` (this transaction's
    /// writes included), with their values.
    pub async fn existing_samples(
        &mut self,
        link: LinkId,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<Vec<(i64, SampleValues)>> {
        let rows: Vec<super::read::SampleRow> = sqlx::query_as(super::read::SAMPLE_SELECT_BY_RANGE)
            .bind(self.link_ids[link.0])
            .bind(from_ns)
            .bind(to_ns)
            .bind(i64::MAX)
            .fetch_all(&mut *self.conn)
            .await?;
        rows.into_iter()
            .map(|r| Ok((r.time_ns, r.values()?)))
            .collect()
    }

    /// Inserts samples (keys must be new).
    pub async fn insert_samples(&mut self, samples: &[NewSample]) -> StoreResult<()> {
        for s in samples {
            finite("sample pose", &pose_columns(&s.values.pose))?;
            finite(
                "sample quality",
                &[s.values.quality.reprojection_rms_px.unwrap_or(0.0)],
            )?;
            if let Some(nis) = s.nis {
                finite("sample NIS", &[nis])?;
            }
        }
        for chunk in samples.chunks(ROWS_PER_STATEMENT) {
            let mut qb: QueryBuilder<Sqlite> = QueryBuilder::new(
                "insert into samples (link_id, time_ns, tx_mm, ty_mm, tz_mm, qw, qx, qy, qz, \
                 uncertainty_kind, uncertainty, reprojection_rms_px, points, disposition, outlier, nis, received_ns) ",
            );
            qb.push_values(chunk, |mut b, s| {
                let p = pose_columns(&s.values.pose);
                let (kind, blob) = s.values.uncertainty.columns();
                b.push_bind(self.link_ids[s.link.0]).push_bind(s.time_ns);
                for v in p {
                    b.push_bind(v);
                }
                b.push_bind(kind)
                    .push_bind(blob)
                    .push_bind(s.values.quality.reprojection_rms_px)
                    .push_bind(s.values.quality.points.map(i64::from))
                    .push_bind(s.disposition.name())
                    .push_bind(s.outlier)
                    .push_bind(s.nis)
                    .push_bind(s.received_ns);
            });
            qb.build().execute(&mut *self.conn).await?;
        }
        Ok(())
    }

    /// Inserts target results and adds them to the rollups, in this transaction; a result at an
    /// existing (target, source, time) replaces it (a raw group completed again by a late
    /// sample, or a filtered result recomputed).
    pub async fn insert_results(&mut self, results: &[NewResult]) -> StoreResult<()> {
        // Both the rows and the rollups carry the sigmas: derive them once.
        let sigmas: Vec<ReportedSigmas> = results
            .iter()
            .map(|r| r.estimate.reported_sigmas())
            .collect();
        for (r, s) in results.iter().zip(&sigmas) {
            finite("result pose", &pose_columns(&r.estimate.pose))?;
            finite("result covariance", r.estimate.cov.as_slice())?;
            finite("result sigma", &s.rotation_arcsec)?;
            finite("result sigma", &s.translation_mm)?;
            finite("result age", &[r.age_s])?;
            if let Some((_, d)) = &r.deformation {
                finite("result deformation", &d.rotation_arcsec)?;
                finite("result deformation", &d.translation_mm)?;
            }
        }
        for (chunk, chunk_sigmas) in results
            .chunks(ROWS_PER_STATEMENT / 2)
            .zip(sigmas.chunks(ROWS_PER_STATEMENT / 2))
        {
            let mut qb: QueryBuilder<Sqlite> = QueryBuilder::new(
                "insert or replace into results (target_id, source, time_ns, tx_mm, ty_mm, tz_mm, qw, qx, qy, qz, cov, \
                 sigma_rx_arcsec, sigma_ry_arcsec, sigma_rz_arcsec, sigma_tx_mm, sigma_ty_mm, sigma_tz_mm, \
                 status, age_s, chi2, reference_version, def_rx_arcsec, def_ry_arcsec, def_rz_arcsec, \
                 def_tx_mm, def_ty_mm, def_tz_mm) ",
            );
            qb.push_values(chunk.iter().zip(chunk_sigmas), |mut b, (r, s)| {
                b.push_bind(self.target_ids[r.target])
                    .push_bind(i64::from(r.filtered))
                    .push_bind(r.time_ns);
                for v in pose_columns(&r.estimate.pose) {
                    b.push_bind(v);
                }
                b.push_bind(encode_mat6(&r.estimate.cov));
                for v in s.rotation_arcsec.iter().chain(&s.translation_mm) {
                    b.push_bind(*v);
                }
                b.push_bind(r.status.name())
                    .push_bind(r.age_s)
                    .push_bind(r.chi2);
                match &r.deformation {
                    Some((version, d)) => {
                        b.push_bind(Some(*version));
                        for v in d.rotation_arcsec.iter().chain(&d.translation_mm) {
                            b.push_bind(Some(*v));
                        }
                    }
                    None => {
                        b.push_bind(None::<i64>);
                        for _ in 0..6 {
                            b.push_bind(None::<f64>);
                        }
                    }
                }
            });
            qb.build().execute(&mut *self.conn).await?;
        }
        self.update_rollups(results, &sigmas).await
    }

    /// Adds new results to the rollups: the touched buckets of every level are read in one
    /// statement, merged, and written back in one.
    async fn update_rollups(
        &mut self,
        results: &[NewResult],
        sigmas: &[ReportedSigmas],
    ) -> StoreResult<()> {
        use super::rollup::{Bucket, decode_bucket, encode_stats};
        use std::collections::HashMap;
        type Key = (i64, i64, i64, i64);
        let mut fresh: Vec<(Key, Bucket)> = super::rollup::aggregate(results, sigmas)
            .into_iter()
            .map(|((target, filtered, width_s, start), b)| {
                (
                    (self.target_ids[target], i64::from(filtered), width_s, start),
                    b,
                )
            })
            .collect();
        fresh.sort_by_key(|(k, _)| *k);
        // Row-value IN: 4 parameters a key, well under SQLite's limit per statement.
        let mut existing: HashMap<Key, Bucket> = HashMap::new();
        for chunk in fresh.chunks(2000) {
            let mut qb: QueryBuilder<Sqlite> = QueryBuilder::new(
                "select target_id, source, width_s, bucket_ns, n, n_def, stats from rollups \
                 where (target_id, source, width_s, bucket_ns) in (values ",
            );
            let mut sep = qb.separated(", ");
            for ((t, s, w, b), _) in chunk {
                sep.push("(")
                    .push_bind_unseparated(*t)
                    .push_unseparated(", ")
                    .push_bind_unseparated(*s)
                    .push_unseparated(", ")
                    .push_bind_unseparated(*w)
                    .push_unseparated(", ")
                    .push_bind_unseparated(*b)
                    .push_unseparated(")");
            }
            qb.push(")");
            let rows: Vec<RollupRow> = qb.build_query_as().fetch_all(&mut *self.conn).await?;
            for (t, s, w, b, n, n_def, stats) in rows {
                existing.insert((t, s, w, b), decode_bucket(b, n, n_def, &stats)?);
            }
        }
        for (key, bucket) in &mut fresh {
            if let Some(old) = existing.get(key) {
                bucket.merge(old);
            }
        }
        for chunk in fresh.chunks(ROWS_PER_STATEMENT) {
            let mut qb: QueryBuilder<Sqlite> = QueryBuilder::new(
                "insert or replace into rollups (target_id, source, width_s, bucket_ns, n, n_def, stats) ",
            );
            qb.push_values(chunk, |mut b, ((t, s, w, start), bucket)| {
                b.push_bind(*t)
                    .push_bind(*s)
                    .push_bind(*w)
                    .push_bind(*start)
                    .push_bind(bucket.n)
                    .push_bind(bucket.n_def)
                    .push_bind(encode_stats(bucket));
            });
            qb.build().execute(&mut *self.conn).await?;
        }
        Ok(())
    }

    /// Stores an alarm transition of `target`; returns its id. A transition recomputed at the
    /// same time and of the same kind (after a rolled-back commit) replaces the values and
    /// keeps the id and any acknowledgement.
    pub async fn insert_alarm(
        &mut self,
        target: usize,
        t: &crate::alarms::Transition,
        now_ns: i64,
    ) -> StoreResult<i64> {
        finite("alarm value", &[t.value])?;
        let (id,): (i64,) = sqlx::query_as(
            "insert into alarms (target_id, time_ns, kind, from_level, to_level, value, unit, message, created_ns) \
             values (?, ?, ?, ?, ?, ?, ?, ?, ?) \
             on conflict (target_id, time_ns, kind) do update set from_level = excluded.from_level, \
             to_level = excluded.to_level, value = excluded.value, unit = excluded.unit, \
             message = excluded.message, created_ns = excluded.created_ns \
             returning alarm_id",
        )
        .bind(self.target_ids[target])
        .bind(t.time_ns)
        .bind(t.kind.name())
        .bind(t.from.name())
        .bind(t.to.name())
        .bind(t.value)
        .bind(t.unit.name())
        .bind(t.message.clone())
        .bind(now_ns)
        .fetch_one(&mut *self.conn)
        .await?;
        Ok(id)
    }

    /// An alarm's new level and acknowledgement, read inside the transaction:
    /// `(to_level, acknowledged_by, ack_note)`; `None` when there is no such alarm.
    pub async fn alarm_ack_state(
        &mut self,
        id: i64,
    ) -> StoreResult<Option<(String, Option<String>, Option<String>)>> {
        Ok(sqlx::query_as(
            "select to_level, acknowledged_by, ack_note from alarms where alarm_id = ?",
        )
        .bind(id)
        .fetch_optional(&mut *self.conn)
        .await?)
    }

    /// Records an acknowledgement of alarm `id`.
    pub async fn acknowledge_alarm(
        &mut self,
        id: i64,
        by: &str,
        note: Option<&str>,
        now_ns: i64,
    ) -> StoreResult<()> {
        sqlx::query(
            "update alarms set acknowledged_by = ?, acknowledged_ns = ?, ack_note = ? where alarm_id = ?",
        )
        .bind(by)
        .bind(now_ns)
        .bind(note)
        .bind(id)
        .execute(&mut *self.conn)
        .await?;
        Ok(())
    }

    /// Deletes samples older than `samples_before_ns` and results older than
    /// `results_before_ns`; rollups stay. Returns how many `(samples, results)` went.
    pub async fn prune(
        &mut self,
        samples_before_ns: i64,
        results_before_ns: i64,
    ) -> StoreResult<(u64, u64)> {
        let samples = sqlx::query("delete from samples where time_ns < ?")
            .bind(samples_before_ns)
            .execute(&mut *self.conn)
            .await?
            .rows_affected();
        let results = sqlx::query("delete from results where time_ns < ?")
            .bind(results_before_ns)
            .execute(&mut *self.conn)
            .await?
            .rows_affected();
        Ok((samples, results))
    }

    /// The filtered results of a target in `[from_ns, to_ns]`, oldest first.
    pub async fn filtered_poses(
        &mut self,
        target: usize,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<Vec<PoseCov>> {
        let rows: Vec<super::read::ResultRow> = sqlx::query_as(super::read::RESULT_SELECT_BY_RANGE)
            .bind(self.target_ids[target])
            .bind(1i64)
            .bind(from_ns)
            .bind(to_ns)
            .bind(i64::MAX)
            .fetch_all(&mut *self.conn)
            .await?;
        rows.into_iter()
            .map(|r| r.into_result().map(|r| r.estimate))
            .collect()
    }

    /// Stores a new reference version of a target; returns its version.
    pub async fn insert_reference(
        &mut self,
        target: usize,
        reference: &crate::deformation::Reference,
        now_ns: i64,
    ) -> StoreResult<i64> {
        let target_id = self.target_ids[target];
        let (max,): (Option<i64>,) =
            sqlx::query_as("select max(version) from target_references where target_id = ?")
                .bind(target_id)
                .fetch_one(&mut *self.conn)
                .await?;
        let version = max.unwrap_or(0) + 1;
        let p = pose_columns(&reference.g0_from_b.pose);
        finite("reference pose", &p)?;
        finite("reference covariance", reference.g0_from_b.cov.as_slice())?;
        let (origin, from, to, count) = match reference.origin {
            crate::deformation::ReferenceOrigin::Explicit => ("explicit", None, None, None),
            crate::deformation::ReferenceOrigin::Window {
                from_ns,
                to_ns,
                count,
            } => ("window", Some(from_ns), Some(to_ns), Some(count as i64)),
        };
        sqlx::query(
            "insert into target_references (target_id, version, tx_mm, ty_mm, tz_mm, qw, qx, qy, qz, cov, \
             origin, window_from_ns, window_to_ns, window_count, created_ns) \
             values (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        )
        .bind(target_id)
        .bind(version)
        .bind(p[0])
        .bind(p[1])
        .bind(p[2])
        .bind(p[3])
        .bind(p[4])
        .bind(p[5])
        .bind(p[6])
        .bind(encode_mat6(&reference.g0_from_b.cov))
        .bind(origin)
        .bind(from)
        .bind(to)
        .bind(count)
        .bind(now_ns)
        .execute(&mut *self.conn)
        .await?;
        Ok(version)
    }

    /// Stores a new calibration version of a link; returns its version.
    pub async fn insert_calibration(
        &mut self,
        link: LinkId,
        valid_from_ns: i64,
        parent_from_child: &PoseCov,
        now_ns: i64,
    ) -> StoreResult<i64> {
        let link_id = self.link_ids[link.0];
        let (max,): (Option<i64>,) =
            sqlx::query_as("select max(version) from calibrations where link_id = ?")
                .bind(link_id)
                .fetch_one(&mut *self.conn)
                .await?;
        let version = max.unwrap_or(0) + 1;
        let p = pose_columns(&parent_from_child.pose);
        finite("calibration pose", &p)?;
        finite("calibration covariance", parent_from_child.cov.as_slice())?;
        sqlx::query(
            "insert into calibrations (link_id, version, valid_from_ns, tx_mm, ty_mm, tz_mm, qw, qx, qy, qz, cov, created_ns) \
             values (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
        )
        .bind(link_id)
        .bind(version)
        .bind(valid_from_ns)
        .bind(p[0])
        .bind(p[1])
        .bind(p[2])
        .bind(p[3])
        .bind(p[4])
        .bind(p[5])
        .bind(p[6])
        .bind(encode_mat6(&parent_from_child.cov))
        .bind(now_ns)
        .execute(&mut *self.conn)
        .await?;
        Ok(version)
    }

    /// Records a manual restart of a link's filter.
    pub async fn insert_link_reset(
        &mut self,
        link: LinkId,
        by: Option<&str>,
        note: Option<&str>,
        now_ns: i64,
    ) -> StoreResult<()> {
        sqlx::query(
            "insert or replace into link_resets (link_id, created_ns, by_name, note) values (?, ?, ?, ?)",
        )
        .bind(self.link_ids[link.0])
        .bind(now_ns)
        .bind(by)
        .bind(note)
        .execute(&mut *self.conn)
        .await?;
        Ok(())
    }

    /// Saves the filter bank's state.
    pub async fn save_filter_state(
        &mut self,
        digest: &str,
        state_json: &str,
        now_ns: i64,
    ) -> StoreResult<()> {
        sqlx::query(
            "insert into filter_state (id, installation_digest, state, updated_ns) values (1, ?, ?, ?) \
             on conflict (id) do update set installation_digest = excluded.installation_digest, \
             state = excluded.state, updated_ns = excluded.updated_ns",
        )
        .bind(digest)
        .bind(state_json)
        .bind(now_ns)
        .execute(&mut *self.conn)
        .await?;
        Ok(())
    }
}
