//! `GET /api/v1/alarms`: stored alarm transitions.

use super::AppState;
use super::error::{ApiError, ErrorBody};
use super::query::Query;
use crate::clock::format_ns;
use crate::store::StoredAlarm;
use axum::Json;
use axum::extract::{Path, State};
use serde::{Deserialize, Serialize};

/// An alarm transition as answered.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct AlarmOut {
    /// Its id (for `POST /api/v1/alarms/{id}/ack`).
    pub id: i64,
    /// Target.
    pub target: String,
    /// When: measurement time for `deformation` and `rate`, the server's clock for `stale`.
    pub time: String,
    /// `deformation`, `rate` or `stale`.
    pub kind: crate::alarms::AlarmKind,
    /// Level before: `none`, `warn` or `alarm`.
    pub from: crate::alarms::Level,
    /// Level after.
    pub to: crate::alarms::Level,
    /// The deciding value, in `unit`: of the rotation and the translation, the one that is the
    /// larger fraction of its threshold; for stale, the age of the oldest link.
    pub value: f64,
    /// `arcsec`, `mm` (deformation), `arcsec_per_s`, `mm_per_s` (rate), `s` (stale), or `none`
    /// (stale transitions stored before ages were).
    pub unit: crate::alarms::ValueUnit,
    /// A sentence.
    pub message: String,
    /// Who acknowledged it; null until someone does.
    pub acknowledged_by: Option<String>,
    /// When it was acknowledged (server clock); null until then.
    pub acknowledged_at: Option<String>,
    /// The acknowledgement's note, if one was given.
    pub note: Option<String>,
}

impl AlarmOut {
    /// From a stored transition of the target named `target`.
    pub(super) fn new(target: String, a: &StoredAlarm) -> Self {
        let t = &a.transition;
        Self {
            id: a.id,
            target,
            time: format_ns(t.time_ns),
            kind: t.kind,
            from: t.from,
            to: t.to,
            value: t.value,
            unit: t.unit,
            message: t.message.clone(),
            acknowledged_by: a.ack.as_ref().map(|k| k.by.clone()),
            acknowledged_at: a.ack.as_ref().map(|k| format_ns(k.at_ns)),
            note: a.ack.as_ref().and_then(|k| k.note.clone()),
        }
    }
}

/// A notification's body: the alarm exactly as `GET /api/v1/alarms` shows it.
pub(super) fn encode_alarm(target: &str, alarm: &StoredAlarm) -> serde_json::Result<Vec<u8>> {
    serde_json::to_vec(&AlarmOut::new(target.to_owned(), alarm))
}

/// Query of `alarms`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub(super) struct AlarmsQuery {
    /// One target only.
    pub target: Option<String>,
    /// Start.
    pub from: Option<String>,
    /// End.
    pub to: Option<String>,
    /// At most this many (default 1000, at most 100000).
    pub limit: Option<i64>,
    /// `asc` (default): the oldest first; `desc`: the newest first, so that `limit` keeps the
    /// latest transitions.
    pub order: Option<String>,
}

/// `GET .../alarms`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct AlarmsOut {
    /// Transitions, oldest first (newest first with `order=desc`).
    pub alarms: Vec<AlarmOut>,
}

/// `GET /api/v1/alarms?target=&from=&to=&limit=&order=`.
#[utoipa::path(get, path = "/alarms", tag = "alarms",
    params(AlarmsQuery),
    responses(
        (status = 200, description = "Alarm transitions, oldest first (or newest first with `order=desc`)", body = AlarmsOut),
        (status = 404, description = "Unknown target", body = ErrorBody),
        (status = 422, description = "Invalid query", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn list_alarms(
    State(app): State<AppState>,
    Query(q): Query<AlarmsQuery>,
) -> Result<Json<AlarmsOut>, ApiError> {
    let names = app.service.installation().model.target_names();
    Ok(Json(alarms_of(app.service.store(), &names, &q).await?))
}

/// The alarm transitions of `store` the query asks for; its targets are `names`, by index.
pub(super) async fn alarms_of(
    store: &crate::store::Store,
    names: &[String],
    q: &AlarmsQuery,
) -> Result<AlarmsOut, ApiError> {
    let target = match &q.target {
        Some(name) => Some(
            names
                .iter()
                .position(|n| n == name)
                .map(crate::model::TargetId)
                .ok_or_else(|| ApiError::not_found(format!("unknown target `{name}`")))?,
        ),
        None => None,
    };
    let (from, to) = super::parse_query_range(q.from.as_deref(), q.to.as_deref())?;
    let limit = super::query_count("limit", q.limit, 1000)?;
    let newest_first = super::query_choice(
        "order",
        q.order.as_deref(),
        false,
        &[("asc", false), ("desc", true)],
    )?;
    let stored = store.alarms(target, from, to, limit, newest_first).await?;
    Ok(AlarmsOut {
        alarms: stored
            .iter()
            .map(|a| AlarmOut::new(names[a.target.0].clone(), a))
            .collect(),
    })
}

/// Body of `POST /api/v1/alarms/{id}/ack`.
#[derive(Debug, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct AckIn {
    /// Who acknowledges (a name for the record).
    pub by: String,
    /// What was seen or done (optional).
    pub note: Option<String>,
}

/// `POST /api/v1/alarms/{id}/ack`: records that someone has seen an alarm transition (who,
/// when, a note). The same acknowledgement again is accepted (a retry); a different one of an
/// acknowledged alarm is a conflict.
#[utoipa::path(post, path = "/alarms/{id}/ack", tag = "alarms",
    params(("id" = i64, Path, description = "The alarm's id")),
    request_body(content = AckIn, description = "Who acknowledges, and a note"),
    responses(
        (status = 200, description = "The alarm, acknowledged", body = AlarmOut),
        (status = 400, description = "Malformed JSON", body = ErrorBody),
        (status = 404, description = "No such alarm", body = ErrorBody),
        (status = 409, description = "Already acknowledged by someone else or with another note", body = ErrorBody),
        (status = 422, description = "No `by`, a text too long, or a transition back to `none`", body = ErrorBody),
    ),
    security(("bearer" = ["admin"])))]
pub(super) async fn post_ack(
    State(app): State<AppState>,
    Path(id): Path<String>,
    body: axum::body::Bytes,
) -> Result<Json<AlarmOut>, ApiError> {
    let id: i64 = id
        .parse()
        .map_err(|_| ApiError::invalid_field("id", format!("`{id}` is not an alarm id")))?;
    let ack: AckIn = super::parse_json_body(&body)?;
    if ack.by.trim().is_empty() {
        return Err(ApiError::invalid_field("by", "say who acknowledges"));
    }
    super::check_texts(&[("by", Some(&ack.by)), ("note", ack.note.as_deref())])?;
    let stored = app.service.acknowledge_alarm(id, ack.by, ack.note).await?;
    let name = app.service.installation().model.targets[stored.target.0]
        .name
        .clone();
    Ok(Json(AlarmOut::new(name, &stored)))
}
