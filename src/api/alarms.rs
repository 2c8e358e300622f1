//! `GET /api/v1/alarms`: stored alarm transitions.

use super::AppState;
use super::error::{ApiError, ErrorBody};
use super::time::format_ns;
use crate::alarms::Transition;
use axum::Json;
use axum::extract::{Query, State};
use serde::{Deserialize, Serialize};

/// An alarm transition as answered.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct AlarmOut {
    /// Target.
    pub target: String,
    /// When (measurement time).
    pub time: String,
    /// `deformation`, `rate` or `stale`.
    pub kind: &'static str,
    /// Level before: `none`, `warn` or `alarm`.
    pub from: &'static str,
    /// Level after.
    pub to: &'static str,
    /// The deciding value, in `unit`: of the rotation and the translation, the one that is the
    /// larger fraction of its threshold (0 for stale).
    pub value: f64,
    /// `arcsec`, `mm` (deformation), `arcsec_per_s`, `mm_per_s` (rate) or `none` (stale).
    pub unit: &'static str,
    /// A sentence.
    pub message: String,
}

impl AlarmOut {
    /// From a transition.
    pub fn new(target: String, t: &Transition) -> Self {
        Self {
            target,
            time: format_ns(t.time_ns),
            kind: t.kind.name(),
            from: t.from.name(),
            to: t.to.name(),
            value: t.value,
            unit: t.unit.name(),
            message: t.message.clone(),
        }
    }
}

/// Query of `alarms`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub struct AlarmsQuery {
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
pub struct AlarmsOut {
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
pub async fn list_alarms(
    State(app): State<AppState>,
    Query(q): Query<AlarmsQuery>,
) -> Result<Json<AlarmsOut>, ApiError> {
    let inst = app.service.installation();
    let target = match &q.target {
        Some(name) => Some(super::targets::target_index(&app, name)?.0),
        None => None,
    };
    let (from, to) = super::time::parse_query_range(q.from.as_deref(), q.to.as_deref())?;
    let limit = super::query_count("limit", q.limit, 1000)?;
    let newest_first = super::query_choice(
        "order",
        q.order.as_deref(),
        false,
        &[("asc", false), ("desc", true)],
    )?;
    let stored = app
        .service
        .store()
        .alarms(target, from, to, limit, newest_first)
        .await?;
    Ok(Json(AlarmsOut {
        alarms: stored
            .iter()
            .map(|a| AlarmOut::new(inst.targets[a.target].name.clone(), &a.transition))
            .collect(),
    }))
}
