//! The centre of a fleet: sites' uploads applied exactly once, and the record of the fleet.
//!
//! Each site's rows live in a schema of their own, `site_<id>` (the id given to the site on its
//! first upload; pg_partman takes only plain identifiers, and names may hold `-`), made then
//! with the tables of `migrations-postgres/` (so every read of the store works on a site's copy
//! as on a service's own database). The schema `fleet` (`migrations-central/`) records the
//! sites, the outbox each uploads from, and per tier the last commit applied.
//!
//! An upload covers the site's commits `(after_seq, upto_seq]` of one tier. It is applied in
//! one transaction, with the tier's row locked, when it continues what was applied
//! (`after_seq <= acked < upto_seq`); rows replace those at the same keys, so an upload that
//! overlaps what was applied brings only the site's current versions. One that ends at or
//! before `acked` changes nothing (a replay, or one overtaken by a later upload); one that
//! starts after `acked` is refused with the number to resume from (a gap).
//!
//! Each generation of a site's outbox (a restored copy of its database starts one) is a stream
//! of its own, per tier. A generation's first batch of a tier continues the nearest ancestor
//! that has one: it may start anywhere up to that ancestor's acknowledged number (the copy
//! recorded those acknowledgements, so it holds nothing the centre lacks below them). The
//! newest commit a generation reports never goes back, and no batch goes past it.

use super::super::outbox::{
    ColumnValues, Kind, OutboxBatch, Registry, RequestedRows, TableRows, Tier,
};
use super::super::{StoreError, StoreResult};
use super::{CONNECT_TIMEOUT, options_of};
use crate::config::{PostgresUrl, SiteName};
use sqlx::postgres::{PgConnectOptions, PgConnection, PgPool, PgPoolOptions};
use sqlx::{ConnectOptions, Connection};
use std::collections::{HashMap, HashSet};

mod requests;
mod rule;

pub use requests::RawRequestRecord;
use requests::apply_requested;
use rule::{
    Acked, BatchRuling, BatchSpan, GenerationHeld, GenerationRuling, rule_batch, rule_generation,
};

/// What a site sends in one request: its identity and state, and a batch of one tier (none in
/// a report of state alone).
#[derive(Debug, Clone, Copy)]
pub struct SiteUpload<'a> {
    /// The site's outbox.
    pub outbox_id: &'a str,
    /// The outbox's generation.
    pub generation: &'a str,
    /// The generations it descends from, the nearest first.
    pub lineage: &'a [String],
    /// The site's newest commit when it read the upload.
    pub head_seq: Option<i64>,
    /// The names behind the ids of the batch's rows.
    pub registry: &'a Registry,
    /// The rows.
    pub batch: Option<&'a OutboxBatch>,
    /// Raw rows of a period the centre asked for (never with a batch).
    pub requested: Option<&'a RequestedRows>,
    /// The site's report of its state (JSON), kept as sent.
    pub status_json: Option<&'a str>,
    /// The site's report of its backlog (JSON), kept as sent.
    pub backlog_json: Option<&'a str>,
    /// The request's size on the wire (bytes), counted per tier.
    pub wire_bytes: u64,
}

/// What became of an upload.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SyncOutcome {
    /// Applied: the tier is now acknowledged up to `acked_seq` (also the answer to a report
    /// of state alone, with the tier's number unchanged).
    Applied {
        /// The tier's last applied commit (`None`: nothing yet).
        acked_seq: Option<i64>,
        /// When the site made that commit, as its batch said (`None`: not known).
        acked_stamp_ns: Option<i64>,
    },
    /// Nothing to apply: it ends at or before what was applied.
    Duplicate {
        /// The tier's last applied commit.
        acked_seq: Option<i64>,
        /// When the site made that commit, as the batch that brought it said.
        acked_stamp_ns: Option<i64>,
    },
    /// It starts after what was applied: the site resumes from `acked_seq`.
    Gap {
        /// The tier's last applied commit (`None`: nothing yet).
        acked_seq: Option<i64>,
    },
    /// Requested rows answer a raw request the site does not have (nothing was applied).
    UnknownRequest {
        /// The request named.
        id: i64,
    },
    /// The site uploads from another outbox than the one first seen under its name.
    OutboxChanged {
        /// The outbox first seen.
        known: String,
    },
    /// A generation the centre has not seen descends from none it has (nothing was applied).
    GenerationUnknown {
        /// The generation.
        generation: String,
    },
    /// A generation a later one descends from, which has uploaded: the site's database was
    /// replaced by a copy, and the old one still uploads beside it (nothing was applied).
    GenerationSuperseded {
        /// The generation.
        generation: String,
        /// A generation that descends from it.
        by: String,
    },
    /// The site's newest commit is below one it reported before in the same generation: its
    /// database was replaced by an older copy that did not start a generation of its own
    /// (nothing was applied).
    CommitsWentBack {
        /// The generation.
        generation: String,
        /// The newest commit the upload reports.
        head_seq: i64,
        /// The newest the generation reported before.
        known_head_seq: i64,
    },
}

/// A site as the centre knows it.
#[derive(Debug, Clone, PartialEq)]
pub struct SiteRecord {
    /// The site.
    pub site: String,
    /// Its first and last upload (centre's clock, ns).
    pub first_contact_ns: i64,
    /// Its last upload or report (centre's clock, ns).
    pub last_contact_ns: i64,
    /// Its last report of its state (JSON, as sent).
    pub status_json: Option<String>,
    /// Its last report of its backlog (JSON, as sent).
    pub backlog_json: Option<String>,
    /// Per tier: the last applied commit, rows applied, bytes received, batches applied.
    pub streams: Vec<StreamRecord>,
}

/// What one pass of the centre's upkeep removed from a site's copy.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SiteUpkeep {
    /// The site.
    pub site: String,
    /// Samples removed (older than the raw tier's days).
    pub samples: u64,
    /// Raw results removed (older than the raw tier's days).
    pub raw_results: u64,
    /// Results removed (older than the results' days; raw ones among them too).
    pub results: u64,
    /// Why the site's upkeep failed, when it did (nothing of it was done).
    pub failed: Option<String>,
}

/// One tier of one site at the centre.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StreamRecord {
    /// The tier.
    pub tier: Tier,
    /// The last commit applied (`None`: nothing yet).
    pub acked_seq: Option<i64>,
    /// Rows applied.
    pub rows_applied: i64,
    /// Bytes received (compressed, as sent).
    pub bytes_received: i64,
    /// Batches applied.
    pub batches_applied: i64,
    /// When the last batch was applied (centre's clock, ns).
    pub updated_ns: i64,
}

/// The centre's side of a fleet on its PostgreSQL database.
#[derive(Debug)]
pub struct Central {
    pool: PgPool,
    options: PgConnectOptions,
    /// Sites whose schema is ready (made and migrated) since start, by id.
    prepared: tokio::sync::Mutex<HashSet<i64>>,
    /// Per site (by id), a small read pool in the site's schema, made on first use (at most
    /// two connections, closed after a minute unused).
    readers: tokio::sync::Mutex<HashMap<i64, super::Reader>>,
}

/// The schema of a site's rows.
pub(crate) fn site_schema(site_id: i64) -> String {
    format!("site_{site_id}")
}

/// The stored form of "nothing applied yet".
const NOTHING: i64 = i64::MIN;

fn acked(stored: i64) -> Option<i64> {
    (stored != NOTHING).then_some(stored)
}

/// The PostgreSQL array type of a column's values.
fn array_type(kind: Kind) -> &'static str {
    match kind {
        Kind::Int => "int8[]",
        Kind::Real => "float8[]",
        Kind::Text => "text[]",
        Kind::Blob => "bytea[]",
        Kind::Bool => "bool[]",
    }
}

/// Writes a table's rows, each replacing the row at its key (`replace`), or only where none is.
async fn apply_rows(conn: &mut PgConnection, rows: &TableRows, replace: bool) -> StoreResult<()> {
    if let Some(problem) = rows.problem() {
        return Err(StoreError::UploadRefused(problem));
    }
    let table = rows.table;
    let spec = table.columns();
    let names: Vec<&str> = spec.iter().map(|(n, _)| *n).collect();
    let arrays: Vec<String> = spec
        .iter()
        .enumerate()
        .map(|(i, (_, k))| format!("${}::{}", i + 1, array_type(*k)))
        .collect();
    let key = table.key();
    let updates: Vec<String> = names
        .iter()
        .filter(|n| !key.contains(n))
        .map(|n| format!("{n} = excluded.{n}"))
        .collect();
    let on_conflict = if replace {
        format!("do update set {}", updates.join(", "))
    } else {
        "do nothing".to_owned()
    };
    let sql = format!(
        "insert into {} ({}) {} select * from unnest({}) on conflict ({}) {on_conflict}",
        table.table(),
        names.join(", "),
        if table.overrides_identity() {
            "overriding system value"
        } else {
            ""
        },
        arrays.join(", "),
        key.join(", "),
    );
    let blobs: Vec<Vec<Option<&[u8]>>> = rows
        .columns
        .iter()
        .filter_map(|c| match c {
            ColumnValues::Blob(v) => Some(v.iter().map(|b| b.as_ref().map(|b| &b.0[..])).collect()),
            _ => None,
        })
        .collect();
    let mut blobs = blobs.iter();
    let mut query = sqlx::query(&sql);
    for values in &rows.columns {
        query = match values {
            ColumnValues::Int(v) => query.bind(v),
            ColumnValues::Real(v) => query.bind(v),
            ColumnValues::Text(v) => query.bind(v),
            ColumnValues::Bool(v) => query.bind(v),
            ColumnValues::Blob(_) => match blobs.next() {
                Some(v) => query.bind(v),
                None => unreachable!("one list per blob column"),
            },
        };
    }
    query.execute(&mut *conn).await?;
    Ok(())
}

/// Writes the site's links and targets (ids as the site has them).
/// Records the upload's generation (registering a new one under its nearest known ancestor)
/// and its newest commit, in the upload's transaction; the refusal, if the upload must be
/// refused: a generation descending from none the centre knows, or commits that went back.
async fn generation(
    conn: &mut PgConnection,
    site: &SiteName,
    upload: &SiteUpload<'_>,
    now_ns: i64,
) -> StoreResult<Option<SyncOutcome>> {
    let generation = upload.generation;
    // Serialises the site's uploads' changes of generations.
    sqlx::query("select 1 from fleet.sites where site = $1 for update")
        .bind(site.as_str())
        .execute(&mut *conn)
        .await?;
    let known: Option<(Option<i64>,)> = sqlx::query_as(
        "select head_seq from fleet.generations where site = $1 and generation = $2",
    )
    .bind(site.as_str())
    .bind(generation)
    .fetch_optional(&mut *conn)
    .await?;
    let generations: Vec<String>;
    let held = match known {
        Some((head_seq,)) => {
            let child: Option<(String,)> = sqlx::query_as(
                "select generation from fleet.generations where site = $1 and parent = $2 \
                 order by first_contact_ns limit 1",
            )
            .bind(site.as_str())
            .bind(generation)
            .fetch_optional(&mut *conn)
            .await?;
            GenerationHeld::Known {
                head_seq,
                child: child.map(|(g,)| g),
            }
        }
        None => {
            generations =
                sqlx::query_scalar("select generation from fleet.generations where site = $1")
                    .bind(site.as_str())
                    .fetch_all(&mut *conn)
                    .await?;
            GenerationHeld::New {
                known: &generations,
            }
        }
    };
    match rule_generation(generation, upload.lineage, upload.head_seq, held) {
        GenerationRuling::Refused(outcome) => return Ok(Some(outcome)),
        GenerationRuling::GoOn => {}
        GenerationRuling::Register { parent } => {
            sqlx::query(
                "insert into fleet.generations (site, generation, parent, head_seq, \
                 first_contact_ns, last_contact_ns) values ($1, $2, $3, null, $4, $4)",
            )
            .bind(site.as_str())
            .bind(generation)
            .bind(parent)
            .bind(now_ns)
            .execute(&mut *conn)
            .await?;
        }
    }
    // The newest commit known is what a batch proves the site made, never a number a report
    // states alone: a false one would refuse the real site's every upload after it.
    sqlx::query(
        "update fleet.generations set head_seq = greatest(head_seq, $3), last_contact_ns = $4 \
         where site = $1 and generation = $2",
    )
    .bind(site.as_str())
    .bind(generation)
    .bind(upload.batch.map(|b| b.upto_seq))
    .bind(now_ns)
    .execute(&mut *conn)
    .await?;
    if upload.batch.is_some() {
        sqlx::query("update fleet.sites set generation = $2 where site = $1")
            .bind(site.as_str())
            .bind(generation)
            .execute(&mut *conn)
            .await?;
    }
    Ok(None)
}

/// Where a generation's first batch of `tier` may start at the latest: its nearest ancestor's
/// acknowledged number for the tier (`NOTHING` when none has one).
async fn inherited_ack(
    conn: &mut PgConnection,
    site: &SiteName,
    generation: &str,
    tier: &str,
) -> StoreResult<i64> {
    let mut current = generation.to_owned();
    // A lineage is a chain the centre made itself: bounded, but guard against a cycle anyway.
    for _ in 0..=crate::store::outbox::LINEAGE_KEPT * 4 {
        let parent: Option<(Option<String>,)> = sqlx::query_as(
            "select parent from fleet.generations where site = $1 and generation = $2",
        )
        .bind(site.as_str())
        .bind(&current)
        .fetch_optional(&mut *conn)
        .await?;
        let Some((Some(parent),)) = parent else {
            return Ok(NOTHING);
        };
        let acked: Option<(i64,)> = sqlx::query_as(
            "select acked_seq from fleet.streams where site = $1 and generation = $2 \
             and tier = $3",
        )
        .bind(site.as_str())
        .bind(&parent)
        .bind(tier)
        .fetch_optional(&mut *conn)
        .await?;
        if let Some((acked,)) = acked
            && acked != NOTHING
        {
            return Ok(acked);
        }
        current = parent;
    }
    Ok(NOTHING)
}

async fn apply_registry(conn: &mut PgConnection, registry: &Registry) -> StoreResult<()> {
    for (table, id, list) in [
        ("links", "link_id", &registry.links),
        ("targets", "target_id", &registry.targets),
    ] {
        let ids: Vec<i64> = list.iter().map(|r| r.id).collect();
        let names: Vec<&str> = list.iter().map(|r| r.name.as_str()).collect();
        let created: Vec<i64> = list.iter().map(|r| r.created_ns).collect();
        sqlx::query(&format!(
            "insert into {table} ({id}, name, created_ns) overriding system value \
             select * from unnest($1::int8[], $2::text[], $3::int8[]) \
             on conflict ({id}) do update set name = excluded.name"
        ))
        .bind(&ids)
        .bind(&names)
        .bind(&created)
        .execute(&mut *conn)
        .await?;
    }
    Ok(())
}

impl Central {
    /// Opens the centre's record of its fleet on the database at `url` (its schema made or
    /// migrated).
    pub async fn open(url: &PostgresUrl) -> StoreResult<Central> {
        let options = options_of(url)?;
        let refused = |e: StoreError| StoreError::Open {
            database: url.to_string(),
            message: format!("cannot prepare the fleet's schema: {e}"),
        };
        let mut conn = options.connect().await.map_err(|e| refused(e.into()))?;
        let migrate = async {
            sqlx::query("create schema if not exists fleet")
                .execute(&mut conn)
                .await?;
            sqlx::query("set search_path to fleet")
                .execute(&mut conn)
                .await?;
            crate::store::migrations::CENTRAL.run(&mut conn).await?;
            StoreResult::Ok(())
        };
        migrate.await.map_err(refused)?;
        let _ = conn.close().await;
        let pool = PgPoolOptions::new()
            .max_connections(8)
            .acquire_timeout(CONNECT_TIMEOUT)
            .connect_with(options.clone())
            .await
            .map_err(|e| refused(e.into()))?;
        Ok(Central {
            pool,
            options,
            prepared: tokio::sync::Mutex::new(HashSet::new()),
            readers: tokio::sync::Mutex::new(HashMap::new()),
        })
    }

    /// Makes (or migrates) the schema of a site's rows, once per site and start.
    async fn prepare_site(&self, site_id: i64) -> StoreResult<()> {
        let mut prepared = self.prepared.lock().await;
        if prepared.contains(&site_id) {
            return Ok(());
        }
        let schema = site_schema(site_id);
        sqlx::query(&format!("create schema if not exists {schema}"))
            .execute(&self.pool)
            .await?;
        // A pool of one connection in the site's schema (the migrator takes a pool).
        let in_schema = PgPoolOptions::new()
            .max_connections(1)
            .acquire_timeout(CONNECT_TIMEOUT)
            .connect_with(
                self.options
                    .clone()
                    .options([("search_path", schema.as_str())]),
            )
            .await?;
        crate::store::migrations::POSTGRES.run(&in_schema).await?;
        in_schema.close().await;
        prepared.insert(site_id);
        Ok(())
    }

    /// The id of a site (its schema's number) and the outbox it uploads from, registering it
    /// with `outbox_id` on its first contact.
    async fn register(
        &self,
        site: &SiteName,
        outbox_id: &str,
        now_ns: i64,
    ) -> StoreResult<(i64, String)> {
        sqlx::query(
            "insert into fleet.sites (site, outbox_id, first_contact_ns, last_contact_ns) \
             values ($1, $2, $3, $3) on conflict (site) do nothing",
        )
        .bind(site.as_str())
        .bind(outbox_id)
        .bind(now_ns)
        .execute(&self.pool)
        .await?;
        Ok(
            sqlx::query_as("select site_id, outbox_id from fleet.sites where site = $1")
                .bind(site.as_str())
                .fetch_one(&self.pool)
                .await?,
        )
    }

    /// Applies an upload of `site` (or records its report of state), in one transaction;
    /// `now_ns` is the centre's clock.
    pub async fn sync(
        &self,
        site: &SiteName,
        upload: SiteUpload<'_>,
        now_ns: i64,
    ) -> StoreResult<SyncOutcome> {
        let (site_id, known) = self.register(site, upload.outbox_id, now_ns).await?;
        if known != upload.outbox_id {
            return Ok(SyncOutcome::OutboxChanged { known });
        }
        self.prepare_site(site_id).await?;
        let mut tx = self.pool.begin().await?;
        sqlx::query(&format!(
            "set local search_path to {}",
            site_schema(site_id)
        ))
        .execute(&mut *tx)
        .await?;
        sqlx::query(
            "update fleet.sites set last_contact_ns = $2, status = coalesce($3, status), \
             backlog = coalesce($4, backlog) where site = $1",
        )
        .bind(site.as_str())
        .bind(now_ns)
        .bind(upload.status_json)
        .bind(upload.backlog_json)
        .execute(&mut *tx)
        .await?;
        if let Some(refused) = self::generation(&mut tx, site, &upload, now_ns).await? {
            tx.rollback().await?;
            return Ok(refused);
        }
        if let Some(slice) = upload.requested {
            let outcome = apply_requested(&mut tx, site, slice, upload.registry, now_ns).await?;
            if let SyncOutcome::UnknownRequest { .. } = outcome {
                // Refused: nothing of it is stored, its report of state neither.
                tx.rollback().await?;
            } else {
                tx.commit().await?;
            }
            return Ok(outcome);
        }
        let Some(batch) = upload.batch else {
            tx.commit().await?;
            return Ok(SyncOutcome::Applied {
                acked_seq: None,
                acked_stamp_ns: None,
            });
        };
        let tier = batch.tier.name();
        let generation = upload.generation;
        sqlx::query(
            "insert into fleet.streams (site, generation, tier, acked_seq, updated_ns) \
             values ($1, $2, $3, $4, $5) on conflict (site, generation, tier) do nothing",
        )
        .bind(site.as_str())
        .bind(generation)
        .bind(tier)
        .bind(NOTHING)
        .bind(now_ns)
        .execute(&mut *tx)
        .await?;
        // Locks the tier's row: uploads of one site and tier apply one after the other.
        let (stored, stored_stamp): (i64, Option<i64>) = sqlx::query_as(
            "select acked_seq, acked_stamp_ns from fleet.streams where site = $1 \
             and generation = $2 and tier = $3 for update",
        )
        .bind(site.as_str())
        .bind(generation)
        .bind(tier)
        .fetch_one(&mut *tx)
        .await?;
        let stored = Acked {
            seq: acked(stored),
            stamp_ns: stored_stamp,
        };
        // A generation's first batch of the tier continues its nearest ancestor's stream.
        let inherited = match stored.seq {
            None => acked(inherited_ack(&mut tx, site, generation, tier).await?),
            Some(_) => None,
        };
        let span = BatchSpan {
            after_seq: (batch.after_seq != NOTHING).then_some(batch.after_seq),
            upto_seq: batch.upto_seq,
            upto_stamp_ns: batch.upto_stamp_ns,
            partial: batch.partial,
        };
        let outcome = match rule_batch(stored, inherited, span) {
            BatchRuling::Duplicate => SyncOutcome::Duplicate {
                acked_seq: stored.seq,
                acked_stamp_ns: stored.stamp_ns,
            },
            BatchRuling::Gap => SyncOutcome::Gap {
                acked_seq: stored.seq,
            },
            BatchRuling::Apply(now_acked) => {
                apply_registry(&mut tx, upload.registry).await?;
                for rows in &batch.tables {
                    if rows.table.tier() != batch.tier {
                        return Err(StoreError::UploadRefused(format!(
                            "{} rows in a batch of the {tier} tier",
                            rows.table.name()
                        )));
                    }
                    apply_rows(&mut tx, rows, true).await?;
                }
                sqlx::query(
                    "update fleet.streams set acked_seq = $3, acked_stamp_ns = $8, \
                     rows_applied = rows_applied + $4, bytes_received = bytes_received + $5, \
                     batches_applied = batches_applied + 1, updated_ns = $6 \
                     where site = $1 and tier = $2 and generation = $7",
                )
                .bind(site.as_str())
                .bind(tier)
                .bind(now_acked.seq.unwrap_or(NOTHING))
                .bind(i64::try_from(batch.rows()).unwrap_or(i64::MAX))
                .bind(i64::try_from(upload.wire_bytes).unwrap_or(i64::MAX))
                .bind(now_ns)
                .bind(generation)
                .bind(now_acked.stamp_ns)
                .execute(&mut *tx)
                .await?;
                SyncOutcome::Applied {
                    acked_seq: now_acked.seq,
                    acked_stamp_ns: now_acked.stamp_ns,
                }
            }
        };
        tx.commit().await?;
        Ok(outcome)
    }

    /// The schema of a site's rows, when the site has uploaded.
    pub async fn schema_of(&self, site: &SiteName) -> StoreResult<Option<String>> {
        let row: Option<(i64,)> = sqlx::query_as("select site_id from fleet.sites where site = $1")
            .bind(site.as_str())
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.map(|(id,)| site_schema(id)))
    }

    /// Every site the centre has heard from, by name.
    pub async fn sites(&self) -> StoreResult<Vec<SiteRecord>> {
        type SiteRow = (String, i64, i64, Option<String>, Option<String>);
        let sites: Vec<SiteRow> = sqlx::query_as(
            "select site, first_contact_ns, last_contact_ns, status, backlog from fleet.sites \
             order by site",
        )
        .fetch_all(&self.pool)
        .await?;
        type StreamRow = (String, String, i64, i64, i64, i64, i64);
        // The streams of the generation each site uploaded from last.
        let streams: Vec<StreamRow> = sqlx::query_as(
            "select s.site, s.tier, s.acked_seq, s.rows_applied, s.bytes_received, \
             s.batches_applied, s.updated_ns from fleet.streams s \
             join fleet.sites t on t.site = s.site and t.generation = s.generation",
        )
        .fetch_all(&self.pool)
        .await?;
        Ok(sites
            .into_iter()
            .map(
                |(site, first_contact_ns, last_contact_ns, status_json, backlog_json)| {
                    let mut mine: Vec<StreamRecord> = streams
                        .iter()
                        .filter(|s| s.0 == site)
                        .filter_map(|s| {
                            Some(StreamRecord {
                                tier: Tier::parse(&s.1)?,
                                acked_seq: acked(s.2),
                                rows_applied: s.3,
                                bytes_received: s.4,
                                batches_applied: s.5,
                                updated_ns: s.6,
                            })
                        })
                        .collect();
                    mine.sort_by_key(|s| s.tier);
                    SiteRecord {
                        site,
                        first_contact_ns,
                        last_contact_ns,
                        status_json,
                        backlog_json,
                        streams: mine,
                    }
                },
            )
            .collect())
    }

    /// A site's id and its last report of its state (JSON, as sent); `None` when the centre has
    /// not heard from it.
    pub async fn site_report(&self, site: &SiteName) -> StoreResult<Option<(i64, Option<String>)>> {
        Ok(
            sqlx::query_as("select site_id, status from fleet.sites where site = $1")
                .bind(site.as_str())
                .fetch_optional(&self.pool)
                .await?,
        )
    }

    /// The store's read side over the copy of the site `site_id`, and the names of the site's
    /// targets by index: `described` first (the site's installation, in its order), then any
    /// other target the site's rows name (one its installation no longer has). `None` before
    /// the site's first batch made its schema.
    pub async fn site_store(
        &self,
        site_id: i64,
        described: &[String],
    ) -> StoreResult<Option<(super::super::Store, Vec<String>)>> {
        let schema = site_schema(site_id);
        let reader = {
            let mut readers = self.readers.lock().await;
            match readers.get(&site_id) {
                Some(r) => r.clone(),
                // The schema exists once the site's first batch was applied; before, nothing
                // to read (and no reader kept).
                None if !self.schema_ready(&schema).await? => return Ok(None),
                None => {
                    // Made, but perhaps by an older centre or still being migrated by this
                    // one: every migration applied before the first read (a reader between two
                    // would miss the columns the later one adds).
                    self.prepare_site(site_id).await?;
                    let options = self
                        .options
                        .clone()
                        .options([("search_path", schema.as_str())]);
                    // Connections close after a minute unused: a fleet of many sites browsed now
                    // and then must not hold the server's connections.
                    let pool = PgPoolOptions::new()
                        .max_connections(2)
                        .min_connections(0)
                        .idle_timeout(std::time::Duration::from_secs(60))
                        .acquire_timeout(CONNECT_TIMEOUT)
                        .connect_lazy_with(options.clone());
                    let r = super::Reader {
                        pool,
                        health_conn: std::sync::Arc::new(tokio::sync::Mutex::new(None)),
                        options: std::sync::Arc::new(options),
                    };
                    readers.insert(site_id, r.clone());
                    r
                }
            }
        };
        let registered: Vec<(i64, String)> =
            sqlx::query_as("select target_id, name from targets order by target_id")
                .fetch_all(&reader.pool)
                .await?;
        let mut names: Vec<String> = described.to_vec();
        names.extend(
            registered
                .iter()
                .filter(|(_, n)| !described.contains(n))
                .map(|(_, n)| n.clone()),
        );
        // A described target with no row yet has no results: an id no row holds.
        let target_ids: Vec<i64> = names
            .iter()
            .map(|n| {
                registered
                    .iter()
                    .find(|(_, r)| r == n)
                    .map_or(-1, |(id, _)| *id)
            })
            .collect();
        let store = super::super::Store {
            reader: super::super::Reader::Postgres(reader),
            writer: std::sync::Arc::new(super::super::WriterHealth::default()),
            link_ids: std::sync::Arc::from(Vec::<i64>::new()),
            target_ids: target_ids.into(),
        };
        Ok(Some((store, names)))
    }

    /// Upkeep of every site's copy, one site at a time, each in one transaction that holds the
    /// site's uploads back meanwhile: the raw tier (samples, raw results) before
    /// `now_ns - raw_days` and filtered results before `now_ns - results_days` are removed
    /// (whole daily partitions dropped where they can be), rollups and the events tier stay;
    /// then rows that landed in a default partition (a site catching up on past days) move
    /// into their day's, and the coming days' partitions are made. Returns what went, per site.
    pub async fn maintain(
        &self,
        now_ns: i64,
        raw_days: f64,
        results_days: f64,
    ) -> StoreResult<Vec<SiteUpkeep>> {
        let days = |d: f64| now_ns.saturating_sub((d * 86_400e9) as i64);
        let (raw_cutoff_ns, results_cutoff_ns) = (days(raw_days), days(results_days));
        let sites: Vec<(String, i64)> =
            sqlx::query_as("select site, site_id from fleet.sites order by site")
                .fetch_all(&self.pool)
                .await?;
        let mut out = Vec::with_capacity(sites.len());
        for (site, site_id) in sites {
            let schema = site_schema(site_id);
            if !self.schema_ready(&schema).await? {
                continue;
            }
            let pass = async {
                let mut tx = self.pool.begin().await?;
                sqlx::query(&format!("set local search_path to {schema}"))
                    .execute(&mut *tx)
                    .await?;
                // The site's uploads wait (they lock these rows) while its partitions change.
                sqlx::query("select tier from fleet.streams where site = $1 for update")
                    .bind(&site)
                    .execute(&mut *tx)
                    .await?;
                let samples = super::drop_before(&mut tx, "samples", raw_cutoff_ns).await?;
                let raw_results =
                    sqlx::query("delete from results where source = 0 and time_ns < $1")
                        .bind(raw_cutoff_ns)
                        .execute(&mut *tx)
                        .await?
                        .rows_affected();
                let results = super::drop_before(&mut tx, "results", results_cutoff_ns).await?;
                super::maintain(&mut tx).await?;
                tx.commit().await?;
                StoreResult::Ok((samples, raw_results, results))
            };
            // One site's failure (a row its partitions cannot take) is its own: reported, and
            // the others still get their upkeep.
            out.push(match pass.await {
                Ok((samples, raw_results, results)) => SiteUpkeep {
                    site,
                    samples,
                    raw_results,
                    results,
                    failed: None,
                },
                Err(e) => SiteUpkeep {
                    site,
                    samples: 0,
                    raw_results: 0,
                    results: 0,
                    failed: Some(e.to_string()),
                },
            });
        }
        Ok(out)
    }

    /// Whether a site's schema has its tables (made with the site's first upload).
    async fn schema_ready(&self, schema: &str) -> StoreResult<bool> {
        let (ready,): (bool,) = sqlx::query_as(
            "select exists (select 1 from information_schema.tables \
             where table_schema = $1 and table_name = 'samples')",
        )
        .bind(schema)
        .fetch_one(&self.pool)
        .await?;
        Ok(ready)
    }

    /// Whether the database answers (for the health check).
    pub async fn problem(&self) -> Option<String> {
        super::super::probe(sqlx::query("select 1").execute(&self.pool)).await
    }
}
