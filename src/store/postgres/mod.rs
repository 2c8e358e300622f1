//! The PostgreSQL backend: a server database for a centre, or for an installation whose
//! history outgrows one file.
//!
//! Reads go through a pool (at most 8 connections; a request waits at most 5 s for one, so
//! while the server is down requests answer 503 instead of hanging). The writer is one
//! connection of its own (`Writer`). The schema (`migrations-postgres/`) partitions samples,
//! results and rollups into days with pg_partman; `maintain` makes the coming days'
//! partitions and moves rows that landed in the default partition (a backfill, a restart after
//! a long stop) into their own, at start-up and with each retention pass.

pub(crate) mod central;

mod write;

pub(super) use write::{Tx, Writer};

use super::{StoreError, StoreResult};
use crate::config::PostgresUrl;
use sqlx::postgres::{PgConnectOptions, PgConnection, PgPool, PgPoolOptions};
use sqlx::{ConnectOptions, Connection};
use std::str::FromStr;
use std::time::Duration;

/// How long a connection attempt may take before the server counts as unreachable.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);

/// The advisory lock the writer holds ("BRRY"): one writer per database.
const WRITER_LOCK: i64 = 0x4252_5259;

/// The tables partitioned by time.
const PARTITIONED: [&str; 3] = ["samples", "results", "rollups"];

/// The read side of a PostgreSQL database.
#[derive(Debug, Clone)]
pub(super) struct Reader {
    pub(in crate::store) pool: PgPool,
    /// A connection of its own for the health check, so that busy readers cannot fail it.
    health_conn: std::sync::Arc<tokio::sync::Mutex<Option<PgConnection>>>,
    options: std::sync::Arc<PgConnectOptions>,
}

/// The connection options of a URL, quiet (statements are not logged one by one).
fn options_of(url: &PostgresUrl) -> StoreResult<PgConnectOptions> {
    let options = PgConnectOptions::from_str(url.secret()).map_err(|e| StoreError::Open {
        database: url.to_string(),
        message: format!("the URL does not parse: {e}"),
    })?;
    Ok(options
        .application_name("brokenray")
        .disable_statement_logging())
}

/// Opens the database at `url`: connects (refusing clearly when the server is down, the
/// credentials are wrong, the database does not exist), applies the migrations (refusing when
/// the role may not), takes the writer's lock, makes the coming partitions and registers the
/// names of the installation's links and targets. Returns the read side, the writer and the
/// database ids of the links and targets.
pub(super) async fn open(
    url: &PostgresUrl,
    link_names: &[&String],
    target_names: &[&String],
    now_ns: i64,
) -> StoreResult<(Reader, Writer, Vec<i64>, Vec<i64>)> {
    let options = options_of(url)?;
    let refused = |step: &str, e: StoreError| StoreError::Open {
        database: url.to_string(),
        message: format!("{step}: {e}"),
    };
    let mut conn = Writer::connect(&options).await.map_err(|e| match e {
        StoreError::WriterLocked => refused("cannot write", e),
        e => refused("cannot connect", e),
    })?;
    if let Err(e) = super::migrations::POSTGRES.run(&mut conn).await {
        release_lock(conn).await;
        return Err(refused(
            "cannot prepare the schema (the role needs to create tables in the database, and \
             the pg_partman extension must be installed, or the role allowed to create it)",
            e.into(),
        ));
    }
    let ready = async {
        maintain(&mut conn).await?;
        let mut link_ids = Vec::with_capacity(link_names.len());
        for name in link_names {
            link_ids.push(register(&mut conn, "links", "link_id", name, now_ns).await?);
        }
        let mut target_ids = Vec::with_capacity(target_names.len());
        for name in target_names {
            target_ids.push(register(&mut conn, "targets", "target_id", name, now_ns).await?);
        }
        let pool = PgPoolOptions::new()
            .max_connections(8)
            .acquire_timeout(CONNECT_TIMEOUT)
            .connect_with(options.clone())
            .await?;
        StoreResult::Ok((link_ids, target_ids, pool))
    };
    let (link_ids, target_ids, pool) = match ready.await {
        Ok(ready) => ready,
        Err(e) => {
            release_lock(conn).await;
            return Err(refused("cannot prepare the database", e));
        }
    };
    Ok((
        Reader {
            pool,
            health_conn: std::sync::Arc::new(tokio::sync::Mutex::new(None)),
            options: std::sync::Arc::new(options.clone()),
        },
        Writer::new(conn, &options),
        link_ids,
        target_ids,
    ))
}

/// Gives back the locks of a start-up that failed after taking them (the writer's, and the
/// migrations' own when they failed holding it), before closing its connection: dropped, the
/// connection would keep them until the server noticed, and a start-up right after (a
/// supervisor's restart) would be refused as a second writer.
async fn release_lock(mut conn: PgConnection) {
    let _ = sqlx::query("rollback").execute(&mut conn).await;
    let _ = sqlx::query("select pg_advisory_unlock_all()")
        .execute(&mut conn)
        .await;
    let _ = conn.close().await;
}

/// Opens the database at `url` for reading only (while a service writes to it): no
/// migration, no writer's lock. The installation's links and targets must be registered
/// (the service does so when it starts).
pub(super) async fn open_reader(
    url: &PostgresUrl,
    link_names: &[&String],
    target_names: &[&String],
) -> StoreResult<(Reader, Vec<i64>, Vec<i64>)> {
    let options = options_of(url)?;
    let refused = |message: String| StoreError::Open {
        database: url.to_string(),
        message,
    };
    let pool = PgPoolOptions::new()
        .max_connections(4)
        .acquire_timeout(CONNECT_TIMEOUT)
        .connect_with(options.clone())
        .await
        .map_err(|e| refused(format!("cannot connect: {e}")))?;
    let mut link_ids = Vec::with_capacity(link_names.len());
    for name in link_names {
        link_ids.push(
            registered(&pool, "links", "link_id", name)
                .await
                .map_err(refused)?,
        );
    }
    let mut target_ids = Vec::with_capacity(target_names.len());
    for name in target_names {
        target_ids.push(
            registered(&pool, "targets", "target_id", name)
                .await
                .map_err(refused)?,
        );
    }
    Ok((
        Reader {
            pool,
            health_conn: std::sync::Arc::new(tokio::sync::Mutex::new(None)),
            options: std::sync::Arc::new(options),
        },
        link_ids,
        target_ids,
    ))
}

/// The id of a registered link or target; a message when there is none.
async fn registered(
    pool: &PgPool,
    table: &str,
    id_column: &str,
    name: &str,
) -> Result<i64, String> {
    let row: Option<(i64,)> =
        sqlx::query_as(&format!("select {id_column} from {table} where name = $1"))
            .bind(name)
            .fetch_optional(pool)
            .await
            .map_err(|e| format!("cannot read {table}: {e}"))?;
    row.map(|(id,)| id).ok_or_else(|| {
        format!(
            "it holds no `{name}` in {table}: the service registers the installation's names \
             when it starts on this database"
        )
    })
}

/// The id of a link or target by name, registering it when new.
async fn register(
    conn: &mut PgConnection,
    table: &str,
    id_column: &str,
    name: &str,
    now_ns: i64,
) -> StoreResult<i64> {
    sqlx::query(&format!(
        "insert into {table} (name, created_ns) values ($1, $2) on conflict (name) do nothing"
    ))
    .bind(name)
    .bind(now_ns)
    .execute(&mut *conn)
    .await?;
    let (id,): (i64,) = sqlx::query_as(&format!("select {id_column} from {table} where name = $1"))
        .bind(name)
        .fetch_one(&mut *conn)
        .await?;
    Ok(id)
}

/// `schema.table` of one of the schema's tables, as pg_partman names it.
async fn qualified(conn: &mut PgConnection, table: &str) -> StoreResult<String> {
    let (name,): (String,) = sqlx::query_as("select format('%s.%s', current_schema(), $1::text)")
        .bind(table)
        .fetch_one(&mut *conn)
        .await?;
    Ok(name)
}

/// Partition upkeep: rows in a default partition are moved into partitions of their own
/// (made as needed), then pg_partman makes the partitions of the coming days.
async fn maintain(conn: &mut PgConnection) -> StoreResult<()> {
    for table in PARTITIONED {
        let parent = qualified(&mut *conn, table).await?;
        let (stray,): (bool,) =
            sqlx::query_as(&format!("select exists (select 1 from {table}_default)"))
                .fetch_one(&mut *conn)
                .await?;
        if stray {
            let (moved,): (i64,) = sqlx::query_as(
                "select partman.partition_data_id($1, p_batch_count => 100000, p_analyze => false)",
            )
            .bind(&parent)
            .fetch_one(&mut *conn)
            .await?;
            // pg_partman keeps the moved rows in a temporary table shaped like this parent,
            // dropped only at commit: gone now, so that the next parent gets its own.
            sqlx::query("drop table if exists pg_temp.partman_temp_data_storage")
                .execute(&mut *conn)
                .await?;
            tracing::info!(table, moved, "rows moved out of the default partition");
        }
        sqlx::query("select partman.run_maintenance($1, p_jobmon => false)")
            .bind(&parent)
            .execute(&mut *conn)
            .await?;
    }
    Ok(())
}

/// Removes the rows of `table` (partitioned on `time_ns`) before `cutoff_ns`: whole daily
/// partitions that end before it are dropped, the rest deleted. Returns how many went.
pub(super) async fn drop_before(
    conn: &mut PgConnection,
    table: &str,
    cutoff_ns: i64,
) -> StoreResult<u64> {
    let parent = qualified(&mut *conn, table).await?;
    let children: Vec<(String, i64)> = sqlx::query_as(
        "select format('%I.%I', p.partition_schemaname, p.partition_tablename), i.child_end_id \
         from partman.show_partitions($1) p, \
         lateral partman.show_partition_info(format('%I.%I', p.partition_schemaname, \
         p.partition_tablename), p_parent_table => $1) i",
    )
    .bind(&parent)
    .fetch_all(&mut *conn)
    .await?;
    let mut gone = 0u64;
    for (child, last_ns) in children {
        if last_ns < cutoff_ns {
            let (n,): (i64,) = sqlx::query_as(&format!("select count(*) from {child}"))
                .fetch_one(&mut *conn)
                .await?;
            sqlx::query(&format!("drop table {child}"))
                .execute(&mut *conn)
                .await?;
            gone += u64::try_from(n).unwrap_or(0);
        }
    }
    gone += sqlx::query(&format!("delete from {table} where time_ns < $1"))
        .bind(cutoff_ns)
        .execute(&mut *conn)
        .await?
        .rows_affected();
    Ok(gone)
}

impl Reader {
    /// What is wrong with the database, on the health check's own connection: it must answer
    /// a query within 2 s.
    pub(super) async fn problem(&self) -> Option<String> {
        let mut guard = self.health_conn.lock().await;
        if guard.is_none() {
            match tokio::time::timeout(CONNECT_TIMEOUT, self.options.connect()).await {
                Ok(Ok(conn)) => *guard = Some(conn),
                Ok(Err(e)) => return Some(format!("cannot connect to PostgreSQL: {e}")),
                Err(_) => return Some("PostgreSQL did not answer within 5 s".to_owned()),
            }
        }
        let conn = guard.as_mut()?;
        let problem = super::probe(sqlx::query("select 1").execute(conn)).await;
        if problem.is_some() {
            *guard = None;
        }
        problem
    }

    /// Closes the read pool and the health connection.
    pub(super) async fn close(&self) {
        self.pool.close().await;
        if let Some(conn) = self.health_conn.lock().await.take() {
            let _ = conn.close().await;
        }
    }
}

/// Writes a `pg_dump` archive (custom format: one consistent snapshot, restored with
/// `pg_restore`) of the database to `out` while the service may be writing. Refuses to
/// overwrite `out`; the password goes to `pg_dump` in its environment, not on its command
/// line. Returns the archive's size in bytes.
pub(super) async fn backup(url: &PostgresUrl, out: &std::path::Path) -> StoreResult<u64> {
    if out.exists() {
        return Err(StoreError::Backup(format!(
            "{} already exists; a backup never overwrites a file",
            out.display()
        )));
    }
    let mut public = url::Url::parse(url.secret())
        .map_err(|e| StoreError::Backup(format!("the database URL does not parse: {e}")))?;
    let password = public.password().map(str::to_owned);
    let _ = public.set_password(None);
    let mut command = tokio::process::Command::new("pg_dump");
    command
        .arg("--format=custom")
        .arg("--file")
        .arg(out)
        .arg("--dbname")
        .arg(public.as_str());
    if let Some(password) = password {
        command.env("PGPASSWORD", password);
    }
    let output = command.output().await.map_err(|e| {
        StoreError::Backup(format!(
            "cannot run pg_dump ({e}); install PostgreSQL's client programs"
        ))
    })?;
    if !output.status.success() {
        let _ = std::fs::remove_file(out);
        return Err(StoreError::Backup(format!(
            "pg_dump failed: {}",
            String::from_utf8_lossy(&output.stderr).trim()
        )));
    }
    Ok(std::fs::metadata(out).map(|m| m.len()).unwrap_or(0))
}
