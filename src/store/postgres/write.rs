//! The PostgreSQL write connection and the statements of one transaction.
//!
//! Like the SQLite writer, transactions are plain `BEGIN` / `COMMIT` statements on one
//! connection, and a transaction that did not commit leaves the connection unclean: the next
//! [`Writer::begin`] rolls it back, or, when that fails (the server restarted, the network
//! dropped), connects again. The writer's session runs with `synchronous_commit = on`
//! whatever the server's default, so a `COMMIT` returns only once the server has flushed it
//! to its write-ahead log. It holds an advisory lock: a second brokenray service writing to
//! the same database is refused instead of interleaving its rollups with this one's.
//!
//! Samples and results go in by binary `COPY` (rows in the server's own format, no statement
//! to plan); rollups and the keys to look up as one statement each, every column an array
//! expanded by `unnest`.

use super::super::rows::{ResultColumns, RollupKey, RollupRow, SampleColumns};
use super::super::schema::{RESULTS, SAMPLES, Table};
use super::super::{StoreError, StoreResult};
use sqlx::postgres::{PgConnectOptions, PgConnection};
use sqlx::{ConnectOptions, Connection};

/// Keys per rollup statement: bounds the arrays a statement carries.
const ROWS_PER_STATEMENT: usize = 10_000;

/// The one connection that writes.
#[derive(Debug)]
pub(in crate::store) struct Writer {
    /// `None` after a failure until the next [`Writer::begin`] reconnects.
    conn: Option<PgConnection>,
    /// False from `BEGIN` until a successful `COMMIT`: the connection's state is then unknown.
    clean: bool,
    options: Box<PgConnectOptions>,
}

/// One write transaction. Dropped without [`Tx::commit`], it is rolled back when the next
/// begins.
pub(in crate::store) struct Tx<'c> {
    pub(in crate::store) conn: &'c mut PgConnection,
    clean: &'c mut bool,
}

impl Writer {
    /// Connects, with the session settings the writer relies on, and takes the writer's lock.
    pub(super) async fn connect(options: &PgConnectOptions) -> StoreResult<PgConnection> {
        let mut conn = tokio::time::timeout(
            super::CONNECT_TIMEOUT,
            options
                .clone()
                .options([("synchronous_commit", "on")])
                .connect(),
        )
        .await
        .map_err(|_| StoreError::Unreachable("the server did not answer within 5 s".into()))??;
        let (locked,): (bool,) = sqlx::query_as("select pg_try_advisory_lock($1)")
            .bind(super::WRITER_LOCK)
            .fetch_one(&mut conn)
            .await?;
        if !locked {
            let _ = conn.close().await;
            return Err(StoreError::WriterLocked);
        }
        Ok(conn)
    }

    pub(super) fn new(conn: PgConnection, options: &PgConnectOptions) -> Self {
        Self {
            conn: Some(conn),
            clean: true,
            options: Box::new(options.clone()),
        }
    }

    /// Starts a transaction: after one that did not commit, first rolls it back, or connects
    /// again when the connection does not answer.
    pub(in crate::store) async fn begin(&mut self) -> StoreResult<Tx<'_>> {
        self.ready().await?;
        self.clean = false;
        let began = match self.conn.as_mut() {
            Some(conn) => sqlx::query("begin").execute(&mut *conn).await.map(|_| ()),
            None => unreachable!("connected above"),
        };
        if let Err(e) = began {
            // A connection that cannot begin is gone (the server restarted between commits).
            self.conn = None;
            return Err(e.into());
        }
        let Some(conn) = self.conn.as_mut() else {
            unreachable!("connected above")
        };
        Ok(Tx {
            conn,
            clean: &mut self.clean,
        })
    }

    /// The connection, outside any transaction: after one that did not commit, first rolls
    /// it back, or connects again when the connection does not answer.
    pub(in crate::store) async fn ready(&mut self) -> StoreResult<&mut PgConnection> {
        if !self.clean
            && let Some(conn) = self.conn.as_mut()
            && sqlx::query("rollback").execute(&mut *conn).await.is_err()
            && let Some(old) = self.conn.take()
        {
            let _ = old.close().await;
        }
        if self.conn.is_none() {
            self.conn = Some(Self::connect(&self.options).await?);
            tracing::info!("the writer reconnected to PostgreSQL");
        }
        self.clean = true;
        let Some(conn) = self.conn.as_mut() else {
            unreachable!("connected above")
        };
        Ok(conn)
    }

    /// Marks the connection's state unknown after a statement outside a transaction failed:
    /// the next use rolls back or connects again.
    pub(in crate::store) fn suspect(&mut self) {
        self.clean = false;
    }

    /// Closes the connection (rolling back an unfinished transaction), which also releases
    /// the writer's lock.
    pub(in crate::store) async fn close(self) -> StoreResult<()> {
        if let Some(mut conn) = self.conn {
            if !self.clean {
                let _ = sqlx::query("rollback").execute(&mut conn).await;
            }
            // Released before the connection closes: the server ends a closed session's
            // backend on its own time, and the next writer must not find the lock still held.
            let _ = sqlx::query("select pg_advisory_unlock($1)")
                .bind(super::WRITER_LOCK)
                .execute(&mut conn)
                .await;
            conn.close().await?;
        }
        Ok(())
    }
}

/// Rows of one table in PostgreSQL's binary `COPY` format: a header, then per row the field
/// count (the table's width) and each field as its length (-1 for null) and its bytes in
/// network order, then a trailer. A row with other than the table's fields is caught at
/// [`CopyRows::finish`], before anything is sent.
struct CopyRows {
    table: Table,
    buf: Vec<u8>,
    /// Fields written to the current row.
    fields: usize,
    /// Whether a row had other than the table's width.
    misshapen: bool,
}

impl CopyRows {
    fn new(table: Table) -> Self {
        let mut buf = Vec::with_capacity(1 << 16);
        buf.extend_from_slice(b"PGCOPY\n\xff\r\n\0");
        buf.extend_from_slice(&0i32.to_be_bytes()); // flags
        buf.extend_from_slice(&0i32.to_be_bytes()); // header extension
        Self {
            table,
            buf,
            fields: table.width(),
            misshapen: false,
        }
    }

    /// Starts a row.
    fn row(&mut self) {
        self.end_row();
        let width = i16::try_from(self.table.width()).unwrap_or(i16::MAX);
        self.buf.extend_from_slice(&width.to_be_bytes());
    }

    fn end_row(&mut self) {
        self.misshapen |= self.fields != self.table.width();
        self.fields = 0;
    }

    fn field(&mut self, len: i32, bytes: &[u8]) {
        self.fields += 1;
        self.buf.extend_from_slice(&len.to_be_bytes());
        self.buf.extend_from_slice(bytes);
    }

    fn null(&mut self) {
        self.field(-1, &[]);
    }

    fn i64(&mut self, v: i64) {
        self.field(8, &v.to_be_bytes());
    }

    fn i64_or_null(&mut self, v: Option<i64>) {
        match v {
            Some(v) => self.i64(v),
            None => self.null(),
        }
    }

    fn f64(&mut self, v: f64) {
        self.field(8, &v.to_be_bytes());
    }

    fn f64_or_null(&mut self, v: Option<f64>) {
        match v {
            Some(v) => self.f64(v),
            None => self.null(),
        }
    }

    fn bool(&mut self, v: bool) {
        self.field(1, &[u8::from(v)]);
    }

    /// A `bytea` or `text` field (text's binary form is its UTF-8).
    fn bytes(&mut self, v: Option<&[u8]>) {
        match v {
            Some(v) => {
                // Fields are a few hundred bytes at most; one over 2 GB would make the server
                // refuse the copy (its length no longer matches), never store a wrong value.
                self.field(i32::try_from(v.len()).unwrap_or(i32::MAX), v);
            }
            None => self.null(),
        }
    }

    /// The rows with their trailer; an error when a row had other than the table's fields.
    fn finish(mut self) -> StoreResult<Vec<u8>> {
        self.end_row();
        if self.misshapen {
            return Err(StoreError::Defect(format!(
                "a row for `{}` without its {} fields",
                self.table.name,
                self.table.width()
            )));
        }
        self.buf.extend_from_slice(&(-1i16).to_be_bytes());
        Ok(self.buf)
    }
}

impl Tx<'_> {
    /// None: PostgreSQL's rows carry no commit number (a centre's copy is no outbox).
    pub(in crate::store) fn outbox_seq(&self) -> Option<i64> {
        None
    }

    /// Commits: flushed to the server's write-ahead log when this returns `Ok`.
    pub(in crate::store) async fn commit(self) -> StoreResult<()> {
        sqlx::query("commit").execute(&mut *self.conn).await?;
        *self.clean = true;
        Ok(())
    }

    /// Inserts samples by binary `COPY` (the fastest way into PostgreSQL: no statement to
    /// plan, rows in the server's own format).
    pub(in crate::store) async fn insert_samples(
        &mut self,
        samples: &[SampleColumns],
    ) -> StoreResult<()> {
        if samples.is_empty() {
            return Ok(());
        }
        let mut rows = CopyRows::new(SAMPLES);
        for s in samples {
            rows.row();
            rows.i64(s.link_id);
            rows.i64(s.time_ns);
            for v in s.pose {
                rows.f64(v);
            }
            rows.i64(s.uncertainty_kind);
            rows.bytes(s.uncertainty.as_deref());
            rows.f64_or_null(s.reprojection_rms_px);
            rows.i64_or_null(s.points);
            rows.bytes(Some(s.disposition.as_bytes()));
            rows.bool(s.outlier);
            rows.f64_or_null(s.nis);
            rows.i64(s.received_ns);
        }
        self.copy_in(rows).await
    }

    /// Inserts results; one at an existing key replaces it: the rows at the batch's keys are
    /// deleted (usually none), then the batch goes in by binary `COPY`.
    pub(in crate::store) async fn upsert_results(
        &mut self,
        results: &[ResultColumns],
    ) -> StoreResult<()> {
        if results.is_empty() {
            return Ok(());
        }
        // Per target and source, one index scan over the batch's times; the time span stated
        // on its own lets the planner skip the partitions outside it.
        let mut keys: std::collections::BTreeMap<(i64, i64), Vec<i64>> =
            std::collections::BTreeMap::new();
        for r in results {
            keys.entry((r.target_id, r.source))
                .or_default()
                .push(r.time_ns);
        }
        for ((target_id, source), times) in keys {
            let first = times.iter().copied().min().unwrap_or(0);
            let last = times.iter().copied().max().unwrap_or(0);
            sqlx::query(
                "delete from results where target_id = $1 and source = $2 \
                 and time_ns = any($3) and time_ns >= $4 and time_ns <= $5",
            )
            .bind(target_id)
            .bind(source)
            .bind(times)
            .bind(first)
            .bind(last)
            .execute(&mut *self.conn)
            .await?;
        }
        let mut rows = CopyRows::new(RESULTS);
        for r in results {
            rows.row();
            rows.i64(r.target_id);
            rows.i64(r.source);
            rows.i64(r.time_ns);
            for v in r.pose {
                rows.f64(v);
            }
            rows.bytes(Some(&r.cov));
            for v in r.sigmas {
                rows.f64(v);
            }
            rows.bytes(Some(r.status.as_bytes()));
            rows.f64(r.age_s);
            rows.f64_or_null(r.chi2);
            rows.i64_or_null(r.deformation.map(|(v, _)| v));
            for i in 0..6 {
                rows.f64_or_null(r.deformation.map(|(_, d)| d[i]));
            }
            rows.bytes(Some(&r.cov_systematic));
            rows.i64_or_null(r.calibration_stamp);
        }
        self.copy_in(rows).await
    }

    /// `COPY table (columns) FROM STDIN` of binary rows.
    async fn copy_in(&mut self, rows: CopyRows) -> StoreResult<()> {
        let statement = format!(
            "copy {} ({}) from stdin with (format binary)",
            rows.table.name,
            rows.table.list()
        );
        let rows = rows.finish()?;
        let mut copy = self.conn.copy_in_raw(&statement).await?;
        if let Err(e) = copy.send(rows).await {
            let _ = copy.abort("the rows could not be sent").await;
            return Err(e.into());
        }
        copy.finish().await?;
        Ok(())
    }

    /// The stored rollup rows at these keys.
    pub(in crate::store) async fn rollup_rows(
        &mut self,
        keys: &[RollupKey],
    ) -> StoreResult<Vec<RollupRow>> {
        let mut out = Vec::new();
        for chunk in keys.chunks(ROWS_PER_STATEMENT) {
            // The span of the keys' bucket starts, stated on its own, lets the planner skip
            // the partitions outside it (a join on the keys alone reads them all).
            let first = chunk.iter().map(|k| k.bucket_ns).min().unwrap_or(0);
            let last = chunk.iter().map(|k| k.bucket_ns).max().unwrap_or(0);
            let rows: Vec<RollupRow> = sqlx::query_as(
                "select r.target_id, r.source, r.width_s, r.bucket_ns, r.n, r.n_def, r.stats \
                 from unnest($1::int8[], $2::int8[], $3::int8[], $4::int8[]) as k (t, s, w, b) \
                 join rollups r on r.target_id = k.t and r.source = k.s and r.width_s = k.w \
                 and r.bucket_ns = k.b where r.bucket_ns >= $5 and r.bucket_ns <= $6",
            )
            .bind(chunk.iter().map(|k| k.target_id).collect::<Vec<_>>())
            .bind(chunk.iter().map(|k| k.source).collect::<Vec<_>>())
            .bind(chunk.iter().map(|k| k.width_s).collect::<Vec<_>>())
            .bind(chunk.iter().map(|k| k.bucket_ns).collect::<Vec<_>>())
            .bind(first)
            .bind(last)
            .fetch_all(&mut *self.conn)
            .await?;
            out.extend(rows);
        }
        Ok(out)
    }

    /// Writes rollup rows, replacing those at the same keys.
    pub(in crate::store) async fn upsert_rollups(&mut self, rows: &[RollupRow]) -> StoreResult<()> {
        for chunk in rows.chunks(ROWS_PER_STATEMENT) {
            sqlx::query(
                "insert into rollups (target_id, source, width_s, bucket_ns, n, n_def, stats) \
                 select * from unnest($1::int8[], $2::int8[], $3::int8[], $4::int8[], $5::int8[], \
                 $6::int8[], $7::bytea[]) \
                 on conflict (target_id, source, width_s, bucket_ns) do update set \
                 n = excluded.n, n_def = excluded.n_def, stats = excluded.stats",
            )
            .bind(chunk.iter().map(|r| r.target_id).collect::<Vec<_>>())
            .bind(chunk.iter().map(|r| r.source).collect::<Vec<_>>())
            .bind(chunk.iter().map(|r| r.width_s).collect::<Vec<_>>())
            .bind(chunk.iter().map(|r| r.bucket_ns).collect::<Vec<_>>())
            .bind(chunk.iter().map(|r| r.n).collect::<Vec<_>>())
            .bind(chunk.iter().map(|r| r.n_def).collect::<Vec<_>>())
            .bind(chunk.iter().map(|r| r.stats.as_slice()).collect::<Vec<_>>())
            .execute(&mut *self.conn)
            .await?;
        }
        Ok(())
    }

    /// Retention: drops the day partitions wholly before each cutoff, deletes the older rows
    /// of the partition a cutoff falls in (and of the default partition), then lets pg_partman
    /// make the coming days' partitions.
    pub(in crate::store) async fn prune(
        &mut self,
        samples_before_ns: i64,
        results_before_ns: i64,
    ) -> StoreResult<(u64, u64)> {
        let samples = super::drop_before(&mut *self.conn, "samples", samples_before_ns).await?;
        let results = super::drop_before(&mut *self.conn, "results", results_before_ns).await?;
        super::maintain(&mut *self.conn).await?;
        Ok((samples, results))
    }
}
