//! The SQLite write connection and the statements of one transaction.
//!
//! Transactions are plain `BEGIN` / `COMMIT` statements, not the driver's nested
//! transaction objects: SQLite rolls a transaction back by itself when a commit fails on a
//! full disk or an I/O error, and the driver's bookkeeping does not follow, so later "commits"
//! would only release savepoints of a transaction that never commits. Instead, any transaction
//! that did not commit (a failed statement, a failed commit, a cancelled task) leaves the
//! connection marked unclean, and the next [`Writer::begin`] replaces it with a fresh one:
//! whatever happened, the writer starts from a known state. When it begins and after it
//! commits, the writer checks that the configured file is still the one open (device and
//! inode), so a deleted or replaced file is never written to in silence.

use super::super::outbox::{KeepUnsent, Tier};
use super::super::rows::{ResultColumns, RollupKey, RollupRow, SampleColumns};
use super::super::schema::{RESULTS, SAMPLES};
use super::super::{BudgetCut, StoreResult};
use super::{FileIdentity, check_identity};
use sqlx::{ConnectOptions, Connection, QueryBuilder, Sqlite, SqliteConnection};
use std::path::{Path, PathBuf};

/// Rows per multi-row insert: a sample binds 19 parameters and a result 30 (half as many rows
/// a statement), under SQLite's limit of 32,766. Fewer, larger statements cost the writer
/// less (BENCHMARKS.md).
const ROWS_PER_STATEMENT: usize = 1000;

/// The one connection that writes.
#[derive(Debug)]
pub(in crate::store) struct Writer {
    /// `None` after a failure until the next [`Writer::begin`] reconnects.
    conn: Option<SqliteConnection>,
    /// False from `BEGIN` until a successful `COMMIT`: the connection's state is then unknown.
    clean: bool,
    path: PathBuf,
    identity: FileIdentity,
}

/// One write transaction. Dropped without [`Tx::commit`], it is rolled back (the next
/// transaction starts on a fresh connection).
pub(in crate::store) struct Tx<'c> {
    pub(in crate::store) conn: &'c mut SqliteConnection,
    clean: &'c mut bool,
    path: &'c Path,
    identity: FileIdentity,
    /// This transaction's commit sequence number: every row it writes carries it
    /// (`commit_seq`), the outbox of a fleet's site.
    seq: i64,
}

impl Writer {
    pub(super) fn new(conn: SqliteConnection, path: &Path, identity: FileIdentity) -> Self {
        Self {
            conn: Some(conn),
            clean: true,
            path: path.to_owned(),
            identity,
        }
    }

    /// Starts a transaction (`BEGIN`), on a fresh connection when the last one did
    /// not commit. Fails when the configured file is no longer the one opened at start.
    pub(in crate::store) async fn begin(&mut self, now_ns: i64) -> StoreResult<Tx<'_>> {
        check_identity(&self.path, self.identity)?;
        self.ready().await?;
        self.clean = false;
        let Some(conn) = self.conn.as_mut() else {
            unreachable!("connected above")
        };
        sqlx::query("begin").execute(&mut *conn).await?;
        // The next number: one past the last committed (a rolled-back transaction's number is
        // used again, as nothing carries it).
        let (seq,): (i64,) =
            sqlx::query_as("insert into commits (created_ns) values (?) returning seq")
                .bind(now_ns)
                .fetch_one(&mut *conn)
                .await?;
        Ok(Tx {
            conn,
            clean: &mut self.clean,
            path: &self.path,
            identity: self.identity,
            seq,
        })
    }

    /// The connection, outside any transaction: a fresh one when the last transaction did
    /// not commit. A statement that fails on it leaves it to be replaced the same way.
    pub(in crate::store) async fn ready(&mut self) -> StoreResult<&mut SqliteConnection> {
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
        Ok(conn)
    }

    /// Marks the connection's state unknown after a statement outside a transaction failed:
    /// the next use replaces it.
    pub(in crate::store) fn suspect(&mut self) {
        self.clean = false;
    }

    /// Checkpoints the WAL into the database file (so that the file alone is complete) and
    /// closes the connection.
    pub(in crate::store) async fn close(self) -> StoreResult<()> {
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

impl Tx<'_> {
    /// The commit number every row this transaction writes carries (`commit_seq`).
    pub(in crate::store) fn outbox_seq(&self) -> Option<i64> {
        Some(self.seq)
    }

    /// Commits: on disk, in the configured file, when this returns `Ok`.
    pub(in crate::store) async fn commit(self) -> StoreResult<()> {
        sqlx::query("commit").execute(&mut *self.conn).await?;
        *self.clean = true;
        check_identity(self.path, self.identity)
    }

    /// Inserts samples, many rows a statement.
    pub(in crate::store) async fn insert_samples(
        &mut self,
        samples: &[SampleColumns],
    ) -> StoreResult<()> {
        for chunk in samples.chunks(ROWS_PER_STATEMENT) {
            let mut qb: QueryBuilder<Sqlite> = QueryBuilder::new(format!(
                "insert into samples ({}, commit_seq) ",
                SAMPLES.list()
            ));
            qb.push_values(chunk, |mut b, s| {
                b.push_bind(s.link_id).push_bind(s.time_ns);
                for v in s.pose {
                    b.push_bind(v);
                }
                b.push_bind(s.uncertainty_kind)
                    .push_bind(s.uncertainty.as_deref())
                    .push_bind(s.reprojection_rms_px)
                    .push_bind(s.points)
                    .push_bind(s.disposition)
                    .push_bind(s.outlier)
                    .push_bind(s.nis)
                    .push_bind(s.received_ns)
                    .push_bind(self.seq);
            });
            qb.build().execute(&mut *self.conn).await?;
        }
        Ok(())
    }

    /// Inserts results; one at an existing key replaces it.
    pub(in crate::store) async fn upsert_results(
        &mut self,
        results: &[ResultColumns],
    ) -> StoreResult<()> {
        for chunk in results.chunks(ROWS_PER_STATEMENT / 2) {
            let mut qb: QueryBuilder<Sqlite> = QueryBuilder::new(format!(
                "insert or replace into results ({}, commit_seq) ",
                RESULTS.list()
            ));
            qb.push_values(chunk, |mut b, r| {
                b.push_bind(r.target_id)
                    .push_bind(r.source)
                    .push_bind(r.time_ns);
                for v in r.pose {
                    b.push_bind(v);
                }
                b.push_bind(r.cov.as_slice());
                for v in r.sigmas {
                    b.push_bind(v);
                }
                b.push_bind(r.status).push_bind(r.age_s).push_bind(r.chi2);
                b.push_bind(r.deformation.map(|(v, _)| v));
                for i in 0..6 {
                    b.push_bind(r.deformation.map(|(_, d)| d[i]));
                }
                b.push_bind(r.cov_systematic.as_slice());
                b.push_bind(r.calibration_stamp);
                b.push_bind(self.seq);
            });
            qb.build().execute(&mut *self.conn).await?;
        }
        Ok(())
    }

    /// The stored rollup rows at these keys.
    pub(in crate::store) async fn rollup_rows(
        &mut self,
        keys: &[RollupKey],
    ) -> StoreResult<Vec<RollupRow>> {
        let mut out = Vec::new();
        // Row-value IN: 4 parameters a key, well under SQLite's limit per statement.
        for chunk in keys.chunks(2000) {
            let mut qb: QueryBuilder<Sqlite> = QueryBuilder::new(
                "select target_id, source, width_s, bucket_ns, n, n_def, stats from rollups \
                 where (target_id, source, width_s, bucket_ns) in (values ",
            );
            let mut sep = qb.separated(", ");
            for k in chunk {
                sep.push("(")
                    .push_bind_unseparated(k.target_id)
                    .push_unseparated(", ")
                    .push_bind_unseparated(k.source)
                    .push_unseparated(", ")
                    .push_bind_unseparated(k.width_s)
                    .push_unseparated(", ")
                    .push_bind_unseparated(k.bucket_ns)
                    .push_unseparated(")");
            }
            qb.push(")");
            out.extend(
                qb.build_query_as::<RollupRow>()
                    .fetch_all(&mut *self.conn)
                    .await?,
            );
        }
        Ok(out)
    }

    /// Writes rollup rows, replacing those at the same keys.
    pub(in crate::store) async fn upsert_rollups(&mut self, rows: &[RollupRow]) -> StoreResult<()> {
        for chunk in rows.chunks(ROWS_PER_STATEMENT) {
            let mut qb: QueryBuilder<Sqlite> = QueryBuilder::new(
                "insert or replace into rollups (target_id, source, width_s, bucket_ns, n, n_def, stats, commit_seq) ",
            );
            qb.push_values(chunk, |mut b, r| {
                b.push_bind(r.target_id)
                    .push_bind(r.source)
                    .push_bind(r.width_s)
                    .push_bind(r.bucket_ns)
                    .push_bind(r.n)
                    .push_bind(r.n_def)
                    .push_bind(r.stats.as_slice())
                    .push_bind(self.seq);
            });
            qb.build().execute(&mut *self.conn).await?;
        }
        Ok(())
    }

    /// Deletes samples and results older than the cutoffs, but none that the centre has not
    /// acknowledged (`keep`); old commit numbers go with them.
    pub(in crate::store) async fn prune(
        &mut self,
        samples_before_ns: i64,
        results_before_ns: i64,
        keep: KeepUnsent,
    ) -> StoreResult<(u64, u64)> {
        let unsent = |acked: Option<i64>| acked.unwrap_or(i64::MAX);
        let samples = sqlx::query("delete from samples where time_ns < ? and commit_seq <= ?")
            .bind(samples_before_ns)
            .bind(unsent(keep.raw))
            .execute(&mut *self.conn)
            .await?
            .rows_affected();
        let results = sqlx::query(
            "delete from results where time_ns < ? \
             and commit_seq <= case source when 0 then ? else ? end",
        )
        .bind(results_before_ns)
        .bind(unsent(keep.raw))
        .bind(unsent(keep.results))
        .execute(&mut *self.conn)
        .await?
        .rows_affected();
        // The commits table only dates commits: those older than both cutoffs go (never the
        // newest, which numbers the next).
        sqlx::query("delete from commits where created_ns < ? and seq < ?")
            .bind(samples_before_ns.min(results_before_ns))
            .bind(self.seq)
            .execute(&mut *self.conn)
            .await?;
        Ok((samples, results))
    }

    /// Bytes of the file in use (its pages less the free ones), as this transaction sees it.
    async fn used_bytes(&mut self) -> StoreResult<u64> {
        let (pages,): (i64,) = sqlx::query_as("pragma page_count")
            .fetch_one(&mut *self.conn)
            .await?;
        let (free,): (i64,) = sqlx::query_as("pragma freelist_count")
            .fetch_one(&mut *self.conn)
            .await?;
        let (size,): (i64,) = sqlx::query_as("pragma page_size")
            .fetch_one(&mut *self.conn)
            .await?;
        Ok(u64::try_from((pages - free) * size).unwrap_or(0))
    }

    /// Brings the file's bytes in use under 90 % of `budget_bytes` when they are over it: an
    /// hour at a time, the oldest samples and raw results go, then (when no raw row is left)
    /// the oldest filtered results; rollups, alarms, references, calibrations and resets
    /// stay. `keep` says what the centre has not acknowledged, to count what went unsent.
    pub(in crate::store) async fn shrink_to_budget(
        &mut self,
        budget_bytes: u64,
        keep: KeepUnsent,
        link_ids: &[i64],
        target_ids: &[i64],
    ) -> StoreResult<BudgetCut> {
        const HOUR_NS: i64 = 3_600_000_000_000;
        let used = self.used_bytes().await?;
        let mut cut = BudgetCut {
            used_bytes_before: used,
            used_bytes_after: used,
            ..BudgetCut::default()
        };
        if used <= budget_bytes {
            return Ok(cut);
        }
        let goal = budget_bytes / 10 * 9;
        let unsent = |acked: Option<i64>| acked.unwrap_or(i64::MAX);
        // Raw rows first (samples and raw results, one clock), then filtered results.
        for filtered in [false, true] {
            loop {
                let mut oldest: Option<i64> = None;
                let mut consider = |t: Option<i64>| {
                    oldest = match (oldest, t) {
                        (Some(a), Some(b)) => Some(a.min(b)),
                        (a, b) => a.or(b),
                    };
                };
                if !filtered {
                    for id in link_ids {
                        let (t,): (Option<i64>,) =
                            sqlx::query_as("select min(time_ns) from samples where link_id = ?")
                                .bind(id)
                                .fetch_one(&mut *self.conn)
                                .await?;
                        consider(t);
                    }
                }
                for id in target_ids {
                    let (t,): (Option<i64>,) = sqlx::query_as(
                        "select min(time_ns) from results where target_id = ? and source = ?",
                    )
                    .bind(id)
                    .bind(i64::from(filtered))
                    .fetch_one(&mut *self.conn)
                    .await?;
                    consider(t);
                }
                let Some(oldest) = oldest else { break };
                let before_ns = oldest.saturating_add(HOUR_NS);
                if !filtered {
                    for id in link_ids {
                        let (n,): (i64,) = sqlx::query_as(
                            "select count(*) from samples where link_id = ? and time_ns < ? \
                             and commit_seq > ?",
                        )
                        .bind(id)
                        .bind(before_ns)
                        .bind(unsent(keep.raw))
                        .fetch_one(&mut *self.conn)
                        .await?;
                        cut.unsent += u64::try_from(n).unwrap_or(0);
                        cut.samples +=
                            sqlx::query("delete from samples where link_id = ? and time_ns < ?")
                                .bind(id)
                                .bind(before_ns)
                                .execute(&mut *self.conn)
                                .await?
                                .rows_affected();
                    }
                }
                let acked = if filtered { keep.results } else { keep.raw };
                for id in target_ids {
                    let (n,): (i64,) = sqlx::query_as(
                        "select count(*) from results where target_id = ? and source = ? \
                         and time_ns < ? and commit_seq > ?",
                    )
                    .bind(id)
                    .bind(i64::from(filtered))
                    .bind(before_ns)
                    .bind(unsent(acked))
                    .fetch_one(&mut *self.conn)
                    .await?;
                    cut.unsent += u64::try_from(n).unwrap_or(0);
                    let gone = sqlx::query(
                        "delete from results where target_id = ? and source = ? and time_ns < ?",
                    )
                    .bind(id)
                    .bind(i64::from(filtered))
                    .bind(before_ns)
                    .execute(&mut *self.conn)
                    .await?
                    .rows_affected();
                    if filtered {
                        cut.results += gone;
                    } else {
                        cut.raw_results += gone;
                    }
                }
                if filtered {
                    cut.results_before_ns = Some(before_ns);
                } else {
                    cut.raw_before_ns = Some(before_ns);
                }
                cut.used_bytes_after = self.used_bytes().await?;
                if cut.used_bytes_after <= goal {
                    return Ok(cut);
                }
            }
        }
        Ok(cut)
    }

    /// Records that the centre acknowledged `tier` up to the commit `seq`.
    pub(in crate::store) async fn record_ack(
        &mut self,
        tier: Tier,
        seq: i64,
        now_ns: i64,
    ) -> StoreResult<()> {
        sqlx::query(
            "insert into upstream_acks (tier, acked_seq, updated_ns) values (?, ?, ?) \
             on conflict (tier) do update set acked_seq = max(acked_seq, excluded.acked_seq), \
             updated_ns = excluded.updated_ns",
        )
        .bind(tier.name())
        .bind(seq)
        .bind(now_ns)
        .execute(&mut *self.conn)
        .await?;
        Ok(())
    }

    /// Per tier, the last commit the centre acknowledged.
    pub(in crate::store) async fn upstream_acks(&mut self) -> StoreResult<Vec<(Tier, i64)>> {
        let rows: Vec<(String, i64)> = sqlx::query_as("select tier, acked_seq from upstream_acks")
            .fetch_all(&mut *self.conn)
            .await?;
        Ok(rows
            .into_iter()
            .filter_map(|(t, s)| Some((Tier::parse(&t)?, s)))
            .collect())
    }
}
