//! The site's outbox on SQLite: batches of a tier's rows in commit order, what the centre
//! acknowledged, the backlog. Reads run in one read transaction each, so a batch is one
//! consistent snapshot.

use super::super::StoreResult;
use super::super::outbox::{
    Backlog, ColumnValues, HexBytes, LINEAGE_KEPT, OutboxBatch, OutboxIdentity, PartCursor,
    Registered, Registry, SyncTable, TableRows, Tier,
};
use super::Reader;
use sqlx::sqlite::SqliteRow;
use sqlx::{Row, SqliteConnection};

/// The outbox's identity and generation, read on `conn`.
async fn identity(conn: &mut SqliteConnection) -> StoreResult<OutboxIdentity> {
    let (outbox_id, generation, lineage): (String, String, String) =
        sqlx::query_as("select outbox_id, generation, lineage from outbox where id = 1")
            .fetch_one(&mut *conn)
            .await?;
    Ok(OutboxIdentity {
        outbox_id,
        generation,
        lineage: lineage
            .split(',')
            .filter(|g| !g.is_empty())
            .map(str::to_owned)
            .collect(),
    })
}

/// Starts a new generation of the outbox in the database on `conn`: a new random name, the
/// current one first in the lineage (which keeps [`LINEAGE_KEPT`] names). Returns the new
/// identity.
pub(super) async fn start_generation(conn: &mut SqliteConnection) -> StoreResult<OutboxIdentity> {
    let old = identity(conn).await?;
    let mut lineage = vec![old.generation.clone()];
    lineage.extend(old.lineage.iter().cloned());
    lineage.truncate(LINEAGE_KEPT);
    sqlx::query(
        "update outbox set generation = lower(hex(randomblob(16))), lineage = ? where id = 1",
    )
    .bind(lineage.join(","))
    .execute(&mut *conn)
    .await?;
    identity(conn).await
}

/// Appends one row's values to the columns of `rows`.
fn push_row(rows: &mut TableRows, row: &SqliteRow) -> StoreResult<()> {
    for (i, values) in rows.columns.iter_mut().enumerate() {
        match values {
            ColumnValues::Int(v) => v.push(row.try_get(i)?),
            ColumnValues::Real(v) => v.push(row.try_get(i)?),
            ColumnValues::Text(v) => v.push(row.try_get(i)?),
            ColumnValues::Blob(v) => v.push(row.try_get::<Option<Vec<u8>>, _>(i)?.map(HexBytes)),
            ColumnValues::Bool(v) => v.push(row.try_get(i)?),
        }
    }
    Ok(())
}

/// `select <columns>, commit_seq from <table> where <filter> and commit_seq > ? ...`.
fn select(table: SyncTable, condition: &str) -> String {
    let columns: Vec<&str> = table.columns().iter().map(|(n, _)| *n).collect();
    let filter = table
        .filter()
        .map_or(String::new(), |f| format!("{f} and "));
    format!(
        "select {}, commit_seq from {} where {filter}{condition} order by commit_seq",
        columns.join(", "),
        table.table()
    )
}

/// The rows of `table` written by the commits `(after, upto]`, at most `limit + 1` of them.
async fn rows_between(
    conn: &mut SqliteConnection,
    table: SyncTable,
    after: i64,
    upto: i64,
    limit: usize,
) -> StoreResult<Vec<SqliteRow>> {
    Ok(sqlx::query(&format!(
        "{} limit ?",
        select(table, "commit_seq > ? and commit_seq <= ?")
    ))
    .bind(after)
    .bind(upto)
    .bind(i64::try_from(limit + 1).unwrap_or(i64::MAX))
    .fetch_all(&mut *conn)
    .await?)
}

/// The key of a row of `table`, as its integers.
fn key_of(table: SyncTable, row: &SqliteRow) -> StoreResult<Vec<i64>> {
    table
        .key()
        .iter()
        .map(|k| Ok(row.try_get::<i64, _>(*k)?))
        .collect()
}

/// The rows of one commit `seq` of `table` after the key `after_key` (all of them when
/// `None`), in key order, at most `limit` of them.
async fn commit_rows(
    conn: &mut SqliteConnection,
    table: SyncTable,
    seq: i64,
    after_key: Option<&[i64]>,
    limit: usize,
) -> StoreResult<Vec<SqliteRow>> {
    let key = table.key().join(", ");
    let mut condition = "commit_seq = ?".to_owned();
    if after_key.is_some() {
        let marks = vec!["?"; table.key().len()].join(", ");
        condition.push_str(&format!(" and ({key}) > ({marks})"));
    }
    let columns: Vec<&str> = table.columns().iter().map(|(n, _)| *n).collect();
    let filter = table
        .filter()
        .map_or(String::new(), |f| format!("{f} and "));
    let sql = format!(
        "select {}, commit_seq from {} where {filter}{condition} order by {key} limit ?",
        columns.join(", "),
        table.table()
    );
    let mut query = sqlx::query(&sql).bind(seq);
    for k in after_key.unwrap_or(&[]) {
        query = query.bind(*k);
    }
    Ok(query
        .bind(i64::try_from(limit).unwrap_or(i64::MAX))
        .fetch_all(&mut *conn)
        .await?)
}

/// When the commit `seq` was made (`None`: its record is gone, pruned with old rows).
async fn stamp_of(conn: &mut SqliteConnection, seq: i64) -> StoreResult<Option<i64>> {
    let stamp: Option<(i64,)> = sqlx::query_as("select created_ns from commits where seq = ?")
        .bind(seq)
        .fetch_optional(&mut *conn)
        .await?;
    Ok(stamp.map(|(s,)| s))
}

/// One part of the commit `from.seq` of `tier`: at most `limit` rows from `from` on, and
/// where the next part starts (`None`: this is its last).
async fn commit_part(
    conn: &mut SqliteConnection,
    tier: Tier,
    from: &PartCursor,
    limit: usize,
) -> StoreResult<(Vec<TableRows>, Option<PartCursor>)> {
    let limit = limit.max(1);
    let mut tables = Vec::new();
    let mut taken = 0usize;
    for (index, &table) in tier.tables().iter().enumerate().skip(from.table) {
        let after_key = (index == from.table)
            .then_some(from.after_key.as_deref())
            .flatten();
        let room = limit - taken;
        // One row more than there is room for tells whether the table has more.
        let rows = commit_rows(conn, table, from.seq, after_key, room + 1).await?;
        if rows.is_empty() {
            continue;
        }
        if room == 0 {
            return Ok((
                tables,
                Some(PartCursor {
                    seq: from.seq,
                    table: index,
                    after_key: after_key.map(<[i64]>::to_vec),
                }),
            ));
        }
        let mut out = TableRows::new(table);
        for row in rows.iter().take(room) {
            push_row(&mut out, row)?;
        }
        taken += out.rows();
        tables.push(out);
        if rows.len() > room {
            let last = key_of(table, &rows[room - 1])?;
            return Ok((
                tables,
                Some(PartCursor {
                    seq: from.seq,
                    table: index,
                    after_key: Some(last),
                }),
            ));
        }
    }
    Ok((tables, None))
}

impl Reader {
    /// The next batch of `tier` after the commit `after`: whole commits, about `limit` rows,
    /// `None` when nothing is waiting. A commit that alone holds more than `limit` rows goes
    /// in parts of `limit` rows: `part` says where the next one starts, and the batch returned
    /// with a batch says where the one after it does (`None`: the batch ends a commit).
    pub(in crate::store) async fn outbox_batch(
        &self,
        tier: Tier,
        after: i64,
        limit: usize,
        part: Option<&PartCursor>,
    ) -> StoreResult<Option<(OutboxBatch, Option<PartCursor>)>> {
        let limit = limit.max(1);
        let mut tx = self.pool.begin().await?;
        if let Some(from) = part {
            let (tables, rest) = commit_part(&mut tx, tier, from, limit).await?;
            let batch = OutboxBatch {
                tier,
                after_seq: after,
                upto_seq: from.seq,
                partial: rest.is_some(),
                upto_stamp_ns: stamp_of(&mut tx, from.seq).await?,
                tables,
            };
            tx.rollback().await?;
            return Ok(Some((batch, rest)));
        }
        let (head,): (Option<i64>,) = sqlx::query_as("select max(seq) from commits")
            .fetch_one(&mut *tx)
            .await?;
        // Rows from before the outbox carry negative numbers: the head is at least 0.
        let head = head.unwrap_or(0).max(0);
        if head <= after {
            return Ok(None);
        }
        let mut fetched = Vec::new();
        let mut upto = head;
        // The first commit with rows, and one that alone holds more than `limit` rows.
        let mut first_seq = i64::MAX;
        let mut large = None;
        for &table in tier.tables() {
            let rows = rows_between(&mut tx, table, after, head, limit).await?;
            if let Some(row) = rows.first() {
                first_seq = first_seq.min(row.try_get("commit_seq")?);
            }
            if rows.len() > limit {
                let last: i64 = rows[limit].try_get("commit_seq")?;
                let first: i64 = rows[0].try_get("commit_seq")?;
                if first == last {
                    large = Some(large.map_or(first, |l: i64| l.min(first)));
                    upto = upto.min(first);
                } else {
                    upto = upto.min(last - 1);
                }
            }
            fetched.push((table, rows));
        }
        if let Some(seq) = large
            && seq <= upto
        {
            if first_seq < seq {
                // Whole commits before the large one go first.
                upto = seq - 1;
            } else {
                // The large commit is the first waiting: its first part.
                drop(fetched);
                let from = PartCursor {
                    seq,
                    table: 0,
                    after_key: None,
                };
                let (tables, rest) = commit_part(&mut tx, tier, &from, limit).await?;
                let batch = OutboxBatch {
                    tier,
                    after_seq: after,
                    upto_seq: seq,
                    partial: rest.is_some(),
                    upto_stamp_ns: stamp_of(&mut tx, seq).await?,
                    tables,
                };
                tx.rollback().await?;
                return Ok(Some((batch, rest)));
            }
        }
        let mut tables = Vec::new();
        for (table, rows) in fetched {
            let mut out = TableRows::new(table);
            for row in &rows {
                let seq: i64 = row.try_get("commit_seq")?;
                if seq <= upto {
                    push_row(&mut out, row)?;
                }
            }
            if out.rows() > 0 {
                tables.push(out);
            }
        }
        let upto_stamp_ns = stamp_of(&mut tx, upto).await?;
        tx.rollback().await?;
        Ok((!tables.is_empty()).then_some((
            OutboxBatch {
                tier,
                after_seq: after,
                upto_seq: upto,
                partial: false,
                upto_stamp_ns,
                tables,
            },
            None,
        )))
    }

    /// When the commit `seq` was made (the site's clock, ns); `None` when its record is gone.
    pub(in crate::store) async fn commit_stamp(&self, seq: i64) -> StoreResult<Option<i64>> {
        let mut conn = self.pool.acquire().await?;
        stamp_of(&mut conn, seq).await
    }

    /// The raw rows (samples and raw results) measured in `[from_ns, to_ns)`, in one
    /// snapshot; tables without a row are left out.
    pub(in crate::store) async fn raw_rows_in(
        &self,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<Vec<TableRows>> {
        let mut tx = self.pool.begin().await?;
        let mut tables = Vec::new();
        for &table in Tier::Raw.tables() {
            let rows = sqlx::query(&select(table, "time_ns >= ? and time_ns < ?"))
                .bind(from_ns)
                .bind(to_ns)
                .fetch_all(&mut *tx)
                .await?;
            let mut out = TableRows::new(table);
            for row in &rows {
                push_row(&mut out, row)?;
            }
            if out.rows() > 0 {
                tables.push(out);
            }
        }
        tx.rollback().await?;
        Ok(tables)
    }

    /// The earliest time of a raw row (sample or raw result) measured in `[from_ns, to_ns)`.
    pub(in crate::store) async fn next_raw_time(
        &self,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<Option<i64>> {
        let (next,): (Option<i64>,) = sqlx::query_as(
            "select min(t) from (select min(time_ns) as t from samples \
             where time_ns >= ?1 and time_ns < ?2 union all select min(time_ns) from results \
             where source = 0 and time_ns >= ?1 and time_ns < ?2)",
        )
        .bind(from_ns)
        .bind(to_ns)
        .fetch_one(&self.pool)
        .await?;
        Ok(next)
    }

    /// The raw rows (samples and raw results) measured in `[from_ns, to_ns)`, counted.
    pub(in crate::store) async fn count_raw_in(
        &self,
        from_ns: i64,
        to_ns: i64,
    ) -> StoreResult<u64> {
        let (n,): (i64,) = sqlx::query_as(
            "select (select count(*) from samples where time_ns >= ?1 and time_ns < ?2) + \
             (select count(*) from results where source = 0 and time_ns >= ?1 and time_ns < ?2)",
        )
        .bind(from_ns)
        .bind(to_ns)
        .fetch_one(&self.pool)
        .await?;
        Ok(u64::try_from(n).unwrap_or(0))
    }

    /// The names behind the ids of the site's rows.
    pub(in crate::store) async fn registry(&self) -> StoreResult<Registry> {
        let read = |sql: &'static str| async move {
            let rows: Vec<(i64, String, i64)> = sqlx::query_as(sql).fetch_all(&self.pool).await?;
            StoreResult::Ok(
                rows.into_iter()
                    .map(|(id, name, created_ns)| Registered {
                        id,
                        name,
                        created_ns,
                    })
                    .collect(),
            )
        };
        Ok(Registry {
            links: read("select link_id, name, created_ns from links order by link_id").await?,
            targets: read("select target_id, name, created_ns from targets order by target_id")
                .await?,
        })
    }

    /// The outbox's identity and generation.
    pub(in crate::store) async fn outbox_identity(&self) -> StoreResult<OutboxIdentity> {
        let mut conn = self.pool.acquire().await?;
        identity(&mut conn).await
    }

    /// The newest commit (0 before any).
    pub(in crate::store) async fn outbox_head(&self) -> StoreResult<i64> {
        let (head,): (Option<i64>,) = sqlx::query_as("select max(seq) from commits")
            .fetch_one(&self.pool)
            .await?;
        Ok(head.unwrap_or(0).max(0))
    }

    /// Per tier, the last number the centre acknowledged and the rows above it.
    pub(in crate::store) async fn backlog(&self) -> StoreResult<Vec<(Tier, Backlog)>> {
        let acks: Vec<(String, i64)> = sqlx::query_as("select tier, acked_seq from upstream_acks")
            .fetch_all(&self.pool)
            .await?;
        let mut out = Vec::new();
        for &tier in Tier::ALL {
            let acked_seq = acks.iter().find(|(t, _)| t == tier.name()).map(|(_, s)| *s);
            let mut rows = 0u64;
            for &table in tier.tables() {
                let filter = table
                    .filter()
                    .map_or(String::new(), |f| format!("{f} and "));
                let (n,): (i64,) = sqlx::query_as(&format!(
                    "select count(*) from {} where {filter}commit_seq > ?",
                    table.table()
                ))
                .bind(acked_seq.unwrap_or(i64::MIN))
                .fetch_one(&self.pool)
                .await?;
                rows += u64::try_from(n).unwrap_or(0);
            }
            out.push((tier, Backlog { acked_seq, rows }));
        }
        Ok(out)
    }
}

/// The type of a column, for the tests of the column lists against the schema.
#[cfg(test)]
fn sqlite_type(kind: super::super::outbox::Kind) -> &'static str {
    use super::super::outbox::Kind;
    match kind {
        Kind::Int | Kind::Bool => "integer",
        Kind::Real => "real",
        Kind::Text => "text",
        Kind::Blob => "blob",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every uploaded column exists in the SQLite schema with its type, and every column of
    /// the tables (but `commit_seq`) is uploaded: a migration that adds a column must add it
    /// to the upload too.
    #[tokio::test]
    async fn the_uploaded_columns_are_the_schemas() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("site.db");
        let (_reader, _writer, _, _) = super::super::open(&path, &[], &[], 0).await.unwrap();
        let mut conn = sqlx::ConnectOptions::connect(&super::super::options(&path))
            .await
            .unwrap();
        for &tier in Tier::ALL {
            for &table in tier.tables() {
                let schema: Vec<(String, String)> = sqlx::query_as(&format!(
                    "select name, lower(type) from pragma_table_info('{}') where name != 'commit_seq'",
                    table.table()
                ))
                .fetch_all(&mut conn)
                .await
                .unwrap();
                let uploaded: Vec<(String, String)> = table
                    .columns()
                    .iter()
                    .map(|(n, k)| ((*n).to_owned(), sqlite_type(*k).to_owned()))
                    .collect();
                let mut a = schema.clone();
                let mut b = uploaded.clone();
                a.sort();
                b.sort();
                assert_eq!(a, b, "{table:?}");
            }
        }
    }
}
