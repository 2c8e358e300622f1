//! Periods of raw rows the centre asks of a site: recorded, delivered in slices applied
//! exactly once, cancelled, listed.

use super::super::super::outbox::{RawRequest, Registry, RequestedRows, Tier};
use super::super::super::{StoreError, StoreResult};
use super::rule::{SliceRuling, rule_slice};
use super::{Central, SyncOutcome, apply_registry, apply_rows};
use crate::config::SiteName;
use sqlx::postgres::PgConnection;

/// Applies a slice of a period the centre asked for, in the upload's transaction: only when it
/// continues what was delivered (a replay or a slice of a finished request changes nothing; one
/// that starts later is a gap, and the site resumes from the request's `delivered_to_ns`).
pub(super) async fn apply_requested(
    conn: &mut PgConnection,
    site: &SiteName,
    slice: &RequestedRows,
    registry: &Registry,
    now_ns: i64,
) -> StoreResult<SyncOutcome> {
    let row: Option<(i64, i64, Option<i64>)> = sqlx::query_as(
        "select to_ns, delivered_to_ns, done_ns from fleet.raw_requests \
         where request_id = $1 and site = $2 for update",
    )
    .bind(slice.request_id)
    .bind(site.as_str())
    .fetch_optional(&mut *conn)
    .await?;
    let Some((to_ns, delivered_to_ns, done_ns)) = row else {
        return Ok(SyncOutcome::UnknownRequest {
            id: slice.request_id,
        });
    };
    let delivered = match rule_slice(
        to_ns,
        delivered_to_ns,
        done_ns.is_some(),
        slice.from_ns,
        slice.to_ns,
    ) {
        SliceRuling::Duplicate => {
            return Ok(SyncOutcome::Duplicate {
                acked_seq: None,
                acked_stamp_ns: None,
            });
        }
        SliceRuling::Gap => return Ok(SyncOutcome::Gap { acked_seq: None }),
        SliceRuling::Apply { delivered_to_ns } => delivered_to_ns,
    };
    apply_registry(&mut *conn, registry).await?;
    let mut rows_applied = 0i64;
    for rows in &slice.tables {
        if rows.table.tier() != Tier::Raw {
            return Err(StoreError::UploadRefused(format!(
                "{} rows in a slice of raw rows",
                rows.table.name()
            )));
        }
        apply_rows(&mut *conn, rows, slice.replace).await?;
        rows_applied += i64::try_from(rows.rows()).unwrap_or(i64::MAX);
    }
    sqlx::query(
        "update fleet.raw_requests set delivered_to_ns = $2, rows_applied = rows_applied + $3, \
         done_ns = case when $2 >= to_ns then $4 end where request_id = $1",
    )
    .bind(slice.request_id)
    .bind(delivered)
    .bind(rows_applied)
    .bind(now_ns)
    .execute(&mut *conn)
    .await?;
    Ok(SyncOutcome::Applied {
        acked_seq: None,
        acked_stamp_ns: None,
    })
}

/// A period of raw rows asked of a site, as the centre records it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RawRequestRecord {
    /// The request's id.
    pub id: i64,
    /// The period's start (ns, measurement time).
    pub from_ns: i64,
    /// Its end, excluded.
    pub to_ns: i64,
    /// How far the site delivered it.
    pub delivered_to_ns: i64,
    /// Rows applied.
    pub rows_applied: i64,
    /// Who asked (the token's name, or a name given).
    pub requested_by: Option<String>,
    /// When it was asked (centre's clock).
    pub created_ns: i64,
    /// When the last of it arrived, or it was cancelled.
    pub done_ns: Option<i64>,
    /// Who cancelled it and when, if it was.
    pub cancelled: Option<(Option<String>, i64)>,
}

/// A row of `fleet.raw_requests`, as [`RAW_REQUEST_COLUMNS`] reads it.
struct RawRequestRow {
    request_id: i64,
    from_ns: i64,
    to_ns: i64,
    delivered_to_ns: i64,
    rows_applied: i64,
    requested_by: Option<String>,
    created_ns: i64,
    done_ns: Option<i64>,
    cancelled_by: Option<String>,
    cancelled_ns: Option<i64>,
}

crate::store::rows::from_columns!(RawRequestRow {
    request_id,
    from_ns,
    to_ns,
    delivered_to_ns,
    rows_applied,
    requested_by,
    created_ns,
    done_ns,
    cancelled_by,
    cancelled_ns,
});

impl From<RawRequestRow> for RawRequestRecord {
    fn from(r: RawRequestRow) -> Self {
        RawRequestRecord {
            id: r.request_id,
            from_ns: r.from_ns,
            to_ns: r.to_ns,
            delivered_to_ns: r.delivered_to_ns,
            rows_applied: r.rows_applied,
            requested_by: r.requested_by,
            created_ns: r.created_ns,
            done_ns: r.done_ns,
            cancelled: r.cancelled_ns.map(|at| (r.cancelled_by, at)),
        }
    }
}

const RAW_REQUEST_COLUMNS: &str = "request_id, from_ns, to_ns, delivered_to_ns, rows_applied, \
                                   requested_by, created_ns, done_ns, cancelled_by, cancelled_ns";

impl Central {
    /// Asks `site` for its raw rows measured in `[from_ns, to_ns)`; `None` when the centre has
    /// not heard from the site.
    pub async fn request_raw(
        &self,
        site: &SiteName,
        from_ns: i64,
        to_ns: i64,
        requested_by: Option<&str>,
        now_ns: i64,
    ) -> StoreResult<Option<RawRequestRecord>> {
        let row: Option<RawRequestRow> = sqlx::query_as(&format!(
            "insert into fleet.raw_requests (site, from_ns, to_ns, delivered_to_ns, requested_by, \
             created_ns) select site, $2, $3, $2, $4, $5 from fleet.sites where site = $1 \
             returning {RAW_REQUEST_COLUMNS}"
        ))
        .bind(site.as_str())
        .bind(from_ns)
        .bind(to_ns)
        .bind(requested_by)
        .bind(now_ns)
        .fetch_optional(&self.pool)
        .await?;
        Ok(row.map(RawRequestRecord::from))
    }

    /// Cancels a raw request of `site` that is still pending: no site delivers it any more.
    /// `None` when there is no such request; the request as it stands otherwise (one already
    /// done or cancelled is left as it is).
    pub async fn cancel_raw(
        &self,
        site: &SiteName,
        id: i64,
        by: Option<&str>,
        now_ns: i64,
    ) -> StoreResult<Option<RawRequestRecord>> {
        sqlx::query(
            "update fleet.raw_requests set done_ns = $4, cancelled_ns = $4, cancelled_by = $3 \
             where site = $1 and request_id = $2 and done_ns is null",
        )
        .bind(site.as_str())
        .bind(id)
        .bind(by)
        .bind(now_ns)
        .execute(&self.pool)
        .await?;
        let row: Option<RawRequestRow> = sqlx::query_as(&format!(
            "select {RAW_REQUEST_COLUMNS} from fleet.raw_requests where site = $1 \
             and request_id = $2"
        ))
        .bind(site.as_str())
        .bind(id)
        .fetch_optional(&self.pool)
        .await?;
        Ok(row.map(RawRequestRecord::from))
    }

    /// Every raw request of `site`, the newest first.
    pub async fn raw_requests(&self, site: &SiteName) -> StoreResult<Vec<RawRequestRecord>> {
        let rows: Vec<RawRequestRow> = sqlx::query_as(&format!(
            "select {RAW_REQUEST_COLUMNS} from fleet.raw_requests where site = $1 \
             order by request_id desc"
        ))
        .bind(site.as_str())
        .fetch_all(&self.pool)
        .await?;
        Ok(rows.into_iter().map(RawRequestRecord::from).collect())
    }

    /// The raw requests of `site` not yet delivered, the oldest first: what its uploads are
    /// answered with.
    pub async fn pending_raw(&self, site: &SiteName) -> StoreResult<Vec<RawRequest>> {
        let rows: Vec<(i64, i64, i64, i64)> = sqlx::query_as(
            "select request_id, from_ns, to_ns, delivered_to_ns from fleet.raw_requests \
             where site = $1 and done_ns is null order by request_id",
        )
        .bind(site.as_str())
        .fetch_all(&self.pool)
        .await?;
        Ok(rows
            .into_iter()
            .map(|(id, from_ns, to_ns, delivered_to_ns)| RawRequest {
                id,
                from_ns,
                to_ns,
                delivered_to_ns,
            })
            .collect())
    }
}
