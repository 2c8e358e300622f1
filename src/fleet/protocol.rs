//! The upload's wire format: a JSON document, compressed with zstd
//! (`Content-Encoding: zstd`), posted to `POST /api/v1/sites/{site}/sync`.

use crate::store::outbox::{OutboxBatch, Registry, TableRows, Tier};
use serde::{Deserialize, Serialize};

/// The zstd level of uploads: a satellite link costs more than the site's cores.
pub const ZSTD_LEVEL: i32 = 9;

/// One upload: the site's identity and state, and at most one batch.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SyncRequest {
    /// The site's outbox (random, made with its file).
    pub outbox_id: String,
    /// The names behind the ids of the rows.
    pub registry: Registry,
    /// The rows of one tier; absent in a report of state alone.
    #[serde(default)]
    pub batch: Option<WireBatch>,
    /// The site's current state.
    #[serde(default)]
    pub status: Option<SiteStatus>,
    /// What the site has still to send, per tier.
    #[serde(default)]
    pub backlog: Vec<TierBacklog>,
}

/// A batch on the wire.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WireBatch {
    /// The tier.
    pub tier: Tier,
    /// The commit after which it starts (`None`: the outbox's start).
    pub after_seq: Option<i64>,
    /// The last commit it covers.
    pub upto_seq: i64,
    /// The rows, per table.
    pub tables: Vec<TableRows>,
}

impl From<OutboxBatch> for WireBatch {
    fn from(b: OutboxBatch) -> Self {
        WireBatch {
            tier: b.tier,
            after_seq: (b.after_seq != i64::MIN).then_some(b.after_seq),
            upto_seq: b.upto_seq,
            tables: b.tables,
        }
    }
}

impl From<WireBatch> for OutboxBatch {
    fn from(b: WireBatch) -> Self {
        OutboxBatch {
            tier: b.tier,
            after_seq: b.after_seq.unwrap_or(i64::MIN),
            upto_seq: b.upto_seq,
            tables: b.tables,
        }
    }
}

/// A site's state as it reports it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SiteStatus {
    /// When the site made the report (its clock, RFC 3339).
    pub time: String,
    /// Its targets.
    pub targets: Vec<TargetStatus>,
}

/// One target of a site.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct TargetStatus {
    /// The target.
    pub name: String,
    /// `ok`, `stale`, `degraded`, `initializing` or `predicted`.
    pub status: String,
    /// Its alarm level: `none`, `warn` or `alarm`.
    pub alarm: String,
    /// The time of its newest result (RFC 3339).
    pub time: Option<String>,
}

/// One tier's backlog as the site reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct TierBacklog {
    /// The tier.
    #[schema(value_type = String)]
    pub tier: Tier,
    /// Rows still to send.
    pub rows: u64,
    /// The last commit the centre acknowledged.
    pub acked_seq: Option<i64>,
}

/// What became of an upload.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// Applied (or a report of state recorded).
    Applied,
    /// Nothing to apply: the centre has it already.
    Duplicate,
    /// The batch starts after what the centre has: resume from `acked_seq`.
    Gap,
}

/// The centre's answer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct SyncResponse {
    /// What became of the upload.
    pub outcome: Outcome,
    /// The tier's last applied commit (absent: nothing yet, or a report of state alone).
    pub acked_seq: Option<i64>,
}
