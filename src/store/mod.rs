//! The store: the history of one installation, on SQLite or PostgreSQL.
//!
//! Only this module contains SQL. It takes and returns domain types (poses, covariances,
//! results); rows are converted at its edge. [`Store`] (the read side) and [`WriteConn`] (the
//! one writer, owned by the service's pipeline, which commits many requests per transaction)
//! are the seam the rest of the service uses; each dispatches to a backend module:
//!
//! * [`sqlite`]: one file, WAL mode, `synchronous = FULL` (`migrations/`), the embedded default;
//! * [`postgres`]: a server, samples, results and rollups partitioned by time with pg_partman
//!   (`migrations-postgres/`), synchronous commit.
//!
//! Both promise the same: a commit returns only once durable, so what the service
//! acknowledges survives a crash; a transaction that fails leaves nothing behind and the next
//! starts on a fresh connection; the same keys and conflict rules. The behaviour both share
//! (checks of values before they reach a row, the merge of rollups, the planning of a history)
//! lives here, once; the backends hold only their statements. Conventions of both schemas:
//! times are integer nanoseconds since the Unix epoch (UTC), lengths millimetres, rotations
//! unit quaternions, covariances 36 little-endian f64 (column-major) in a byte string, except
//! a result's two covariances, now written as the 21 of their upper triangle (column by
//! column; older rows hold 36, and both forms read).

/// Runs the same expression on whichever backend `$value` holds.
macro_rules! on_backend {
    ($value:expr, $enum:ident, $b:ident => $body:expr) => {
        match $value {
            $enum::Sqlite($b) => $body,
            $enum::Postgres($b) => $body,
        }
    };
}

/// Runs one statement on whichever backend `$value` holds: `sqlx::query_as($sql)` with the
/// `$arg`s bound in order, then `$fetch` on the connection or pool `$conn`.
macro_rules! query_on {
    ($value:expr, $enum:ident, $b:ident => $conn:expr, $sql:expr, [$($arg:expr),* $(,)?], $fetch:ident) => {
        on_backend!($value, $enum, $b => sqlx::query_as($sql)$(.bind($arg))*.$fetch($conn).await)
    };
}

/// Runs an [`sql::Outboxed`] write on whichever backend `$value` holds, the `$arg`s bound in
/// order and, on SQLite, the transaction's commit number last: `fetch_one` answers the
/// statement's row, `execute` nothing.
macro_rules! outboxed {
    ($value:expr, $stmt:expr, [$($arg:expr),* $(,)?], fetch_one) => {
        on_backend!($value, Tx, t => {
            let seq = t.outbox_seq();
            let q = sqlx::query_as($stmt.text(seq.is_some()))$(.bind($arg))*;
            let q = match seq {
                Some(seq) => q.bind(seq),
                None => q,
            };
            q.fetch_one(&mut *t.conn).await
        })
    };
    ($value:expr, $stmt:expr, [$($arg:expr),* $(,)?], execute) => {
        on_backend!($value, Tx, t => {
            let seq = t.outbox_seq();
            let q = sqlx::query($stmt.text(seq.is_some()))$(.bind($arg))*;
            let q = match seq {
                Some(seq) => q.bind(seq),
                None => q,
            };
            q.execute(&mut *t.conn).await.map(|_| ())
        })
    };
}

mod codec;
mod migrations;
pub mod outbox;
pub mod postgres;
pub(crate) mod rollup;
mod rows;
pub mod schema;
mod sql;
pub mod sqlite;
mod write;

pub use codec::{Quality, SampleValues};
pub use postgres::central::{
    Central, RawRequestRecord, SiteRecord, SiteUpkeep, SiteUpload, StreamRecord, SyncOutcome,
};
pub use rows::{
    Acknowledgement, StoredAcceptance, StoredAlarm, StoredCalibration, StoredResult, StoredSample,
};
pub use sqlite::APPLICATION_ID;
use write::Writer;
pub use write::{BudgetCut, NewAcceptance, NewResult, NewSample, WriteConn, WriteTx};

use crate::bank::ResultSource;
use crate::chain::LinkId;
use crate::config::Database;
use crate::deformation::{MeasuredPose, SmallMotion};
use crate::geometry::{PoseCov, ReportedSigmas};
use crate::model::TargetId;
use codec::{encode_mat6, encode_sym6, pose_columns};
use outbox::{Backlog, KeepUnsent, OutboxBatch, Registry, TableRows, Tier};
use rows::{ResultColumns, SampleColumns, VersionColumns};
use std::path::PathBuf;
use std::sync::Arc;

/// Errors of the store.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The database failed.
    #[error("database error: {0}")]
    Database(sqlx::Error),
    /// A migration failed.
    #[error("migration failed: {0}")]
    Migration(sqlx::migrate::MigrateError),
    /// The database could not be opened or prepared at start-up.
    #[error("cannot open the database {database}: {message}")]
    Open {
        /// The configured file, or the URL without its password.
        database: String,
        /// Why.
        message: String,
    },
    /// The file is an SQLite database of another program.
    #[error(
        "{} is not a brokenray database (it holds tables of another program); \
         choose another `[server] database`", path.display()
    )]
    Foreign {
        /// The configured file.
        path: PathBuf,
    },
    /// The configured file was removed or replaced while the service ran: writes would go to a
    /// file nobody can find again, so none is accepted.
    #[error(
        "the database file {} was removed or replaced while the service ran; no write is \
         accepted until the service is restarted", path.display()
    )]
    FileReplaced {
        /// The configured file.
        path: PathBuf,
    },
    /// A value about to be written is not finite (a defect upstream; nothing is written).
    #[error("refusing to store a non-finite {what}")]
    NonFinite {
        /// The column or quantity.
        what: String,
    },
    /// The database server cannot be reached.
    #[error("the database server cannot be reached: {0}")]
    Unreachable(String),
    /// Another brokenray service holds this database's writer lock.
    #[error(
        "another brokenray service writes to this database (it holds the writer's lock); \
         one database has one writer"
    )]
    WriterLocked,
    /// The outbox of a fleet's site is an SQLite file's; this database has none.
    #[error("this database is no site's outbox (a site that uploads keeps its history in SQLite)")]
    NotAnOutbox,
    /// A long scan (through rusqlite) failed.
    #[error("database error while scanning: {0}")]
    Scan(String),
    /// A stored value could not be decoded (a corrupted or foreign database).
    #[error("stored data is malformed: {0}")]
    Malformed(String),
    /// A site's upload holds rows the centre cannot write (of another tier than its batch's,
    /// or not the table's columns): the same upload is refused every time.
    #[error("the upload cannot be applied: {0}")]
    UploadRefused(String),
    /// What a check upstream should have prevented did happen (a defect; nothing is written).
    #[error("a defect: {0}")]
    Defect(String),
    /// A backup, or a new outbox generation, cannot be made (the file exists or is missing,
    /// `pg_dump` failed); nothing stored changed.
    #[error("{0}")]
    Backup(String),
    /// The database refuses a value it was given (a data exception or a broken constraint):
    /// it will refuse the same again, so retrying is useless.
    #[error("the database refuses a value: {0}")]
    ValueRefused(String),
}

impl StoreError {
    /// The error as [`StoreError::ValueRefused`] when the database refused a value (SQLSTATE
    /// class 22, a data exception, or 23, an integrity constraint), unchanged otherwise.
    pub fn refusal_of_value(self) -> StoreError {
        if let StoreError::Database(sqlx::Error::Database(e)) = &self
            && let Some(code) = e.code()
            && (code.starts_with("22") || code.starts_with("23"))
        {
            return StoreError::ValueRefused(format!("{} (SQLSTATE {code})", e.message()));
        }
        self
    }
}

// By hand rather than `#[from]`: the message already carries the cause, and a `source` would
// print it a second time in an error chain.
impl From<sqlx::Error> for StoreError {
    fn from(e: sqlx::Error) -> Self {
        StoreError::Database(e)
    }
}

impl From<sqlx::migrate::MigrateError> for StoreError {
    fn from(e: sqlx::migrate::MigrateError) -> Self {
        StoreError::Migration(e)
    }
}

/// How many samples of a link a window holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct SampleCount {
    /// Samples stored.
    pub stored: u64,
    /// Of them, those the filter rejected as outliers.
    pub outliers: u64,
}

/// What the health check knows of the writer: whether its last commit failed, and why.
#[derive(Debug, Default)]
pub struct WriterHealth {
    failing: std::sync::atomic::AtomicBool,
    consecutive_failures: std::sync::atomic::AtomicU64,
    last_error: std::sync::Mutex<Option<String>>,
}

impl WriterHealth {
    /// Records a commit that succeeded: the writer is healthy again.
    pub fn record_ok(&self) {
        use std::sync::atomic::Ordering::Relaxed;
        self.failing.store(false, Relaxed);
        self.consecutive_failures.store(0, Relaxed);
    }

    /// Records a failed commit.
    pub fn record_failure(&self, error: &StoreError) {
        use std::sync::atomic::Ordering::Relaxed;
        self.failing.store(true, Relaxed);
        self.consecutive_failures.fetch_add(1, Relaxed);
        if let Ok(mut last) = self.last_error.lock() {
            *last = Some(error.to_string());
        }
    }

    /// The last failure, while the writer has not committed since.
    pub fn problem(&self) -> Option<String> {
        use std::sync::atomic::Ordering::Relaxed;
        if !self.failing.load(Relaxed) {
            return None;
        }
        let last = self.last_error.lock().ok().and_then(|l| l.clone());
        Some(format!(
            "the last {} commit(s) failed: {}",
            self.consecutive_failures.load(Relaxed),
            last.unwrap_or_default()
        ))
    }
}

/// The state of the database as the health check sees it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DatabaseHealth {
    /// The configured file is the one open, and answers a query on the health connection.
    pub reachable: bool,
    /// The writer's last commit succeeded (or none was tried).
    pub writer_ok: bool,
    /// What is wrong, when something is.
    pub problem: Option<String>,
}

/// Result alias of the store.
pub type StoreResult<T> = Result<T, StoreError>;

/// A health probe's verdict: `None` when `query` answered within 2 s, else what is wrong (the
/// caller then drops its health connection, so the next probe connects afresh).
async fn probe<T, E: std::fmt::Display>(
    query: impl std::future::Future<Output = Result<T, E>>,
) -> Option<String> {
    match tokio::time::timeout(std::time::Duration::from_secs(2), query).await {
        Ok(Ok(_)) => None,
        Ok(Err(e)) => Some(format!("the database does not answer: {e}")),
        Err(_) => Some("the database did not answer within 2 s".to_owned()),
    }
}

/// How a reference came about, as its row stores it.
struct WindowOrigin {
    /// `explicit` or `window`.
    origin: &'static str,
    /// The window's start, end (ns) and results averaged, for a reference from a window.
    from_ns: Option<i64>,
    to_ns: Option<i64>,
    count: Option<i64>,
}

/// The read side of a backend.
#[derive(Debug, Clone)]
enum Reader {
    Sqlite(sqlite::Reader),
    Postgres(postgres::Reader),
}

/// The read side of the store, and the ids of the installation's links and targets.
#[derive(Debug, Clone)]
pub struct Store {
    reader: Reader,
    writer: Arc<WriterHealth>,
    /// Database ids of the installation's links, indexed by `LinkId`.
    link_ids: Arc<[i64]>,
    /// Database ids of the installation's targets, indexed by target index.
    target_ids: Arc<[i64]>,
}

/// Opens the installation's database (`server.database`: an SQLite file, created if needed,
/// or a PostgreSQL database), applies migrations and registers the names of its links and
/// targets. Returns the read side and the one write connection. Every error names the
/// database.
pub async fn open(
    installation: &crate::config::Installation,
    now_ns: i64,
) -> StoreResult<(Store, WriteConn)> {
    let link_names: Vec<&String> = installation.model.links.iter().map(|l| &l.name).collect();
    let target_names: Vec<&String> = installation.model.targets.iter().map(|t| &t.name).collect();
    let (reader, backend, link_ids, target_ids) = match &installation.server.database {
        Database::Sqlite(path) => {
            let (r, w, l, t) = sqlite::open(path, &link_names, &target_names, now_ns).await?;
            (Reader::Sqlite(r), Writer::Sqlite(w), l, t)
        }
        Database::Postgres(url) => {
            let (r, w, l, t) = postgres::open(url, &link_names, &target_names, now_ns).await?;
            (Reader::Postgres(r), Writer::Postgres(w), l, t)
        }
    };
    let writer = Arc::new(WriterHealth::default());
    let link_ids: Arc<[i64]> = link_ids.into();
    let target_ids: Arc<[i64]> = target_ids.into();
    Ok((
        Store {
            reader,
            writer: Arc::clone(&writer),
            link_ids: Arc::clone(&link_ids),
            target_ids: Arc::clone(&target_ids),
        },
        WriteConn {
            backend,
            health: writer,
            link_ids,
            target_ids,
        },
    ))
}

/// Opens the installation's database for reading only, beside a service that writes to it
/// (`replay`): on PostgreSQL without migrating or taking the writer's lock; on SQLite as
/// [`open`] does, the write connection dropped at once (WAL lets both go on).
pub async fn open_reader(
    installation: &crate::config::Installation,
    now_ns: i64,
) -> StoreResult<Store> {
    let link_names: Vec<&String> = installation.model.links.iter().map(|l| &l.name).collect();
    let target_names: Vec<&String> = installation.model.targets.iter().map(|t| &t.name).collect();
    match &installation.server.database {
        Database::Sqlite(_) => {
            // Dropped, not closed: closing checkpoints the WAL, which would hold up the
            // service's writer.
            let (store, _write) = open(installation, now_ns).await?;
            Ok(store)
        }
        Database::Postgres(url) => {
            let (reader, link_ids, target_ids) =
                postgres::open_reader(url, &link_names, &target_names).await?;
            Ok(Store {
                reader: Reader::Postgres(reader),
                writer: Arc::new(WriterHealth::default()),
                link_ids: link_ids.into(),
                target_ids: target_ids.into(),
            })
        }
    }
}

/// Writes a consistent copy of the database to `out` while the service may be writing to it:
/// for SQLite a database file (`VACUUM INTO`) whose outbox starts a new generation (restored,
/// it never reuses the original's commit numbers at a centre), for PostgreSQL a `pg_dump`
/// archive (custom format, one snapshot). Refuses to overwrite `out`. Returns the copy's size
/// in bytes.
pub async fn backup(database: &Database, out: &std::path::Path) -> StoreResult<u64> {
    match database {
        Database::Sqlite(path) => sqlite::backup(path, out).await,
        Database::Postgres(url) => postgres::backup(url, out).await,
    }
}

/// Starts a new generation of the outbox of the SQLite database at `path` (migrated first),
/// for a database restored from a copy that did not start one itself (a file-system snapshot):
/// the centre then takes its commits as a new stream. Run while no service uses the file.
pub async fn new_outbox_generation(path: &std::path::Path) -> StoreResult<outbox::OutboxIdentity> {
    sqlite::new_generation(path).await
}

impl Store {
    /// The next batch of `tier` after the commit `after` (`None`: from the start), about
    /// `limit` rows of whole commits; `None` when nothing waits. A commit of more than `limit`
    /// rows goes in parts: `part` is where the next starts, and the answer says where the
    /// one after it does (`None`: the batch ends a commit).
    pub async fn outbox_batch(
        &self,
        tier: Tier,
        after: Option<i64>,
        limit: usize,
        part: Option<&outbox::PartCursor>,
    ) -> StoreResult<Option<(OutboxBatch, Option<outbox::PartCursor>)>> {
        match &self.reader {
            Reader::Sqlite(r) => {
                r.outbox_batch(tier, after.unwrap_or(i64::MIN), limit, part)
                    .await
            }
            Reader::Postgres(_) => Err(StoreError::NotAnOutbox),
        }
    }

    /// When the outbox's commit `seq` was made (the site's clock, ns); `None` when its record
    /// is gone (pruned with old rows).
    pub async fn commit_stamp(&self, seq: i64) -> StoreResult<Option<i64>> {
        match &self.reader {
            Reader::Sqlite(r) => r.commit_stamp(seq).await,
            Reader::Postgres(_) => Err(StoreError::NotAnOutbox),
        }
    }

    /// The raw rows (samples and raw results) measured in `[from_ns, to_ns)`, for a period the
    /// centre asked for (a site's outbox: SQLite only).
    pub async fn raw_rows_in(&self, from_ns: i64, to_ns: i64) -> StoreResult<Vec<TableRows>> {
        match &self.reader {
            Reader::Sqlite(r) => r.raw_rows_in(from_ns, to_ns).await,
            Reader::Postgres(_) => Err(StoreError::NotAnOutbox),
        }
    }

    /// The earliest time of a raw row measured in `[from_ns, to_ns)` (a site's outbox).
    pub async fn next_raw_time(&self, from_ns: i64, to_ns: i64) -> StoreResult<Option<i64>> {
        match &self.reader {
            Reader::Sqlite(r) => r.next_raw_time(from_ns, to_ns).await,
            Reader::Postgres(_) => Err(StoreError::NotAnOutbox),
        }
    }

    /// The raw rows measured in `[from_ns, to_ns)`, counted (a site's outbox).
    pub async fn count_raw_in(&self, from_ns: i64, to_ns: i64) -> StoreResult<u64> {
        match &self.reader {
            Reader::Sqlite(r) => r.count_raw_in(from_ns, to_ns).await,
            Reader::Postgres(_) => Err(StoreError::NotAnOutbox),
        }
    }

    /// The names behind the ids of the outbox's rows.
    pub async fn registry(&self) -> StoreResult<Registry> {
        match &self.reader {
            Reader::Sqlite(r) => r.registry().await,
            Reader::Postgres(_) => Err(StoreError::NotAnOutbox),
        }
    }

    /// The outbox's identity (random, made with the file) and its generation.
    pub async fn outbox_identity(&self) -> StoreResult<outbox::OutboxIdentity> {
        match &self.reader {
            Reader::Sqlite(r) => r.outbox_identity().await,
            Reader::Postgres(_) => Err(StoreError::NotAnOutbox),
        }
    }

    /// The outbox's newest commit (0 before any).
    pub async fn outbox_head(&self) -> StoreResult<i64> {
        match &self.reader {
            Reader::Sqlite(r) => r.outbox_head().await,
            Reader::Postgres(_) => Err(StoreError::NotAnOutbox),
        }
    }

    /// Per tier, the acknowledged number and the rows still to send.
    pub async fn backlog(&self) -> StoreResult<Vec<(Tier, Backlog)>> {
        match &self.reader {
            Reader::Sqlite(r) => r.backlog().await,
            Reader::Postgres(_) => Err(StoreError::NotAnOutbox),
        }
    }

    /// The health of the database and the writer: the database must answer a query (on a
    /// connection of its own, so that busy readers cannot fail it) and the writer's last
    /// commit must have succeeded.
    pub async fn health(&self) -> DatabaseHealth {
        let writer_problem = self.writer.problem();
        let database_problem = on_backend!(&self.reader, Reader, r => r.problem().await);
        DatabaseHealth {
            reachable: database_problem.is_none(),
            writer_ok: writer_problem.is_none(),
            problem: database_problem.or(writer_problem),
        }
    }

    /// Closes the read pool and the health connection.
    pub async fn close(&self) {
        on_backend!(&self.reader, Reader, r => r.close().await)
    }

    /// Stored samples of a link in `[from_ns, to_ns]`, oldest first, at most `limit`.
    pub async fn samples(
        &self,
        link: LinkId,
        from_ns: i64,
        to_ns: i64,
        limit: i64,
    ) -> StoreResult<Vec<StoredSample>> {
        let id = self.link_ids[link.0];
        let rows: Vec<rows::SampleRow> = query_on!(
            &self.reader, Reader, r => &r.pool,
            &sql::SAMPLES_IN, [id, from_ns, to_ns, limit],
            fetch_all
        )?;
        rows.into_iter().map(rows::SampleRow::into_sample).collect()
    }

    /// The committed samples of a link with times in `[from_ns, to_ns]`, with their values,
    /// read through a reader: for the writer, which must know what is stored before it
    /// filters a batch that may repeat it, while a commit of its own is still being written.
    pub async fn sample_values(
        &self,
        link: LinkId,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<Vec<(i64, SampleValues)>> {
        let samples = self.samples(link, from_ns, to_ns, i64::MAX).await?;
        Ok(samples.into_iter().map(|s| (s.time_ns, s.values)).collect())
    }

    /// Stored results of a target in `[from_ns, to_ns]`, oldest first, at most `limit`.
    pub async fn results(
        &self,
        target: TargetId,
        source: ResultSource,
        from_ns: i64,
        to_ns: i64,
        limit: i64,
    ) -> StoreResult<Vec<StoredResult>> {
        let (id, source) = (self.target_ids[target.0], codec::source_column(source));
        let rows: Vec<rows::ResultRow> = query_on!(
            &self.reader, Reader, r => &r.pool,
            &sql::RESULTS_IN, [id, source, from_ns, to_ns, limit],
            fetch_all
        )?;
        rows.into_iter().map(rows::ResultRow::into_result).collect()
    }

    /// The paper's statistics (Table 4/5) of a target's results in `[from_ns, to_ns]`, with the
    /// times of the first and last result. The rows are streamed and folded one by one:
    /// memory does not grow with the window.
    pub async fn pose_stats(
        &self,
        target: TargetId,
        source: ResultSource,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<(Option<crate::stats::PoseStats>, Option<(i64, i64)>)> {
        let (id, source) = (self.target_ids[target.0], codec::source_column(source));
        match &self.reader {
            Reader::Sqlite(r) => r.pose_stats(id, source, from_ns, to_ns).await,
            Reader::Postgres(r) => {
                use futures::TryStreamExt as _;
                type PoseRow = (
                    i64,
                    f64,
                    f64,
                    f64,
                    f64,
                    f64,
                    f64,
                    f64,
                    Vec<u8>,
                    Option<Vec<u8>>,
                );
                let mut rows = sqlx::query_as::<_, PoseRow>(sql::RESULT_POSES_IN)
                    .bind(id)
                    .bind(source)
                    .bind(from_ns)
                    .bind(to_ns)
                    .fetch(&r.pool);
                let mut acc = crate::stats::PoseStatsAccumulator::default();
                let mut span: Option<(i64, i64)> = None;
                while let Some((t, tx, ty, tz, qw, qx, qy, qz, cov, systematic)) =
                    rows.try_next().await?
                {
                    let pose = codec::pose_from_columns([tx, ty, tz, qw, qx, qy, qz]);
                    match codec::random_covariance(&cov, systematic.as_deref()) {
                        Some(random) => acc.push_with_random(&pose, &random),
                        None => acc.push(&pose),
                    }
                    span = Some((span.map_or(t, |(first, _)| first), t));
                }
                Ok((acc.finish(), span))
            }
        }
    }

    /// How many results of a target are stored in `[from_ns, to_ns]`.
    pub async fn count_results(
        &self,
        target: TargetId,
        source: ResultSource,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<u64> {
        let (id, source) = (self.target_ids[target.0], codec::source_column(source));
        let (n,): (i64,) = query_on!(
            &self.reader, Reader, r => &r.pool,
            sql::COUNT_RESULTS, [id, source, from_ns, to_ns],
            fetch_one
        )?;
        Ok(u64::try_from(n).unwrap_or(0))
    }

    /// The time of a link's newest stored sample, `None` when it has none.
    pub async fn newest_sample_ns(&self, link: LinkId) -> StoreResult<Option<i64>> {
        let id = self.link_ids[link.0];
        let (newest,): (Option<i64>,) = query_on!(
            &self.reader, Reader, r => &r.pool,
            sql::NEWEST_SAMPLE, [id],
            fetch_one
        )?;
        Ok(newest)
    }

    /// How many samples of a link are stored in `[from_ns, to_ns]`.
    pub async fn count_samples(&self, link: LinkId, from_ns: i64, to_ns: i64) -> StoreResult<u64> {
        let id = self.link_ids[link.0];
        let (n,): (i64,) = query_on!(
            &self.reader, Reader, r => &r.pool,
            sql::COUNT_SAMPLES, [id, from_ns, to_ns],
            fetch_one
        )?;
        Ok(u64::try_from(n).unwrap_or(0))
    }

    /// The silences longer than `min_gap_ns` between consecutive results of a target in
    /// `[from_ns, to_ns]`: the times of the result before and after each, oldest first, at
    /// most `limit`.
    pub async fn result_gaps(
        &self,
        target: TargetId,
        source: ResultSource,
        window: (i64, i64),
        min_gap_ns: i64,
        limit: i64,
    ) -> StoreResult<Vec<(i64, i64)>> {
        let (id, source) = (self.target_ids[target.0], codec::source_column(source));
        let (from_ns, to_ns) = window;
        Ok(query_on!(
            &self.reader, Reader, r => &r.pool,
            sql::RESULT_GAPS, [id, source, from_ns, to_ns, min_gap_ns, limit],
            fetch_all
        )?)
    }

    /// How many samples of a link are stored in `[from_ns, to_ns]`, and how many of them
    /// were rejected as outliers.
    pub async fn count_samples_and_outliers(
        &self,
        link: LinkId,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<SampleCount> {
        let id = self.link_ids[link.0];
        let (stored, outliers): (i64, i64) = query_on!(
            &self.reader, Reader, r => &r.pool,
            sql::COUNT_SAMPLES_AND_OUTLIERS, [id, from_ns, to_ns],
            fetch_one
        )?;
        Ok(SampleCount {
            stored: u64::try_from(stored).unwrap_or(0),
            outliers: u64::try_from(outliers).unwrap_or(0),
        })
    }

    /// The stored results of a target nearest to `at_ns`: the newest at or before it and the
    /// oldest after it.
    pub async fn results_around(
        &self,
        target: TargetId,
        source: ResultSource,
        at_ns: i64,
    ) -> StoreResult<(Option<StoredResult>, Option<StoredResult>)> {
        let (id, source) = (self.target_ids[target.0], codec::source_column(source));
        let mut around: [Option<rows::ResultRow>; 2] = [None, None];
        for (i, statement) in [&sql::RESULT_AT_OR_BEFORE, &sql::RESULT_AFTER]
            .into_iter()
            .enumerate()
        {
            around[i] = query_on!(
                &self.reader, Reader, r => &r.pool,
                statement, [id, source, at_ns],
                fetch_optional
            )?;
        }
        let [before, after] = around;
        Ok((
            before.map(rows::ResultRow::into_result).transpose()?,
            after.map(rows::ResultRow::into_result).transpose()?,
        ))
    }

    /// The newest stored result of a target.
    pub async fn latest_result(
        &self,
        target: TargetId,
        source: ResultSource,
    ) -> StoreResult<Option<StoredResult>> {
        Ok(self.results_around(target, source, i64::MAX).await?.0)
    }

    /// Every reference version of a target, oldest first.
    pub async fn references(
        &self,
        target: TargetId,
    ) -> StoreResult<Vec<crate::deformation::ReferenceVersion>> {
        let id = self.target_ids[target.0];
        let rows: Vec<rows::ReferenceRow> =
            query_on!(&self.reader, Reader, r => &r.pool, &sql::REFERENCES_OF, [id], fetch_all)?;
        rows.into_iter()
            .map(rows::ReferenceRow::into_reference)
            .collect()
    }

    /// Every calibration version of a link, oldest first.
    pub async fn calibrations(&self, link: LinkId) -> StoreResult<Vec<StoredCalibration>> {
        let id = self.link_ids[link.0];
        let rows: Vec<rows::CalibrationRow> =
            query_on!(&self.reader, Reader, r => &r.pool, &sql::CALIBRATIONS_OF, [id], fetch_all)?;
        rows.into_iter()
            .map(rows::CalibrationRow::into_calibration)
            .collect()
    }

    /// The newest manual restart of each link's filter: when (ns, wall clock), who, why.
    pub async fn last_link_resets(
        &self,
    ) -> StoreResult<Vec<(LinkId, i64, Option<String>, Option<String>)>> {
        let rows: Vec<(i64, i64, Option<String>, Option<String>)> =
            query_on!(&self.reader, Reader, r => &r.pool, sql::LAST_LINK_RESETS, [], fetch_all)?;
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

    /// The newest acceptances, newest first, at most `limit`.
    pub async fn acceptances(&self, limit: i64) -> StoreResult<Vec<StoredAcceptance>> {
        let rows: Vec<rows::AcceptanceRow> =
            query_on!(&self.reader, Reader, r => &r.pool, &sql::ACCEPTANCES, [limit], fetch_all)?;
        Ok(rows.into_iter().map(StoredAcceptance::from).collect())
    }

    /// The newest acceptance recorded at or before `at_ns`.
    pub async fn acceptance_at(&self, at_ns: i64) -> StoreResult<Option<StoredAcceptance>> {
        let row: Option<rows::AcceptanceRow> = query_on!(
            &self.reader, Reader, r => &r.pool, &sql::ACCEPTANCE_AT, [at_ns], fetch_optional
        )?;
        Ok(row.map(StoredAcceptance::from))
    }

    /// One acceptance by its id.
    pub async fn acceptance(&self, id: i64) -> StoreResult<Option<StoredAcceptance>> {
        let row: Option<rows::AcceptanceRow> =
            query_on!(&self.reader, Reader, r => &r.pool, &sql::ACCEPTANCE, [id], fetch_optional)?;
        Ok(row.map(StoredAcceptance::from))
    }

    /// The persisted filter state: `(installation digest, state)`.
    pub async fn filter_state(&self) -> StoreResult<Option<(String, String)>> {
        Ok(query_on!(&self.reader, Reader, r => &r.pool, sql::FILTER_STATE, [], fetch_optional)?)
    }

    /// One alarm transition by id.
    pub async fn alarm(&self, id: i64) -> StoreResult<Option<StoredAlarm>> {
        let row: Option<rows::AlarmRow> =
            query_on!(&self.reader, Reader, r => &r.pool, &sql::ALARM_BY_ID, [id], fetch_optional)?;
        row.map(|row| rows::alarm_of_row(row, &self.target_ids))
            .transpose()
    }

    /// Alarm transitions in `[from_ns, to_ns]`, of one target or all, at most `limit`: the
    /// oldest first, or with `newest_first` the newest (so a limit keeps the latest ones).
    pub async fn alarms(
        &self,
        target: Option<TargetId>,
        from_ns: i64,
        to_ns: i64,
        limit: i64,
        newest_first: bool,
    ) -> StoreResult<Vec<StoredAlarm>> {
        let id = target.map(|t| self.target_ids[t.0]);
        let statement: &str = if newest_first {
            &sql::ALARMS_NEWEST_FIRST
        } else {
            &sql::ALARMS_OLDEST_FIRST
        };
        let rows: Vec<rows::AlarmRow> = query_on!(
            &self.reader, Reader, r => &r.pool,
            statement, [id, from_ns, to_ns, limit],
            fetch_all
        )?;
        rows.into_iter()
            .map(|row| rows::alarm_of_row(row, &self.target_ids))
            .collect()
    }

    /// The level each alarm kind of a target was last left at (`none` when never raised).
    pub async fn alarm_levels(&self, target: TargetId) -> StoreResult<[crate::alarms::Level; 3]> {
        use crate::alarms::{AlarmKind, Level};
        let id = self.target_ids[target.0];
        let mut out = [Level::None; 3];
        for (i, kind) in [AlarmKind::Deformation, AlarmKind::Rate, AlarmKind::Stale]
            .iter()
            .enumerate()
        {
            let level: Option<(String,)> = query_on!(
                &self.reader, Reader, r => &r.pool,
                sql::LAST_ALARM_LEVEL, [id, kind.name()],
                fetch_optional
            )?;
            if let Some((level,)) = level {
                out[i] = Level::parse(&level).unwrap_or(Level::None);
            }
        }
        Ok(out)
    }
}
