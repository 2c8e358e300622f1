//! A centre's view of one site: the per-target endpoints under `/api/v1/sites/{site}/...`,
//! answered from the site's uploaded copy with the shapes the site itself answers.
//!
//! The copy is what the site uploaded: results, rollups, references and alarms as the site
//! stored them. What the site's installation says of its targets (base, paths, thresholds)
//! comes with each of its reports of state; the newest report's status of a target is the
//! freshest word on it (reports travel with every upload, ahead of a backlog of results).
//! Values are never recomputed here: a compensation is the newest uploaded filtered result
//! (`source` `history`), its `age_s` the time from that result to now on the centre's clock,
//! so a site whose link is down shows an age that grows.

use super::AppState;
use super::alarms::{AlarmsOut, AlarmsQuery, alarms_of};
use super::error::{ApiError, ErrorBody};
use super::fleet::{centre, site_of};
use super::history::{HistoryQuery, StatsOut, WindowQuery, history_of, stats_of};
use super::query::Query;
use super::targets::{
    AtQuery, CompensationOut, CompensationSource, Described, Evaluated, ReferenceOut,
    ReferencesOut, TargetOut, compensation_out, references_of,
};
use crate::bank::{ResultSource, TargetStatus};
use crate::clock::parse_query_time;
use crate::fleet::protocol::{SiteStatus, TargetDescription};
use crate::model::TargetId;
use crate::store::Store;
use axum::Json;
use axum::extract::{Path, State};

/// A site's copy at the centre: its store, its targets' names by index, and its last report.
struct SiteView {
    store: Store,
    /// Every target the copy knows, by the store's index: the described ones first.
    names: Vec<String>,
    /// The site's last report of its state.
    status: SiteStatus,
}

impl SiteView {
    /// The described target `name`: its index and description, or 404.
    fn target(&self, site: &str, name: &str) -> Result<(TargetId, &TargetDescription), ApiError> {
        self.status
            .described
            .iter()
            .enumerate()
            .map(|(i, d)| (TargetId(i), d))
            .find(|(_, d)| d.name == name)
            .ok_or_else(|| {
                ApiError::not_found(format!(
                    "site `{site}` has no target `{name}` (as its last report describes it)"
                ))
            })
    }

    /// The status of target `name` as the site last reported it.
    fn reported_status(&self, name: &str) -> Option<TargetStatus> {
        self.status
            .targets
            .iter()
            .find(|t| t.name == name)
            .and_then(|t| t.status.known())
    }
}

/// The copy of `site`, or 404 saying why there is none.
async fn site_view(app: &AppState, site: &str) -> Result<SiteView, ApiError> {
    let central = &centre(app)?.store;
    let name = site_of(site)?;
    let (site_id, status_json) = central.site_report(&name).await?.ok_or_else(|| {
        ApiError::not_found(format!("the centre has not heard from site `{site}`"))
    })?;
    let status: SiteStatus = status_json
        .as_deref()
        .and_then(|s| serde_json::from_str(s).ok())
        .filter(|s: &SiteStatus| !s.described.is_empty())
        .ok_or_else(|| {
            ApiError::not_found(format!(
                "site `{site}` has not described its targets yet (it reports them with its \
                 uploads; a site of an earlier version does not)"
            ))
        })?;
    let described: Vec<String> = status.described.iter().map(|d| d.name.clone()).collect();
    let (store, names) = central
        .site_store(site_id, &described)
        .await?
        .ok_or_else(|| ApiError::not_found(format!("site `{site}` has uploaded no rows yet")))?;
    Ok(SiteView {
        store,
        names,
        status,
    })
}

/// `GET /api/v1/sites/{site}/targets`.
#[utoipa::path(get, path = "/sites/{site}/targets", tag = "fleet",
    params(("site" = String, Path, description = "The site")),
    responses(
        (status = 200, description = "The site's targets with their paths and status, as the site lists them", body = [TargetOut]),
        (status = 404, description = "No such site at this centre, no rows of it yet, or this service is no centre", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn list_site_targets(
    State(app): State<AppState>,
    Path(site): Path<String>,
) -> Result<Json<Vec<TargetOut>>, ApiError> {
    let view = site_view(&app, &site).await?;
    let mut out = Vec::with_capacity(view.status.described.len());
    for (i, d) in view.status.described.iter().enumerate() {
        let latest = view
            .store
            .latest_result(TargetId(i), ResultSource::Filtered)
            .await?;
        let status = view
            .reported_status(&d.name)
            .or(latest.as_ref().map(|l| l.status))
            .unwrap_or(TargetStatus::Initializing);
        out.push(TargetOut::new(d.clone(), status, latest.map(|l| l.time_ns)));
    }
    Ok(Json(out))
}

/// `GET /api/v1/sites/{site}/targets/{name}/compensation[?at=TIME]`.
#[utoipa::path(get, path = "/sites/{site}/targets/{name}/compensation", tag = "fleet",
    params(("site" = String, Path, description = "The site"),
           ("name" = String, Path, description = "Target frame"), AtQuery),
    responses(
        (status = 200, description = "The site's newest uploaded (or asked-for) pose, deformation and correction", body = CompensationOut),
        (status = 404, description = "Unknown site or target, or no result at that time", body = ErrorBody),
        (status = 422, description = "Invalid `at`", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_site_compensation(
    State(app): State<AppState>,
    Path((site, name)): Path<(String, String)>,
    Query(q): Query<AtQuery>,
) -> Result<Json<CompensationOut>, ApiError> {
    let view = site_view(&app, &site).await?;
    let (ti, d) = view.target(&site, &name)?;
    let target = Described {
        name: &d.name,
        base: &d.base,
        thresholds: d.alarms.thresholds(),
    };
    let reference = view.store.references(ti).await?.last().copied();
    if let Some(at) = q.at {
        let at_ns = parse_query_time(&at).map_err(|m| ApiError::invalid_field("at", m))?;
        let e = Evaluated::from_history(&view.store, ti, &name, at_ns).await?;
        return Ok(Json(compensation_out(&target, e, reference.as_ref())));
    }
    let Some(latest) = view.store.latest_result(ti, ResultSource::Filtered).await? else {
        return Ok(Json(compensation_out(
            &target,
            Evaluated::none(CompensationSource::History),
            reference.as_ref(),
        )));
    };
    let now_ns = app.service.now_ns();
    let e = Evaluated {
        status: view.reported_status(&name).unwrap_or(latest.status),
        age_s: Some((now_ns - latest.time_ns).max(0) as f64 / 1e9),
        ..Evaluated::stored(&latest, CompensationSource::History)
    };
    let mut out = compensation_out(&target, e, reference.as_ref());
    // The site's alarm state (hysteresis, dwell, rate, stale) as its uploaded transitions left it.
    let levels = view.store.alarm_levels(ti).await?;
    out.alarm = levels
        .into_iter()
        .max()
        .unwrap_or(crate::alarms::Level::None);
    Ok(Json(out))
}

/// `GET /api/v1/sites/{site}/targets/{name}/stats?from=&to=&source=raw|filtered`.
#[utoipa::path(get, path = "/sites/{site}/targets/{name}/stats", tag = "fleet",
    params(("site" = String, Path, description = "The site"),
           ("name" = String, Path, description = "Target frame"), WindowQuery),
    responses(
        (status = 200, description = "Min, max, mean and RMS over the window of the site's uploaded results", body = StatsOut),
        (status = 404, description = "Unknown site or target", body = ErrorBody),
        (status = 422, description = "Invalid window", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_site_stats(
    State(app): State<AppState>,
    Path((site, name)): Path<(String, String)>,
    Query(q): Query<WindowQuery>,
) -> Result<Json<StatsOut>, ApiError> {
    let view = site_view(&app, &site).await?;
    let (ti, _) = view.target(&site, &name)?;
    Ok(Json(stats_of(&app, &view.store, ti, name, &q).await?))
}

/// `GET /api/v1/sites/{site}/targets/{name}/history?from=&to=&source=&max_points=&format=csv`.
#[utoipa::path(get, path = "/sites/{site}/targets/{name}/history", tag = "fleet",
    params(("site" = String, Path, description = "The site"),
           ("name" = String, Path, description = "Target frame"), HistoryQuery),
    responses(
        (status = 200, description = "Min, mean and max per time bucket of the site's uploaded results (JSON), or one row per bucket (`format=csv`)", content(
            (super::history::HistoryOut = "application/json"),
            (String = "text/csv"),
        )),
        (status = 404, description = "Unknown site or target", body = ErrorBody),
        (status = 422, description = "Invalid query", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_site_history(
    State(app): State<AppState>,
    Path((site, name)): Path<(String, String)>,
    Query(q): Query<HistoryQuery>,
) -> Result<axum::response::Response, ApiError> {
    let view = site_view(&app, &site).await?;
    let (ti, _) = view.target(&site, &name)?;
    history_of(&app, &view.store, ti, &name, q).await
}

/// `GET /api/v1/sites/{site}/targets/{name}/reference`.
#[utoipa::path(get, path = "/sites/{site}/targets/{name}/reference", tag = "fleet",
    params(("site" = String, Path, description = "The site"),
           ("name" = String, Path, description = "Target frame")),
    responses(
        (status = 200, description = "The site's current reference, as uploaded", body = ReferenceOut),
        (status = 404, description = "Unknown site or target, or no reference yet", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_site_reference(
    State(app): State<AppState>,
    Path((site, name)): Path<(String, String)>,
) -> Result<Json<ReferenceOut>, ApiError> {
    let view = site_view(&app, &site).await?;
    let (ti, _) = view.target(&site, &name)?;
    view.store
        .references(ti)
        .await?
        .last()
        .map(|r| Json(r.into()))
        .ok_or_else(|| {
            ApiError::not_found(format!(
                "target `{name}` of site `{site}` has no reference yet"
            ))
        })
}

/// `GET /api/v1/sites/{site}/targets/{name}/references`.
#[utoipa::path(get, path = "/sites/{site}/targets/{name}/references", tag = "fleet",
    params(("site" = String, Path, description = "The site"),
           ("name" = String, Path, description = "Target frame")),
    responses(
        (status = 200, description = "Every reference version the site uploaded, oldest first", body = ReferencesOut),
        (status = 404, description = "Unknown site or target", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn list_site_references(
    State(app): State<AppState>,
    Path((site, name)): Path<(String, String)>,
) -> Result<Json<ReferencesOut>, ApiError> {
    let view = site_view(&app, &site).await?;
    let (ti, _) = view.target(&site, &name)?;
    Ok(Json(references_of(&view.store, ti, name).await?))
}

/// `GET /api/v1/sites/{site}/alarms?target=&from=&to=&limit=&order=`.
#[utoipa::path(get, path = "/sites/{site}/alarms", tag = "fleet",
    params(("site" = String, Path, description = "The site"), AlarmsQuery),
    responses(
        (status = 200, description = "The site's alarm transitions as uploaded, with their acknowledgements", body = AlarmsOut),
        (status = 404, description = "Unknown site or target", body = ErrorBody),
        (status = 422, description = "Invalid query", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn list_site_alarms(
    State(app): State<AppState>,
    Path(site): Path<String>,
    Query(q): Query<AlarmsQuery>,
) -> Result<Json<AlarmsOut>, ApiError> {
    let view = site_view(&app, &site).await?;
    Ok(Json(alarms_of(&view.store, &view.names, &q).await?))
}
