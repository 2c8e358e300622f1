//! The SQLite backend: one file, WAL mode, `synchronous = FULL`.
//!
//! A commit is on disk before it returns, so what the service acknowledges survives a crash or
//! a power cut. Reads go through a pool of read-only connections; all writes go through the
//! one `Writer`. The file's identity (device and inode) is checked around every commit, so a
//! file deleted or replaced under the service is reported instead of written to in silence.

mod outbox;
mod read;
mod wal;
mod write;

pub(super) use write::{Tx, Writer};

use super::{StoreError, StoreResult};
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous,
};
use sqlx::{ConnectOptions, Connection};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// The SQLite `application_id` of a brokenray database ("BRRY"): a file with another id is
/// another program's and is never migrated into.
pub const APPLICATION_ID: i64 = 0x4252_5259;

/// Device and inode of a file: the identity the open database must keep.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct FileIdentity {
    dev: u64,
    ino: u64,
}

impl FileIdentity {
    /// The identity of the file at `path`, or `None` when there is none.
    pub(crate) fn of(path: &Path) -> Option<FileIdentity> {
        let meta = std::fs::metadata(path).ok()?;
        #[cfg(unix)]
        {
            use std::os::unix::fs::MetadataExt;
            Some(FileIdentity {
                dev: meta.dev(),
                ino: meta.ino(),
            })
        }
        #[cfg(not(unix))]
        {
            let _ = meta;
            Some(FileIdentity { dev: 0, ino: 0 })
        }
    }
}

/// Fails unless the file at `path` is still the one with `identity`.
pub(crate) fn check_identity(path: &Path, identity: FileIdentity) -> StoreResult<()> {
    if FileIdentity::of(path) == Some(identity) {
        Ok(())
    } else {
        Err(StoreError::FileReplaced {
            path: path.to_owned(),
        })
    }
}

/// The read side of an SQLite database.
#[derive(Debug, Clone)]
pub(super) struct Reader {
    pub(in crate::store) pool: SqlitePool,
    /// A connection of its own for the health check, so that busy readers cannot fail it.
    health_conn: std::sync::Arc<tokio::sync::Mutex<Option<sqlx::SqliteConnection>>>,
    path: PathBuf,
    identity: FileIdentity,
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

/// Refuses a file that is another program's SQLite database, and marks a new (or an older
/// brokenray) database with [`APPLICATION_ID`].
async fn claim(conn: &mut sqlx::SqliteConnection, path: &Path) -> StoreResult<()> {
    let (id,): (i64,) = sqlx::query_as("pragma application_id")
        .fetch_one(&mut *conn)
        .await?;
    if id == APPLICATION_ID {
        return Ok(());
    }
    let tables: Vec<(String,)> = sqlx::query_as(
        "select name from sqlite_master where type = 'table' and name not like 'sqlite_%'",
    )
    .fetch_all(&mut *conn)
    .await?;
    let names: std::collections::HashSet<&str> = tables.iter().map(|(n,)| n.as_str()).collect();
    // A brokenray database written before the id was set has these.
    let ours = ["_sqlx_migrations", "samples", "results", "filter_state"]
        .iter()
        .all(|t| names.contains(t));
    if id != 0 || !(names.is_empty() || ours) {
        return Err(StoreError::Foreign {
            path: path.to_owned(),
        });
    }
    sqlx::query(&format!("pragma application_id = {APPLICATION_ID}"))
        .execute(&mut *conn)
        .await?;
    Ok(())
}

/// Opens (creating if needed) the SQLite file, applies migrations and registers the names of
/// the installation's links and targets. Returns the read side, the one write connection and
/// the database ids of the links and targets. Every error names the file.
pub(super) async fn open(
    path: &Path,
    link_names: &[&String],
    target_names: &[&String],
    now_ns: i64,
) -> StoreResult<(Reader, Writer, Vec<i64>, Vec<i64>)> {
    let opened = open_inner(path, link_names, target_names, now_ns).await;
    opened.map_err(|e| match e {
        e @ (StoreError::Foreign { .. } | StoreError::Open { .. }) => e,
        other => StoreError::Open {
            database: path.display().to_string(),
            message: other.to_string(),
        },
    })
}

async fn open_inner(
    path: &Path,
    link_names: &[&String],
    target_names: &[&String],
    now_ns: i64,
) -> StoreResult<(Reader, Writer, Vec<i64>, Vec<i64>)> {
    // Opening replays the write-ahead log up to its first damaged frame and says nothing of
    // what lies past it: look first, and say it.
    match wal::inspect(path) {
        Some(r) if r.lost_commits > 0 || r.lost_frames > 0 => tracing::error!(
            database = %path.display(),
            replayed_commits = r.replayed_commits,
            lost_commits = r.lost_commits,
            lost_frames = r.lost_frames,
            "the database's write-ahead log is damaged: {} commit(s) after the first {} are \
             lost (acknowledged writes among them); the database opens with what precedes the \
             damage",
            r.lost_commits,
            r.replayed_commits
        ),
        Some(r) if r.replayed_commits > 0 => tracing::info!(
            database = %path.display(),
            commits = r.replayed_commits,
            frames = r.replayed_frames,
            "replaying the write-ahead log left by the last run"
        ),
        _ => {}
    }
    let mut conn = options(path).connect().await?;
    claim(&mut conn, path).await?;
    super::migrations::SQLITE.run(&mut conn).await?;
    let identity = FileIdentity::of(path).ok_or_else(|| StoreError::Open {
        database: path.display().to_string(),
        message: "the file vanished while it was opened".into(),
    })?;
    let mut tx = conn.begin().await?;
    let mut link_ids = Vec::with_capacity(link_names.len());
    for name in link_names.iter().copied() {
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
    for name in target_names.iter().copied() {
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
    let health_conn = options(path).read_only(true).connect().await?;
    Ok((
        Reader {
            pool,
            health_conn: std::sync::Arc::new(tokio::sync::Mutex::new(Some(health_conn))),
            path: path.to_owned(),
            identity,
        },
        Writer::new(conn, path, identity),
        link_ids,
        target_ids,
    ))
}

impl Reader {
    /// What is wrong with the database, on the health check's own connection: the configured
    /// file must still be the one open and answer a query.
    pub(super) async fn problem(&self) -> Option<String> {
        let file_problem = check_identity(&self.path, self.identity)
            .err()
            .map(|e| e.to_string());
        let query_problem = {
            let mut guard = self.health_conn.lock().await;
            if guard.is_none() {
                *guard = options(&self.path)
                    .create_if_missing(false)
                    .read_only(true)
                    .connect()
                    .await
                    .ok();
            }
            match guard.as_mut() {
                None => Some(format!("cannot open {}", self.path.display())),
                Some(conn) => {
                    let problem = super::probe(
                        sqlx::query("select count(*) from sqlite_master").execute(&mut *conn),
                    )
                    .await;
                    if problem.is_some() {
                        *guard = None;
                    }
                    problem
                }
            }
        };
        file_problem.or(query_problem)
    }

    /// Closes the read pool and the health connection.
    pub(super) async fn close(&self) {
        self.pool.close().await;
        if let Some(conn) = self.health_conn.lock().await.take() {
            let _ = conn.close().await;
        }
    }
}

/// Writes a consistent copy of the database at `database` to `out` while the service may be
/// writing to it (`VACUUM INTO` reads one snapshot; WAL lets the writer go on). Refuses to
/// overwrite `out`. Returns the copy's size in bytes.
pub(super) async fn backup(database: &Path, out: &Path) -> StoreResult<u64> {
    if out.exists() {
        return Err(StoreError::Backup(format!(
            "{} already exists; a backup never overwrites a file",
            out.display()
        )));
    }
    if !database.exists() {
        return Err(StoreError::Backup(format!(
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
    // The copy is another life of the outbox once restored: a generation of its own.
    new_generation(out).await?;
    Ok(std::fs::metadata(out).map(|m| m.len()).unwrap_or(0))
}

/// Starts a new outbox generation in the brokenray database at `path` (which must exist),
/// migrating it first.
pub(super) async fn new_generation(path: &Path) -> StoreResult<super::outbox::OutboxIdentity> {
    if !path.exists() {
        return Err(StoreError::Backup(format!(
            "no database at {}",
            path.display()
        )));
    }
    let mut conn = options(path).create_if_missing(false).connect().await?;
    claim(&mut conn, path).await?;
    super::migrations::SQLITE.run(&mut conn).await?;
    let mut tx = conn.begin().await?;
    let identity = outbox::start_generation(&mut tx).await?;
    tx.commit().await?;
    conn.close().await?;
    Ok(identity)
}

#[cfg(test)]
mod tests {
    /// The migration that gives alarms ids keeps every row and its values, numbers them in time
    /// order, and leaves them unacknowledged.
    #[test]
    fn alarm_ids_are_given_to_existing_rows_in_time_order() {
        let db = rusqlite::Connection::open_in_memory().expect("memory database");
        for sql in [
            include_str!("../../../migrations/0001_initial.sql"),
            include_str!("../../../migrations/0002_rollups.sql"),
            include_str!("../../../migrations/0003_alarms.sql"),
            include_str!("../../../migrations/0004_alarm_units.sql"),
            include_str!("../../../migrations/0005_link_resets.sql"),
        ] {
            db.execute_batch(sql).expect("older migration");
        }
        db.execute_batch(
            "insert into targets values (1, 'G', 0), (2, 'H', 0);
             insert into alarms (target_id, time_ns, kind, from_level, to_level, value, message, created_ns, unit) values
               (2, 300, 'rate', 'none', 'alarm', 40.5, 'c', 9, 'mm_per_s'),
               (1, 100, 'deformation', 'none', 'warn', 61.0, 'a', 7, null),
               (1, 200, 'stale', 'none', 'alarm', 0.0, 'b', 8, 'none');",
        )
        .expect("old rows");
        db.execute_batch(include_str!(
            "../../../migrations/0006_alarm_ids_and_acks.sql"
        ))
        .expect("migration 0006");
        let mut q = db
            .prepare(
                "select alarm_id, target_id, time_ns, kind, value, unit, message, created_ns, \
                 acknowledged_by, acknowledged_ns, ack_note from alarms order by alarm_id",
            )
            .expect("query");
        type Row = (
            i64,
            i64,
            i64,
            String,
            f64,
            Option<String>,
            String,
            i64,
            Option<String>,
            Option<i64>,
            Option<String>,
        );
        let rows: Vec<Row> = q
            .query_map([], |r| {
                Ok((
                    r.get(0)?,
                    r.get(1)?,
                    r.get(2)?,
                    r.get(3)?,
                    r.get(4)?,
                    r.get(5)?,
                    r.get(6)?,
                    r.get(7)?,
                    r.get(8)?,
                    r.get(9)?,
                    r.get(10)?,
                ))
            })
            .expect("rows")
            .collect::<Result<_, _>>()
            .expect("readable");
        let times: Vec<i64> = rows.iter().map(|r| r.2).collect();
        assert_eq!(times, [100, 200, 300]);
        let ids: Vec<i64> = rows.iter().map(|r| r.0).collect();
        assert!(ids.windows(2).all(|w| w[0] < w[1]), "{ids:?}");
        assert_eq!(
            (
                rows[2].1,
                rows[2].3.as_str(),
                rows[2].4,
                rows[2].5.as_deref()
            ),
            (2, "rate", 40.5, Some("mm_per_s"))
        );
        assert_eq!(
            (rows[0].5.as_deref(), rows[0].6.as_str(), rows[0].7),
            (None, "a", 7)
        );
        assert!(
            rows.iter()
                .all(|r| r.8.is_none() && r.9.is_none() && r.10.is_none())
        );
        // The old key stays unique.
        let again = db.execute(
            "insert into alarms (target_id, time_ns, kind, from_level, to_level, value, message, created_ns) \
             values (1, 100, 'deformation', 'warn', 'none', 1.0, 'd', 10)",
            [],
        );
        assert!(again.is_err(), "the (target, time, kind) key is unique");
    }
}
