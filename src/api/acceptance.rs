//! `/api/v1/acceptance`: the acceptance procedure run against the service, and the recorded
//! acceptances with where each stands (see [`crate::service`]'s acceptance and
//! [`crate::acceptance`]).

use super::AppState;
use super::error::{ApiError, ErrorBody};
use crate::acceptance::Standing;
use crate::service::{AcceptanceOut, AcceptanceSummary, RunOut};
use axum::Json;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use serde::{Deserialize, Serialize};

/// The most acceptances `GET /api/v1/acceptance` lists.
const LISTED: i64 = 100;

/// `GET /api/v1/acceptance`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct AcceptanceListOut {
    /// Whether the installation states a procedure (`[acceptance]`).
    pub configured: bool,
    /// Where the newest acceptance stands (none when none is recorded).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub standing: Option<Standing>,
    /// The newest acceptances, newest first (at most 100).
    pub acceptances: Vec<AcceptanceSummary>,
    /// The run, while one is running or until the next starts.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub run: Option<RunOut>,
}

/// Body of `POST /api/v1/acceptance/run`.
#[derive(Debug, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct RunIn {
    /// Who runs it (a name for the record).
    pub by: String,
    /// A note for the record (optional).
    pub note: Option<String>,
}

/// `GET /api/v1/acceptance`: the recorded acceptances, newest first, each with where it
/// stands (valid, due, no longer holds, failed), and the run.
#[utoipa::path(get, path = "/acceptance", tag = "acceptance",
    responses((status = 200, description = "The acceptances and the run", body = AcceptanceListOut)),
    security(("bearer" = ["read"])))]
pub(super) async fn list_acceptances(
    State(app): State<AppState>,
) -> Result<Json<AcceptanceListOut>, ApiError> {
    let acceptances = app.service.acceptances(LISTED).await?;
    let run = app.service.acceptance_run().await?;
    Ok(Json(AcceptanceListOut {
        configured: app.service.installation().acceptance.is_some(),
        standing: acceptances.first().map(|a| a.standing),
        acceptances,
        run,
    }))
}

/// `GET /api/v1/acceptance/{id}`: one acceptance whole: its steps' windows and figures, its
/// limits, and the calibrations each target was measured with.
#[utoipa::path(get, path = "/acceptance/{id}", tag = "acceptance",
    params(("id" = i64, Path, description = "The acceptance's id")),
    responses(
        (status = 200, description = "The acceptance", body = AcceptanceOut),
        (status = 404, description = "No such acceptance", body = ErrorBody),
        (status = 422, description = "Not an id", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_acceptance(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<AcceptanceOut>, ApiError> {
    let id: i64 = id
        .parse()
        .map_err(|_| ApiError::invalid_field("id", format!("`{id}` is not an acceptance id")))?;
    Ok(Json(app.service.acceptance(id).await?))
}

/// `POST /api/v1/acceptance/run`: starts the installation's procedure; the still window
/// awaits the operator.
#[utoipa::path(post, path = "/acceptance/run", tag = "acceptance",
    request_body(content = RunIn, description = "Who runs it, and a note"),
    responses(
        (status = 201, description = "The run, awaiting the operator", body = RunOut),
        (status = 400, description = "Malformed JSON", body = ErrorBody),
        (status = 409, description = "Another run is measuring", body = ErrorBody),
        (status = 422, description = "No `by`, a text too long, or no `[acceptance]` in the installation", body = ErrorBody),
    ),
    security(("bearer" = ["admin"])))]
pub(super) async fn post_run(
    State(app): State<AppState>,
    body: axum::body::Bytes,
) -> Result<(StatusCode, Json<RunOut>), ApiError> {
    let r: RunIn = super::parse_json_body(&body)?;
    if r.by.trim().is_empty() {
        return Err(ApiError::invalid_field("by", "say who runs the acceptance"));
    }
    super::check_texts(&[("by", Some(&r.by)), ("note", r.note.as_deref())])?;
    let run = app.service.start_acceptance(r.by, r.note).await?;
    Ok((StatusCode::CREATED, Json(run)))
}

/// `GET /api/v1/acceptance/run`: the run, moved on as far as the stored results allow: what
/// the operator is to do, the window measured, the steps done.
#[utoipa::path(get, path = "/acceptance/run", tag = "acceptance",
    responses(
        (status = 200, description = "The run", body = RunOut),
        (status = 404, description = "No run was started", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_run(State(app): State<AppState>) -> Result<Json<RunOut>, ApiError> {
    match app.service.acceptance_run().await? {
        Some(run) => Ok(Json(run)),
        None => {
            Err(crate::service::ServiceError::NotFound("no acceptance is running".into()).into())
        }
    }
}

/// `POST /api/v1/acceptance/run/ready`: the operator placed the current step (kept
/// everything still, or made the move): its results settle from the newest result, then its
/// window is measured.
#[utoipa::path(post, path = "/acceptance/run/ready", tag = "acceptance",
    responses(
        (status = 200, description = "The run, measuring the step", body = RunOut),
        (status = 404, description = "No run was started", body = ErrorBody),
        (status = 409, description = "The step is being measured, or the run finished", body = ErrorBody),
    ),
    security(("bearer" = ["admin"])))]
pub(super) async fn post_ready(State(app): State<AppState>) -> Result<Json<RunOut>, ApiError> {
    Ok(Json(app.service.acceptance_ready().await?))
}

/// `DELETE /api/v1/acceptance/run`: abandons the run; nothing of it is recorded.
#[utoipa::path(delete, path = "/acceptance/run", tag = "acceptance",
    responses(
        (status = 204, description = "Abandoned"),
        (status = 404, description = "No run was started", body = ErrorBody),
    ),
    security(("bearer" = ["admin"])))]
pub(super) async fn delete_run(State(app): State<AppState>) -> Result<StatusCode, ApiError> {
    app.service.abandon_acceptance().await?;
    Ok(StatusCode::NO_CONTENT)
}

/// `GET /api/v1/acceptance/{id}/certificate`: the acceptance's certificate, one self-contained
/// HTML page to print and sign: the rig, what was accepted (each target's calibrations and
/// links), the limits and the decision rule, every step's figures, lines for the signatures.
#[utoipa::path(get, path = "/acceptance/{id}/certificate", tag = "acceptance",
    params(("id" = i64, Path, description = "The acceptance's id")),
    responses(
        (status = 200, description = "The certificate (text/html)", content_type = "text/html"),
        (status = 404, description = "No such acceptance", body = ErrorBody),
        (status = 422, description = "Not an id", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_certificate(
    State(app): State<AppState>,
    Path(id): Path<String>,
) -> Result<axum::response::Response, ApiError> {
    let id: i64 = id
        .parse()
        .map_err(|_| ApiError::invalid_field("id", format!("`{id}` is not an acceptance id")))?;
    let page = app.service.acceptance_certificate(id).await?;
    Ok(super::report::report_page(
        axum::body::Body::from(page),
        Some(&format!(
            "inline; filename=\"brokenray-acceptance-{id}.html\""
        )),
    ))
}
