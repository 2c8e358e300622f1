//! The SQLite store: schema migrations, the write connection, and every query.
//!
//! Only this module contains SQL. It takes and returns domain types (poses, covariances,
//! results); rows are converted at its edge. Conventions of the schema (`migrations/`): times
//! are integer nanoseconds since the Unix epoch (UTC), lengths millimetres, rotations unit
//! quaternions, covariances 36 little-endian f64 (column-major) in a blob.
//!
//! The database runs in WAL mode with `synchronous = FULL`: a commit is on disk before it
//! returns, so what the service acknowledges survives a crash or a power cut. Reads go through
//! a pool of connections; all writes go through the one [`WriteConn`], owned by the service's
//! pipeline task, which commits many requests per transaction.

mod codec;
mod read;
pub mod rollup;
mod write;

/// The statements of one write transaction.
pub mod write_tx {
    pub use super::write::WriteTx;
}

pub use codec::{Quality, SampleValues, StoredUncertainty};
pub use read::{StoredAlarm, StoredCalibration, StoredReference, StoredResult, StoredSample};
pub use write::{NewResult, NewSample, WriteConn};

use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous,
};
use sqlx::{ConnectOptions, Connection};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The embedded migrations (`migrations/`), applied at start-up.
pub static MIGRATOR: sqlx::migrate::Migrator = sqlx::migrate!();

/// Errors of the store.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The database failed.
    #[error("database error: {0}")]
    Database(#[from] sqlx::Error),
    /// A migration failed.
    #[error("migration failed: {0}")]
    Migration(#[from] sqlx::migrate::MigrateError),
    /// A stored value could not be decoded (a corrupted or foreign database).
    #[error("stored data is malformed: {0}")]
    Malformed(String),
}

/// Result alias of the store.
pub type StoreResult<T> = Result<T, StoreError>;

/// The read side of the store, and the ids of the installation's links and targets.
#[derive(Debug, Clone)]
pub struct Store {
    pool: SqlitePool,
    path: PathBuf,
    /// Database ids of the installation's links, indexed by `LinkId`.
    link_ids: Vec<i64>,
    /// Database ids of the installation's targets, indexed by target index.
    target_ids: Vec<i64>,
}

fn options(path: &Path) -> SqliteConnectOptions {
    SqliteConnectOptions::new()
        .filename(path)
        .create_if_missing(true)
        .journal_mode(SqliteJournalMode::Wal)
        .synchronous(SqliteSynchronous::Full)
        .foreign_keys(true)
        .busy_timeout(Duration::from_secs(10))
        .disable_statement_logging()
}

/// Opens (creating if needed) the installation's database (`server.database`), applies
/// migrations and registers the names of its links and targets. Returns the read side and the
/// one write connection.
pub async fn open(
    installation: &crate::config::Installation,
    now_ns: i64,
) -> StoreResult<(Store, WriteConn)> {
    let path = installation.server.database.as_path();
    let link_names: Vec<&String> = installation.links.iter().map(|l| &l.name).collect();
    let target_names: Vec<&String> = installation.targets.iter().map(|t| &t.name).collect();
    let mut conn = options(path).connect().await?;
    MIGRATOR.run(&mut conn).await?;
    let mut tx = conn.begin().await?;
    let mut link_ids = Vec::with_capacity(link_names.len());
    for name in link_names {
        sqlx::query(
            "insert into links (name, created_ns) values (?, ?) on conflict (name) do nothing",
        )
        .bind(name)
        .bind(now_ns)
        .execute(&mut *tx)
        .await?;
        let (id,): (i64,) = sqlx::query_as("select link_id from links where name = ?")
            .bind(name)
            .fetch_one(&mut *tx)
            .await?;
        link_ids.push(id);
    }
    let mut target_ids = Vec::with_capacity(target_names.len());
    for name in target_names {
        sqlx::query(
            "insert into targets (name, created_ns) values (?, ?) on conflict (name) do nothing",
        )
        .bind(name)
        .bind(now_ns)
        .execute(&mut *tx)
        .await?;
        let (id,): (i64,) = sqlx::query_as("select target_id from targets where name = ?")
            .bind(name)
            .fetch_one(&mut *tx)
            .await?;
        target_ids.push(id);
    }
    tx.commit().await?;
    let pool = SqlitePoolOptions::new()
        .max_connections(4)
        .connect_with(options(path).read_only(true))
        .await?;
    Ok((
        Store {
            pool,
            path: path.to_owned(),
            link_ids: link_ids.clone(),
            target_ids: target_ids.clone(),
        },
        WriteConn::new(conn, link_ids, target_ids),
    ))
}

impl Store {
    /// The database file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// True when the database answers a trivial query.
    pub async fn ping(&self) -> bool {
        sqlx::query("select 1").execute(&self.pool).await.is_ok()
    }

    /// Closes the read pool.
    pub async fn close(&self) {
        self.pool.close().await;
    }
}

/// Writes a consistent copy of the database at `database` to `out` while the service may be
/// writing to it (`VACUUM INTO` reads one snapshot; WAL lets the writer go on). Refuses to
/// overwrite `out`. Returns the copy's size in bytes.
pub async fn backup(database: &Path, out: &Path) -> StoreResult<u64> {
    if out.exists() {
        return Err(StoreError::Malformed(format!(
            "{} already exists; a backup never overwrites a file",
            out.display()
        )));
    }
    if !database.exists() {
        return Err(StoreError::Malformed(format!(
            "no database at {}",
            database.display()
        )));
    }
    let mut conn = SqliteConnectOptions::new()
        .filename(database)
        .busy_timeout(Duration::from_secs(30))
        .connect()
        .await?;
    sqlx::query("vacuum into ?")
        .bind(out.to_string_lossy().into_owned())
        .execute(&mut conn)
        .await?;
    conn.close().await?;
    Ok(std::fs::metadata(out).map(|m| m.len()).unwrap_or(0))
}
