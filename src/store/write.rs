//! The write side of the store: [`WriteConn`], the one writer the service's pipeline owns, and
//! its transactions ([`WriteTx`]), which check every value before it reaches a row and commit
//! only once durable; with the rows they take ([`NewSample`], [`NewResult`]).

use super::*;

/// What a disk budget made the retention remove beyond its ages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct BudgetCut {
    /// Bytes of the file in use before.
    pub used_bytes_before: u64,
    /// And after.
    pub used_bytes_after: u64,
    /// Samples removed.
    pub samples: u64,
    /// Raw results removed.
    pub raw_results: u64,
    /// Filtered results removed.
    pub results: u64,
    /// Of those, rows the centre had not acknowledged (on a site whose tier is uploaded).
    pub unsent: u64,
    /// Samples and raw results before this time went (ns), when any did.
    pub raw_before_ns: Option<i64>,
    /// Filtered results before this time went (ns), when any did.
    pub results_before_ns: Option<i64>,
}

impl BudgetCut {
    /// Rows removed.
    pub fn rows(&self) -> u64 {
        self.samples + self.raw_results + self.results
    }
}

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
    pub target: TargetId,
    /// Raw or filtered.
    pub source: ResultSource,
    /// Its time (ns).
    pub time_ns: i64,
    /// `target_from_base` with its whole covariance, its systematic part and its calibrations.
    pub estimate: MeasuredPose,
    /// Its status.
    pub status: crate::bank::TargetStatus,
    /// Age of the newest sample behind it (s).
    pub age_s: f64,
    /// Chi-square of redundant paths, where there were several.
    pub chi2: Option<f64>,
    /// The reference version and the deformation against it.
    pub deformation: Option<(i64, SmallMotion)>,
}

impl NewResult {
    /// What of the result is not a finite number, if anything: such a result cannot be
    /// stored (a target whose configuration gives numbers out of range).
    pub fn non_finite(&self) -> Option<&'static str> {
        let all = |v: &[f64]| v.iter().all(|x| x.is_finite());
        let (whole, systematic) = (&self.estimate.whole, &self.estimate.systematic_cov);
        if !all(&pose_columns(&whole.pose)) {
            Some("pose")
        } else if !all(whole.cov.as_slice()) || !all(systematic.as_slice()) {
            Some("covariance")
        } else if (0..6).any(|i| whole.cov[(i, i)] < 0.0) {
            // The sigmas are the diagonal's roots: finite exactly when it is finite and not
            // negative (checked here without deriving them twice on the ingest path).
            Some("sigma")
        } else if !self.age_s.is_finite() {
            Some("age")
        } else if self
            .deformation
            .as_ref()
            .is_some_and(|(_, d)| !all(&d.rotation_arcsec) || !all(&d.translation_mm))
        {
            Some("deformation")
        } else {
            None
        }
    }
}

/// The writer of a backend.
#[derive(Debug)]
pub(super) enum Writer {
    Sqlite(sqlite::Writer),
    Postgres(postgres::Writer),
}

/// A transaction of a backend.
enum Tx<'c> {
    Sqlite(sqlite::Tx<'c>),
    Postgres(postgres::Tx<'c>),
}

/// The one connection that writes.
#[derive(Debug)]
pub struct WriteConn {
    pub(super) backend: Writer,
    pub(super) health: Arc<WriterHealth>,
    pub(super) link_ids: Arc<[i64]>,
    pub(super) target_ids: Arc<[i64]>,
}

/// One write transaction. Dropped without [`WriteTx::commit`], it is rolled back (the next
/// transaction starts on a fresh connection).
pub struct WriteTx<'c> {
    tx: Tx<'c>,
    link_ids: &'c [i64],
    target_ids: &'c [i64],
}

/// Sample rows as their times and values.
pub(super) fn times_and_values(
    rows: Vec<rows::SampleRow>,
) -> StoreResult<Vec<(i64, SampleValues)>> {
    rows.into_iter()
        .map(|r| Ok((r.time_ns, r.values()?)))
        .collect()
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
    /// What the health check sees of this writer; the service records each commit's outcome.
    pub fn health(&self) -> &WriterHealth {
        &self.health
    }

    /// Starts a transaction, on a fresh connection when the last one did not commit. Fails
    /// when the database cannot be reached (or, for SQLite, the configured file is no longer
    /// the one opened at start).
    pub async fn begin(&mut self, now_ns: i64) -> StoreResult<WriteTx<'_>> {
        let tx = match &mut self.backend {
            Writer::Sqlite(w) => Tx::Sqlite(w.begin(now_ns).await?),
            Writer::Postgres(w) => Tx::Postgres(w.begin().await?),
        };
        Ok(WriteTx {
            tx,
            link_ids: &self.link_ids,
            target_ids: &self.target_ids,
        })
    }

    /// The committed samples of a link with times in `[from_ns, to_ns]`, with their values,
    /// read outside any transaction: for a writer that must know what is stored before it
    /// filters, while nothing of its own is in flight.
    pub async fn stored_samples(
        &mut self,
        link: LinkId,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<Vec<(i64, SampleValues)>> {
        let id = self.link_ids[link.0];
        let rows: StoreResult<Vec<rows::SampleRow>> = on_backend!(&mut self.backend, Writer, w => {
            let read = match w.ready().await {
                Ok(conn) => sqlx::query_as(&sql::SAMPLES_IN)
                    .bind(id)
                    .bind(from_ns)
                    .bind(to_ns)
                    .bind(i64::MAX)
                    .fetch_all(&mut *conn)
                    .await
                    .map_err(Into::into),
                Err(e) => Err(e),
            };
            if read.is_err() {
                w.suspect();
            }
            read
        });
        times_and_values(rows?)
    }

    /// Closes the connection (for SQLite after checkpointing the WAL into the file, so that
    /// the file alone is complete).
    pub async fn close(self) -> StoreResult<()> {
        on_backend!(self.backend, Writer, w => w.close().await)
    }
}

impl WriteTx<'_> {
    /// Commits: everything written in this transaction is durable when this returns `Ok`. On
    /// an error nothing of it is committed (or, for SQLite, when the file was replaced
    /// meanwhile, it went to a file that is no longer the configured one): the caller must not
    /// acknowledge it.
    pub async fn commit(self) -> StoreResult<()> {
        on_backend!(self.tx, Tx, t => t.commit().await)
    }

    /// The stored samples of a link with times in `[from_ns, to_ns]` (this transaction's
    /// writes included), with their values.
    pub async fn existing_samples(
        &mut self,
        link: LinkId,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<Vec<(i64, SampleValues)>> {
        let id = self.link_ids[link.0];
        let rows: Vec<rows::SampleRow> = query_on!(
            &mut self.tx, Tx, t => &mut *t.conn,
            &sql::SAMPLES_IN, [id, from_ns, to_ns, i64::MAX],
            fetch_all
        )?;
        times_and_values(rows)
    }

    /// Inserts samples (keys must be new), many rows a statement. `parts`: the samples in
    /// parts (a commit's requests), written as one.
    pub async fn insert_samples(&mut self, parts: &[&[NewSample]]) -> StoreResult<()> {
        let mut columns = Vec::with_capacity(parts.iter().map(|p| p.len()).sum());
        for s in parts.iter().copied().flatten() {
            let pose = pose_columns(&s.values.pose);
            finite("sample pose", &pose)?;
            finite(
                "sample quality",
                &[s.values.quality.reprojection_rms_px.unwrap_or(0.0)],
            )?;
            if let Some(nis) = s.nis {
                finite("sample NIS", &[nis])?;
            }
            let (uncertainty_kind, uncertainty) = s.values.uncertainty.columns();
            columns.push(SampleColumns {
                link_id: self.link_ids[s.link.0],
                time_ns: s.time_ns,
                pose,
                uncertainty_kind,
                uncertainty,
                reprojection_rms_px: s.values.quality.reprojection_rms_px,
                points: s.values.quality.points.map(i64::from),
                disposition: s.disposition.name(),
                outlier: s.outlier,
                nis: s.nis,
                received_ns: s.received_ns,
            });
        }
        on_backend!(&mut self.tx, Tx, t => t.insert_samples(&columns).await)
    }

    /// Inserts target results and adds them to the rollups, in this transaction; a result at an
    /// existing (target, source, time) replaces it (a raw group completed again by a late
    /// sample, or a filtered result recomputed; within one call the last one counts).
    ///
    /// `parts`: the results in parts (a commit's requests), written as one, so that the
    /// rollups are read and written once a commit. A bucket's sums then add a commit's
    /// results before the stored sum, so they equal those of one request at a time only to
    /// rounding.
    pub async fn insert_results(&mut self, parts: &[&[NewResult]]) -> StoreResult<()> {
        let results: Vec<&NewResult> = parts.iter().copied().flatten().collect();
        // Both the rows and the rollups carry the sigmas: derive them once.
        let sigmas: Vec<ReportedSigmas> = results
            .iter()
            .map(|r| r.estimate.whole.reported_sigmas())
            .collect();
        let mut columns: Vec<ResultColumns> = Vec::with_capacity(results.len());
        let mut at_key: std::collections::HashMap<(TargetId, ResultSource, i64), usize> =
            std::collections::HashMap::with_capacity(results.len());
        for (r, s) in results.iter().zip(&sigmas) {
            let pose = pose_columns(r.estimate.pose());
            finite("result pose", &pose)?;
            finite("result covariance", r.estimate.whole.cov.as_slice())?;
            finite("result covariance", r.estimate.systematic_cov.as_slice())?;
            finite("result sigma", &s.rotation_arcsec)?;
            finite("result sigma", &s.translation_mm)?;
            finite("result age", &[r.age_s])?;
            let deformation = match &r.deformation {
                Some((version, d)) => {
                    finite("result deformation", &d.rotation_arcsec)?;
                    finite("result deformation", &d.translation_mm)?;
                    let [a, b, c] = d.rotation_arcsec;
                    let [x, y, z] = d.translation_mm;
                    Some((*version, [a, b, c, x, y, z]))
                }
                None => None,
            };
            let [a, b, c] = s.rotation_arcsec;
            let [x, y, z] = s.translation_mm;
            let row = ResultColumns {
                target_id: self.target_ids[r.target.0],
                source: codec::source_column(r.source),
                time_ns: r.time_ns,
                pose,
                cov: encode_sym6(&r.estimate.whole.cov),
                sigmas: [a, b, c, x, y, z],
                status: r.status.name(),
                age_s: r.age_s,
                chi2: r.chi2,
                deformation,
                cov_systematic: encode_sym6(&r.estimate.systematic_cov),
                calibration_stamp: r.estimate.calibration.map(|c| c.0),
            };
            // One row a key: a statement may not write the same key twice on every engine.
            match at_key.entry((r.target, r.source, r.time_ns)) {
                std::collections::hash_map::Entry::Occupied(e) => columns[*e.get()] = row,
                std::collections::hash_map::Entry::Vacant(e) => {
                    e.insert(columns.len());
                    columns.push(row);
                }
            }
        }
        on_backend!(&mut self.tx, Tx, t => t.upsert_results(&columns).await)?;
        self.update_rollups(&results, &sigmas).await
    }

    /// Adds new results to the rollups: the touched buckets of every level are read in one
    /// statement, merged, and written back in one.
    async fn update_rollups(
        &mut self,
        results: &[&NewResult],
        sigmas: &[ReportedSigmas],
    ) -> StoreResult<()> {
        use rollup::{Bucket, decode_bucket, encode_stats};
        use std::collections::HashMap;
        let mut fresh: Vec<(rows::RollupKey, Bucket)> = rollup::aggregate(results, sigmas)
            .into_iter()
            .map(|((target, source, width_s, start), b)| {
                (
                    rows::RollupKey {
                        target_id: self.target_ids[target.0],
                        source: codec::source_column(source),
                        width_s,
                        bucket_ns: start,
                    },
                    b,
                )
            })
            .collect();
        fresh.sort_by_key(|(k, _)| *k);
        let keys: Vec<rows::RollupKey> = fresh.iter().map(|(k, _)| *k).collect();
        let stored = on_backend!(&mut self.tx, Tx, t => t.rollup_rows(&keys).await)?;
        let mut existing: HashMap<rows::RollupKey, Bucket> = HashMap::with_capacity(stored.len());
        for row in stored {
            existing.insert(
                row.key(),
                decode_bucket(row.bucket_ns, row.n, row.n_def, &row.stats)?,
            );
        }
        let merged: Vec<rows::RollupRow> = fresh
            .iter_mut()
            .map(|(key, bucket)| {
                if let Some(old) = existing.get(key) {
                    bucket.merge(old);
                }
                rows::RollupRow {
                    target_id: key.target_id,
                    source: key.source,
                    width_s: key.width_s,
                    bucket_ns: key.bucket_ns,
                    n: bucket.n,
                    n_def: bucket.n_def,
                    stats: encode_stats(bucket),
                }
            })
            .collect();
        on_backend!(&mut self.tx, Tx, t => t.upsert_rollups(&merged).await)
    }

    /// Stores an alarm transition of `target`; returns its id. A transition recomputed at the
    /// same time and of the same kind (after a rolled-back commit) replaces the values and
    /// keeps the id and any acknowledgement.
    pub async fn insert_alarm(
        &mut self,
        target: TargetId,
        t: &crate::alarms::Transition,
        now_ns: i64,
    ) -> StoreResult<i64> {
        finite("alarm value", &[t.value])?;
        let id = self.target_ids[target.0];
        let (alarm_id,): (i64,) = outboxed!(
            &mut self.tx,
            sql::INSERT_ALARM,
            [
                id,
                t.time_ns,
                t.kind.name(),
                t.from.name(),
                t.to.name(),
                t.value,
                t.unit.name(),
                t.message.as_str(),
                now_ns,
            ],
            fetch_one
        )?;
        Ok(alarm_id)
    }

    /// An alarm's new level and acknowledgement, read inside the transaction:
    /// `(to_level, acknowledged_by, ack_note)`; `None` when there is no such alarm.
    pub async fn alarm_ack_state(
        &mut self,
        id: i64,
    ) -> StoreResult<Option<(String, Option<String>, Option<String>)>> {
        Ok(query_on!(
            &mut self.tx, Tx, t => &mut *t.conn,
            sql::ALARM_ACK_STATE, [id],
            fetch_optional
        )?)
    }

    /// Records an acknowledgement of alarm `id`.
    pub async fn acknowledge_alarm(
        &mut self,
        id: i64,
        by: &str,
        note: Option<&str>,
        now_ns: i64,
    ) -> StoreResult<()> {
        outboxed!(
            &mut self.tx,
            sql::ACKNOWLEDGE_ALARM,
            [by, now_ns, note, id],
            execute
        )?;
        Ok(())
    }

    /// Deletes samples older than `samples_before_ns` and results older than
    /// `results_before_ns`; rollups stay. Returns how many `(samples, results)` went.
    ///
    /// On a fleet's site, `keep` holds back what the centre has not acknowledged.
    pub async fn prune(
        &mut self,
        samples_before_ns: i64,
        results_before_ns: i64,
        keep: KeepUnsent,
    ) -> StoreResult<(u64, u64)> {
        match &mut self.tx {
            Tx::Sqlite(t) => t.prune(samples_before_ns, results_before_ns, keep).await,
            Tx::Postgres(t) => t.prune(samples_before_ns, results_before_ns).await,
        }
    }

    /// Brings an SQLite file's bytes in use under 90 % of `budget_bytes` when they are over
    /// it, the oldest raw rows first, then the oldest filtered results (see [`BudgetCut`]);
    /// `keep` says what the centre has not acknowledged, to count what goes unsent. Nothing on
    /// PostgreSQL (the configuration refuses a budget there).
    pub async fn shrink_to_budget(
        &mut self,
        budget_bytes: u64,
        keep: KeepUnsent,
    ) -> StoreResult<BudgetCut> {
        match &mut self.tx {
            Tx::Sqlite(t) => {
                t.shrink_to_budget(budget_bytes, keep, self.link_ids, self.target_ids)
                    .await
            }
            Tx::Postgres(_) => Ok(BudgetCut::default()),
        }
    }

    /// Records that the centre acknowledged `tier` up to the commit `seq` (a site's outbox:
    /// SQLite only).
    pub async fn record_ack(&mut self, tier: Tier, seq: i64, now_ns: i64) -> StoreResult<()> {
        match &mut self.tx {
            Tx::Sqlite(t) => t.record_ack(tier, seq, now_ns).await,
            Tx::Postgres(_) => Err(StoreError::NotAnOutbox),
        }
    }

    /// Per tier, the last commit the centre acknowledged (none on PostgreSQL).
    pub async fn upstream_acks(&mut self) -> StoreResult<Vec<(Tier, i64)>> {
        match &mut self.tx {
            Tx::Sqlite(t) => t.upstream_acks().await,
            Tx::Postgres(_) => Ok(Vec::new()),
        }
    }

    /// The filtered results of a target in `[from_ns, to_ns]`, oldest first.
    pub async fn filtered_poses(
        &mut self,
        target: TargetId,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<Vec<StoredResult>> {
        let id = self.target_ids[target.0];
        let rows: Vec<rows::ResultRow> = query_on!(
            &mut self.tx, Tx, t => &mut *t.conn,
            &sql::RESULTS_IN, [id, 1_i64, from_ns, to_ns, i64::MAX],
            fetch_all
        )?;
        rows.into_iter().map(rows::ResultRow::into_result).collect()
    }

    /// Stores a new reference version of a target; returns its version.
    pub async fn insert_reference(
        &mut self,
        target: TargetId,
        reference: &crate::deformation::Reference,
        now_ns: i64,
    ) -> StoreResult<i64> {
        let columns = version_columns("reference", &reference.g0_from_b.whole)?;
        let origin = match reference.origin {
            crate::deformation::ReferenceOrigin::Explicit => WindowOrigin {
                origin: "explicit",
                from_ns: None,
                to_ns: None,
                count: None,
            },
            crate::deformation::ReferenceOrigin::Window {
                from_ns,
                to_ns,
                count,
            } => WindowOrigin {
                origin: "window",
                from_ns: Some(from_ns),
                to_ns: Some(to_ns),
                count: Some(count as i64),
            },
        };
        let id = self.target_ids[target.0];
        let p = columns.pose;
        let (version,): (i64,) = outboxed!(
            &mut self.tx,
            sql::INSERT_REFERENCE,
            [
                id,
                p[0],
                p[1],
                p[2],
                p[3],
                p[4],
                p[5],
                p[6],
                columns.cov.as_slice(),
                origin.origin,
                origin.from_ns,
                origin.to_ns,
                origin.count,
                now_ns,
            ],
            fetch_one
        )?;
        let g0_from_b = &reference.g0_from_b;
        finite("reference covariance", g0_from_b.systematic_cov.as_slice())?;
        let systematic = encode_mat6(&g0_from_b.systematic_cov);
        let stamp = g0_from_b.calibration.map(|c| c.0);
        on_backend!(&mut self.tx, Tx, t => sqlx::query(sql::SET_REFERENCE_SYSTEMATIC)
            .bind(systematic.as_slice())
            .bind(stamp)
            .bind(id)
            .bind(version)
            .execute(&mut *t.conn)
            .await
            .map(|_| ()))?;
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
        let columns = version_columns("calibration", parent_from_child)?;
        let id = self.link_ids[link.0];
        let p = columns.pose;
        let (version,): (i64,) = outboxed!(
            &mut self.tx,
            sql::INSERT_CALIBRATION,
            [
                id,
                valid_from_ns,
                p[0],
                p[1],
                p[2],
                p[3],
                p[4],
                p[5],
                p[6],
                columns.cov.as_slice(),
                now_ns,
            ],
            fetch_one
        )?;
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
        let id = self.link_ids[link.0];
        outboxed!(
            &mut self.tx,
            sql::INSERT_LINK_RESET,
            [id, now_ns, by, note],
            execute
        )?;
        Ok(())
    }

    /// Records an acceptance of the rig; answers its id.
    pub async fn insert_acceptance(
        &mut self,
        new: &NewAcceptance<'_>,
        now_ns: i64,
    ) -> StoreResult<i64> {
        let (id,): (i64,) = on_backend!(&mut self.tx, Tx, t => {
            sqlx::query_as(sql::INSERT_ACCEPTANCE)
                .bind(now_ns)
                .bind(new.by)
                .bind(new.note)
                .bind(new.passed)
                .bind(new.record_json)
                .fetch_one(&mut *t.conn)
                .await
        })?;
        Ok(id)
    }

    /// Saves the filter bank's state.
    pub async fn save_filter_state(
        &mut self,
        digest: &str,
        state_json: &str,
        now_ns: i64,
    ) -> StoreResult<()> {
        on_backend!(&mut self.tx, Tx, t => {
            sqlx::query(sql::SAVE_FILTER_STATE)
                .bind(digest)
                .bind(state_json)
                .bind(now_ns)
                .execute(&mut *t.conn)
                .await
                .map(|_| ())
        })?;
        Ok(())
    }
}

/// An acceptance to record.
#[derive(Debug, Clone, Copy)]
pub struct NewAcceptance<'a> {
    /// Who ran it.
    pub by: &'a str,
    /// Their note.
    pub note: Option<&'a str>,
    /// Whether it passed.
    pub passed: bool,
    /// Its record (JSON).
    pub record_json: &'a str,
}

/// The columns of a reference or calibration, checked finite.
fn version_columns(what: &str, value: &PoseCov) -> StoreResult<VersionColumns> {
    let pose = pose_columns(&value.pose);
    finite(&format!("{what} pose"), &pose)?;
    finite(&format!("{what} covariance"), value.cov.as_slice())?;
    Ok(VersionColumns {
        pose,
        cov: encode_mat6(&value.cov),
    })
}
