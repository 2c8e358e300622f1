//! The fleet's endpoints: a centre's `POST /api/v1/sites/{site}/sync` (a site's uploads) and
//! `GET /api/v1/sites` (the fleet), and a site's `GET /api/v1/upstream` (its uploads).

use super::AppState;
use super::auth::Caller;
use super::error::{ApiError, ErrorBody};
use crate::api::error::ErrorCode;
use crate::clock::format_ns;
use crate::config::SiteName;
use crate::fleet::protocol::{
    Outcome, SiteStatus, SyncRequest, SyncResponse, TargetStatus, TierBacklog, UploadBudget,
    UploadRefusal,
};
use crate::store::outbox::OutboxBatch;
use crate::store::{SiteUpload, SyncOutcome};
use axum::Json;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, StatusCode, header};
use bytes::Bytes;
use serde::Serialize;
use std::collections::BTreeMap;

/// The site of a path, or 404 naming the rule.
pub(super) fn site_of(text: &str) -> Result<SiteName, ApiError> {
    SiteName::parse(text).ok_or_else(|| {
        ApiError::not_found(format!(
            "`{text}` is not a site name (lowercase letters, digits, `-`, `_`)"
        ))
    })
}

/// How long an upload waits for a slot before it is answered 503 (the site retries).
const SYNC_WAIT: std::time::Duration = std::time::Duration::from_secs(10);

/// An upload's refusal as an answer.
fn refused(refusal: UploadRefusal) -> ApiError {
    match refusal {
        UploadRefusal::TooLarge(m) => {
            ApiError::new(StatusCode::PAYLOAD_TOO_LARGE, ErrorCode::PayloadTooLarge, m)
        }
        UploadRefusal::Malformed(m) => ApiError::bad_request(ErrorCode::MalformedBody, m),
        e @ UploadRefusal::Encoding(_) => ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            ErrorCode::UnsupportedMediaType,
            e.to_string(),
        ),
        e @ UploadRefusal::Decoder(_) => ApiError::internal(e.to_string()),
    }
}

/// Decompresses and parses an upload on a blocking thread (never on the async workers).
async fn read_upload(
    headers: HeaderMap,
    body: Bytes,
    budget: UploadBudget,
) -> Result<SyncRequest, ApiError> {
    tokio::task::spawn_blocking(move || {
        // A header that is not text names no encoding this reads: refused, not taken as none.
        let encoding = match headers.get(header::CONTENT_ENCODING) {
            None => None,
            Some(v) => Some(v.to_str().map_err(|_| {
                refused(UploadRefusal::Encoding(
                    String::from_utf8_lossy(v.as_bytes()).into_owned(),
                ))
            })?),
        };
        let json = budget.read(encoding, &body).map_err(refused)?;
        super::parse_json_body::<SyncRequest>(&json)
    })
    .await
    .map_err(|e| ApiError::internal(format!("the upload's reader failed: {e}")))?
}

/// `POST /api/v1/sites/{site}/sync`: a site's upload, applied in one transaction exactly once.
#[utoipa::path(post, path = "/sites/{site}/sync", tag = "fleet",
    params(("site" = String, Path, description = "The site, as its token names it")),
    request_body(content = Object, content_type = "application/json",
        description = "A `SyncRequest` (see docs/interface.md, \"Fleet\"), zstd-compressed with `Content-Encoding: zstd`"),
    responses(
        (status = 200, description = "Applied, a duplicate (nothing changed), or a gap (resume from `acked_seq`)", body = SyncResponse),
        (status = 403, description = "The token uploads for another site", body = ErrorBody),
        (status = 404, description = "This service is no centre", body = ErrorBody),
        (status = 409, description = "The site uploads from another outbox than the one the centre has been receiving, from a generation of it descending from none the centre knows, or from a database older than one it uploaded from before in the same generation", body = ErrorBody),
        (status = 422, description = "The upload is malformed; the field is named", body = ErrorBody),
    ),
    security(("bearer" = ["sync"])))]
pub(super) async fn post_sync(
    State(app): State<AppState>,
    Path(site): Path<String>,
    axum::Extension(caller): axum::Extension<Caller>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Json<SyncResponse>, ApiError> {
    let the_centre = centre(&app)?;
    let central = &the_centre.store;
    let site = site_of(&site)?;
    if caller.authenticated && caller.site.as_ref() != Some(&site) {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            ErrorCode::Forbidden,
            format!("this token does not upload for site `{site}`"),
        ));
    }
    let budget = UploadBudget {
        bytes: the_centre.settings.max_sync_bytes,
    };
    // Held until the upload is applied: what it was read into lives until then.
    let _slot = super::take_slot(&the_centre.sync_slots, SYNC_WAIT, "uploads").await?;
    let request = read_upload(headers, body.clone(), budget).await?;
    let status_json = request
        .check(app.service.now_ns())
        .map_err(|p| ApiError::invalid_field(&p.field, p.message))?;
    let batch: Option<OutboxBatch> = request.batch.map(Into::into);
    let backlog =
        serde_json::to_string(&request.backlog).map_err(|e| ApiError::internal(e.to_string()))?;
    let upload = SiteUpload {
        outbox_id: &request.outbox_id,
        // A site of an earlier version uploads in its outbox's first generation.
        generation: request.generation.as_deref().unwrap_or(&request.outbox_id),
        lineage: &request.lineage,
        head_seq: request.head_seq,
        registry: &request.registry,
        batch: batch.as_ref(),
        requested: request.requested.as_ref(),
        status_json: status_json.as_deref(),
        backlog_json: Some(&backlog),
        wire_bytes: body.len() as u64,
    };
    // A value the database refuses is refused the same every time: the site must hear 422 and
    // stop that stream, not retry a 503 for ever.
    let outcome = central
        .sync(&site, upload, app.service.now_ns())
        .await
        .map_err(crate::store::StoreError::refusal_of_value)?;
    let (outcome, acked_seq, acked_stamp_ns) = match outcome {
        SyncOutcome::Applied {
            acked_seq,
            acked_stamp_ns,
        } => (Outcome::Applied, acked_seq, acked_stamp_ns),
        SyncOutcome::Duplicate {
            acked_seq,
            acked_stamp_ns,
        } => (Outcome::Duplicate, acked_seq, acked_stamp_ns),
        SyncOutcome::Gap { acked_seq } => (Outcome::Gap, acked_seq, None),
        SyncOutcome::UnknownRequest { id } => {
            return Err(ApiError::invalid_field(
                "requested.request_id",
                format!("site `{site}` has no raw request {id}"),
            ));
        }
        SyncOutcome::GenerationUnknown { generation } => {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                ErrorCode::GenerationUnknown,
                format!(
                    "site `{site}` uploads in outbox generation {generation}, which descends \
                     from no generation the centre has received"
                ),
            ));
        }
        SyncOutcome::GenerationSuperseded { generation, by } => {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                ErrorCode::GenerationSuperseded,
                format!(
                    "site `{site}` uploads in outbox generation {generation}, which generation \
                     {by} (a copy of its database, restored) supersedes: two databases upload \
                     as this site; stop the one that was replaced"
                ),
            ));
        }
        SyncOutcome::CommitsWentBack {
            generation,
            head_seq,
            known_head_seq,
        } => {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                ErrorCode::CommitsWentBack,
                format!(
                    "site `{site}` reports {head_seq} as its newest commit, but reported \
                     {known_head_seq} before in outbox generation {generation}: its database was \
                     replaced by an older copy; run `brokenray new-generation` on it with the \
                     service stopped, and the centre takes its commits as a new stream"
                ),
            ));
        }
        SyncOutcome::OutboxChanged { known } => {
            return Err(ApiError::new(
                StatusCode::CONFLICT,
                ErrorCode::OutboxChanged,
                format!(
                    "site `{site}` uploads from outbox {}, but the centre has been receiving outbox {known}: \
                     the site's database was replaced or another site uses this name",
                    request.outbox_id
                ),
            ));
        }
    };
    Ok(Json(SyncResponse {
        outcome,
        acked_seq,
        acked_stamp_ns,
        // Every answer tells the site what the office asks of it, and how much it reads.
        raw_requests: central.pending_raw(&site).await?,
        limits: Some(budget.limits()),
    }))
}

/// One tier of a site at the centre.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct SiteTierOut {
    /// `events`, `results` or `raw`.
    pub tier: crate::store::outbox::Tier,
    /// The last of the site's commits applied (absent: nothing yet).
    pub acked_seq: Option<i64>,
    /// Rows still at the site, as it last reported.
    pub backlog_rows: Option<u64>,
    /// Rows applied.
    pub rows_applied: i64,
    /// Bytes received (compressed).
    pub bytes_received: i64,
    /// When the last batch was applied.
    pub last_applied: Option<String>,
}

/// A site of the fleet.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct SiteOut {
    /// Its name.
    pub site: String,
    /// Its last upload or report (centre's clock).
    pub last_contact: String,
    /// Its first upload.
    pub first_contact: String,
    /// Rows still to send per tier, as it last reported (`events`, `results`, `raw`).
    pub backlog: BTreeMap<String, u64>,
    /// Its targets, as it last reported.
    pub targets: Vec<TargetStatus>,
    /// Its worst alarm level (`none`, `warn`, `alarm`).
    pub alarm: crate::alarms::Level,
    /// When the site made its last report (its clock).
    pub reported: Option<String>,
    /// What is wrong at the site, as it last reported (the disk budget removed rows before
    /// their time, some never sent).
    pub problems: Vec<String>,
    /// Per tier, what the centre has.
    pub tiers: Vec<SiteTierOut>,
}

/// `GET /api/v1/sites`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct SitesOut {
    /// Every site the centre has heard from, by name.
    pub sites: Vec<SiteOut>,
}

/// `GET /api/v1/sites`: the fleet, each site with its last contact, backlog, targets and worst
/// alarm.
#[utoipa::path(get, path = "/sites", tag = "fleet",
    responses(
        (status = 200, description = "Every site the centre has heard from", body = SitesOut),
        (status = 404, description = "This service is no centre", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn list_sites(State(app): State<AppState>) -> Result<Json<SitesOut>, ApiError> {
    let central = &centre(&app)?.store;
    let records = central.sites().await?;
    let sites = records
        .into_iter()
        .map(|r| {
            let status: Option<SiteStatus> = r
                .status_json
                .as_deref()
                .and_then(|s| serde_json::from_str(s).ok());
            let reported: Vec<TierBacklog> = r
                .backlog_json
                .as_deref()
                .and_then(|s| serde_json::from_str(s).ok())
                .unwrap_or_default();
            let targets = status
                .as_ref()
                .map(|s| s.targets.clone())
                .unwrap_or_default();
            let alarm = targets
                .iter()
                .filter_map(|t| t.alarm.known())
                .max()
                .unwrap_or(crate::alarms::Level::None);
            SiteOut {
                last_contact: format_ns(r.last_contact_ns),
                first_contact: format_ns(r.first_contact_ns),
                backlog: reported
                    .iter()
                    .map(|b| (b.tier.name().to_owned(), b.rows))
                    .collect(),
                alarm,
                problems: status
                    .as_ref()
                    .map(|s| s.problems.clone())
                    .unwrap_or_default(),
                reported: status.map(|s| s.time),
                targets,
                tiers: r
                    .streams
                    .iter()
                    .map(|s| SiteTierOut {
                        tier: s.tier,
                        acked_seq: s.acked_seq,
                        backlog_rows: reported.iter().find(|b| b.tier == s.tier).map(|b| b.rows),
                        rows_applied: s.rows_applied,
                        bytes_received: s.bytes_received,
                        last_applied: (s.batches_applied > 0).then(|| format_ns(s.updated_ns)),
                    })
                    .collect(),
                site: r.site,
            }
        })
        .collect();
    Ok(Json(SitesOut { sites }))
}

/// The longest period one raw request may cover: a month (more than a site keeps by default).
const MAX_RAW_REQUEST_NS: i64 = 31 * 86_400_000_000_000;

/// `DELETE /api/v1/sites/{site}/raw-requests/{id}`: withdraws a pending request (admin); the
/// site stops delivering it. One already done or cancelled is answered as it stands.
#[utoipa::path(delete, path = "/sites/{site}/raw-requests/{id}", tag = "fleet",
    params(("site" = String, Path, description = "The site"),
           ("id" = i64, Path, description = "The request")),
    responses(
        (status = 200, description = "The request, now `cancelled` (or as it was, when it had ended)", body = RawRequestOut),
        (status = 404, description = "No such request of the site, or this service is no centre", body = ErrorBody),
    ),
    security(("bearer" = ["admin"])))]
pub(super) async fn cancel_raw_request(
    State(app): State<AppState>,
    Path((site, id)): Path<(String, String)>,
    axum::Extension(caller): axum::Extension<Caller>,
) -> Result<Json<RawRequestOut>, ApiError> {
    let central = &centre(&app)?.store;
    let site = site_of(&site)?;
    let id: i64 = id
        .parse()
        .map_err(|_| ApiError::invalid_field("id", format!("`{id}` is not a request id")))?;
    let cancelled = central
        .cancel_raw(&site, id, caller.name.as_deref(), app.service.now_ns())
        .await?
        .ok_or_else(|| ApiError::not_found(format!("site `{site}` has no raw request {id}")))?;
    Ok(Json((&cancelled).into()))
}

/// Body of `POST /api/v1/sites/{site}/raw-requests`.
#[derive(Debug, serde::Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct RawRequestIn {
    /// The period's start (RFC 3339 or integer ns, measurement time).
    #[schema(schema_with = crate::wire::time_schema)]
    pub from: serde_json::Value,
    /// Its end, excluded.
    #[schema(schema_with = crate::wire::time_schema)]
    pub to: serde_json::Value,
    /// Who asks (for the record).
    pub by: Option<String>,
}

/// A period of raw rows asked of a site.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct RawRequestOut {
    /// Its id.
    pub id: i64,
    /// The period's start.
    pub from: String,
    /// Its end, excluded.
    pub to: String,
    /// `pending` until the site has delivered all of it, then `done`; `cancelled` when the
    /// office withdrew it first.
    pub state: super::vocab::RawRequestState,
    /// How far the site has delivered it: every raw row measured before this time is here.
    pub delivered_to: String,
    /// Rows applied (samples and raw results).
    pub rows: i64,
    /// Who asked.
    pub requested_by: Option<String>,
    /// When it was asked (centre's clock).
    pub created: String,
    /// When the last of it arrived (or it was cancelled).
    pub done: Option<String>,
    /// Who cancelled it, when it was.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cancelled_by: Option<String>,
}

impl From<&crate::store::RawRequestRecord> for RawRequestOut {
    fn from(r: &crate::store::RawRequestRecord) -> Self {
        RawRequestOut {
            id: r.id,
            from: format_ns(r.from_ns),
            to: format_ns(r.to_ns),
            state: match (r.done_ns, &r.cancelled) {
                (_, Some(_)) => super::vocab::RawRequestState::Cancelled,
                (Some(_), None) => super::vocab::RawRequestState::Done,
                (None, None) => super::vocab::RawRequestState::Pending,
            },
            cancelled_by: r.cancelled.as_ref().and_then(|(by, _)| by.clone()),
            delivered_to: format_ns(r.delivered_to_ns),
            rows: r.rows_applied,
            requested_by: r.requested_by.clone(),
            created: format_ns(r.created_ns),
            done: r.done_ns.map(format_ns),
        }
    }
}

/// `GET .../raw-requests`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct RawRequestsOut {
    /// The site.
    pub site: String,
    /// Its requests, the newest first.
    pub requests: Vec<RawRequestOut>,
}

/// The centre of this service, or 404.
pub(super) fn centre(app: &AppState) -> Result<&crate::fleet::Centre, ApiError> {
    app.centre.as_deref().ok_or_else(|| {
        ApiError::not_found("this service is no centre (`[central] enabled = true` on PostgreSQL)")
    })
}

/// `POST /api/v1/sites/{site}/raw-requests`: asks a site for its raw samples and raw results
/// of a period (whether or not its raw tier is streamed); the site uploads them with its next
/// contacts, after its events and results.
#[utoipa::path(post, path = "/sites/{site}/raw-requests", tag = "fleet",
    params(("site" = String, Path, description = "The site")),
    request_body(content = RawRequestIn, description = "The period, `[from, to)`, in measurement time"),
    responses(
        (status = 201, description = "Asked; the site delivers it with its next contacts", body = RawRequestOut),
        (status = 404, description = "Not a site this centre has heard from, or this service is no centre", body = ErrorBody),
        (status = 422, description = "Invalid period", body = ErrorBody),
    ),
    security(("bearer" = ["admin"])))]
pub(super) async fn post_raw_request(
    State(app): State<AppState>,
    Path(site): Path<String>,
    body: Bytes,
) -> Result<(StatusCode, Json<RawRequestOut>), ApiError> {
    let central = &centre(&app)?.store;
    let site = site_of(&site)?;
    let r: RawRequestIn = super::parse_json_body(&body)?;
    let from_ns =
        crate::clock::parse_json_time(&r.from).map_err(|m| ApiError::invalid_field("from", m))?;
    let to_ns =
        crate::clock::parse_json_time(&r.to).map_err(|m| ApiError::invalid_field("to", m))?;
    if to_ns <= from_ns {
        return Err(ApiError::invalid_field("to", "`to` is not after `from`"));
    }
    if to_ns.saturating_sub(from_ns) > MAX_RAW_REQUEST_NS {
        return Err(ApiError::invalid_field(
            "to",
            format!(
                "a request covers at most {} days (a site delivers it over its link); ask for \
                 longer periods in several requests",
                MAX_RAW_REQUEST_NS / 86_400_000_000_000
            ),
        ));
    }
    super::check_texts(&[("by", r.by.as_deref())])?;
    let made = central
        .request_raw(&site, from_ns, to_ns, r.by.as_deref(), app.service.now_ns())
        .await?
        .ok_or_else(|| {
            ApiError::not_found(format!("the centre has not heard from site `{site}`"))
        })?;
    Ok((StatusCode::CREATED, Json((&made).into())))
}

/// `GET /api/v1/sites/{site}/raw-requests`: the periods of raw rows asked of a site, and how
/// far each has arrived.
#[utoipa::path(get, path = "/sites/{site}/raw-requests", tag = "fleet",
    params(("site" = String, Path, description = "The site")),
    responses(
        (status = 200, description = "Every request of the site, the newest first", body = RawRequestsOut),
        (status = 404, description = "This service is no centre", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn list_raw_requests(
    State(app): State<AppState>,
    Path(site): Path<String>,
) -> Result<Json<RawRequestsOut>, ApiError> {
    let central = &centre(&app)?.store;
    let site = site_of(&site)?;
    let requests = central.raw_requests(&site).await?;
    Ok(Json(RawRequestsOut {
        site: site.to_string(),
        requests: requests.iter().map(Into::into).collect(),
    }))
}

/// One tier of this site's uploads.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct UpstreamTierOut {
    /// `events`, `results` or `raw`.
    pub tier: crate::store::outbox::Tier,
    /// The last of this site's commits the centre acknowledged (absent: none yet).
    pub acked_seq: Option<i64>,
    /// Still to send: rows, and bytes on the wire (estimated from what was sent).
    pub backlog: BacklogOut,
    /// Since start: batches, rows and compressed bytes the centre acknowledged.
    pub sent: SentOut,
    /// Uncompressed over compressed bytes of what was sent (absent before any).
    pub compression_ratio: Option<f64>,
    /// When the centre last acknowledged a batch.
    pub last_success: Option<String>,
    /// The last failure.
    pub last_error: Option<ErrorAtOut>,
    /// Why the stream stopped, when the centre refused it (it resumes after a restart).
    pub stopped: Option<String>,
    /// False for raw samples when `raw_kbit_s` is 0 (they are kept, not sent).
    pub enabled: bool,
}

/// A backlog (null until the uploader has counted it, just after start).
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct BacklogOut {
    /// Rows.
    pub rows: Option<u64>,
    /// Bytes on the wire (estimated from the compressed bytes per row sent so far).
    pub bytes: Option<u64>,
    /// Raw tier: rows of the periods the centre asked for still to send (not in `rows`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub requested_rows: Option<u64>,
}

/// What was sent.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct SentOut {
    /// Batches.
    pub batches: u64,
    /// Rows.
    pub rows: u64,
    /// Compressed bytes.
    pub bytes: u64,
    /// Raw tier only: rows sent for periods the centre asked for (also counted in `bytes`).
    pub requested_rows: u64,
}

/// A failure and when.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct ErrorAtOut {
    /// When (server clock).
    pub time: String,
    /// What.
    pub message: String,
}

/// `GET /api/v1/upstream`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct UpstreamOut {
    /// This site.
    pub site: String,
    /// The centre.
    pub url: String,
    /// When the centre last answered.
    pub last_contact: Option<String>,
    /// The raw samples' budget (kbit/s).
    pub raw_kbit_s: f64,
    /// Per tier, most urgent first.
    pub tiers: Vec<UpstreamTierOut>,
    /// Periods of raw rows the centre asked for and has not all of, as it last said: `id`,
    /// `from`, `to`, `delivered_to`.
    pub raw_requests: Vec<PendingRawOut>,
}

/// A period the centre asked this site for.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct PendingRawOut {
    /// The centre's id of the request.
    pub id: i64,
    /// The period's start.
    pub from: String,
    /// Its end, excluded.
    pub to: String,
    /// How far this site has delivered it.
    pub delivered_to: String,
}

/// `GET /api/v1/upstream`: this site's uploads to its centre, per tier.
#[utoipa::path(get, path = "/upstream", tag = "fleet",
    responses(
        (status = 200, description = "Per tier: acknowledged commit, backlog, last success and failure", body = UpstreamOut),
        (status = 404, description = "This service uploads to no centre", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_upstream(
    State(app): State<AppState>,
) -> Result<Json<UpstreamOut>, ApiError> {
    let Some(upstream) = &app.upstream else {
        return Err(ApiError::not_found(
            "this service uploads to no centre (`[upstream]` in the installation)",
        ));
    };
    let raw_kbit_s = upstream.settings.raw_kbit_s;
    Ok(Json(UpstreamOut {
        site: upstream.site.to_string(),
        url: crate::config::redacted_url(&upstream.settings.url),
        last_contact: upstream.last_contact_ns().map(format_ns),
        raw_kbit_s,
        raw_requests: upstream
            .raw_requests()
            .iter()
            .map(|r| PendingRawOut {
                id: r.id,
                from: format_ns(r.from_ns),
                to: format_ns(r.to_ns),
                delivered_to: format_ns(r.delivered_to_ns),
            })
            .collect(),
        tiers: upstream
            .progress()
            .into_iter()
            .map(|(tier, p)| UpstreamTierOut {
                tier,
                acked_seq: p.acked_seq,
                backlog: BacklogOut {
                    rows: p.backlog_rows,
                    bytes: p.backlog_bytes(),
                    requested_rows: p.requested_rows,
                },
                compression_ratio: (p.bytes_sent > 0)
                    .then(|| p.json_bytes_sent as f64 / p.bytes_sent as f64),
                sent: SentOut {
                    batches: p.batches_sent,
                    rows: p.rows_sent,
                    bytes: p.bytes_sent,
                    requested_rows: p.requested_rows_sent,
                },
                last_success: p.last_success_ns.map(format_ns),
                last_error: p.last_error.map(|(t, m)| ErrorAtOut {
                    time: format_ns(t),
                    message: m,
                }),
                stopped: p.stopped,
                enabled: tier != crate::store::outbox::Tier::Raw || raw_kbit_s > 0.0,
            })
            .collect(),
    }))
}
