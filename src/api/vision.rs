//! The measurement pipeline over HTTP: `POST /api/v1/observations` (raw marker observations,
//! solved by PnP and ingested as link samples) and `POST /api/v1/calibration/hand-eye`
//! (`A_i X = X B_i` for a rigid station; computes, stores nothing).

use super::AppState;
use super::dto::invalid;
use super::error::{ApiError, ErrorBody};
use super::ingest::{IngestResponse, check_batch_size, read_body};
use super::parse_json_body;
use crate::clock::format_ns;
use crate::geometry::PoseCov;
use crate::service::IngestItem;
use crate::wire::{FieldProblem, HandEyeIn, HandEyeOut, ObservationIn, PoseOut, SigmaOut};
use axum::Json;
use axum::body::Body;
use axum::extract::State;
use axum::http::HeaderMap;
use serde::{Deserialize, Serialize};
use std::collections::HashSet;

/// A batch of observations, each solved and stored, or none.
#[derive(Debug, Clone, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(crate) struct ObservationsBatch {
    /// The observations.
    pub observations: Vec<ObservationIn>,
}

/// The pose PnP computed for one observation.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub(crate) struct ObservedPoseOut {
    /// The measured link `<camera>_from_<marker>`.
    pub link: String,
    /// The observation's time (RFC 3339).
    pub time: String,
    /// `camera_from_marker`.
    pub pose: PoseOut,
    /// Its sigmas, from `(J^T J)^-1 pixel_sigma^2`.
    pub sigma: SigmaOut,
    /// Reprojection RMS (px).
    pub reprojection_rms_px: f64,
    /// Points used.
    pub points: usize,
    /// RMS of the best solution over the runner-up's (0 when there is none; near 1 ambiguous).
    pub ambiguity_ratio: f64,
    /// Indices (into `points_px`) left out by robust estimation.
    pub rejected_points: Vec<usize>,
}

/// The answer to an accepted batch of observations.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(crate) struct ObservationsResponse {
    /// What ingesting the computed samples did.
    #[serde(flatten)]
    pub ingest: IngestResponse,
    /// The computed poses, in the order of the observations.
    pub poses: Vec<ObservedPoseOut>,
}

/// `POST /api/v1/observations`.
#[utoipa::path(post, path = "/observations", tag = "ingest",
    request_body(content = ObservationsBatch, description = "Marker observations `{\"observations\": [...]}`"),
    responses(
        (status = 200, description = "Every observation solved and its sample durably stored", body = ObservationsResponse),
        (status = 400, description = "Malformed JSON", body = ErrorBody),
        (status = 409, description = "A sample differs from the one stored at the same link and time", body = ErrorBody),
        (status = 413, description = "Body or batch over the limit", body = ErrorBody),
        (status = 422, description = "An observation is invalid or cannot be solved (each named); nothing was stored", body = ErrorBody),
        (status = 503, description = "The writer is not available", body = ErrorBody),
    ),
    security(("bearer" = ["ingest"])))]
pub(crate) async fn post_observations(
    State(app): State<AppState>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<ObservationsResponse>, ApiError> {
    let bytes = read_body(body, &headers, app.limits.max_body_bytes).await?;
    let batch: ObservationsBatch = parse_json_body(&bytes)?;
    check_batch_size(
        "observations",
        batch.observations.len(),
        app.limits.max_batch_samples,
    )?;
    let observer = app.service.observer();
    // PnP is CPU work (tens of microseconds per observation): off the async workers.
    let latest = crate::clock::latest_accepted_ns(
        app.service.now_ns(),
        app.service.installation().server.max_future_s,
    );
    let solved = blocking(move || solve_batch(&observer, &batch.observations, latest)).await?;
    let (items, poses) = solved.map_err(|problems| {
        invalid(
            format!(
                "{} observation problem(s); nothing was stored",
                problems.len()
            ),
            problems,
        )
    })?;
    let report = app.service.ingest(items).await?;
    Ok(Json(ObservationsResponse {
        ingest: report.into(),
        poses,
    }))
}

/// Runs CPU work on the blocking pool; a panic in it is a 500.
pub(super) async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> T + Send + 'static,
) -> Result<T, ApiError> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| ApiError::internal(e.to_string()))
}

/// Solves every observation, or lists every problem.
fn solve_batch(
    observer: &crate::model::Observer,
    observations: &[ObservationIn],
    latest_ns: i64,
) -> Result<(Vec<IngestItem>, Vec<ObservedPoseOut>), Vec<FieldProblem>> {
    let mut problems = Vec::new();
    let mut items = Vec::with_capacity(observations.len());
    let mut poses = Vec::with_capacity(observations.len());
    let mut seen = HashSet::new();
    for (index, o) in observations.iter().enumerate() {
        let time_ns = match crate::clock::parse_measurement_time(&o.time, latest_ns) {
            Ok(t) => t,
            Err(m) => {
                problems.push(FieldProblem::new("time", m).at(index));
                continue;
            }
        };
        let (link, solution) = match observer.solve(
            &o.camera,
            &o.marker,
            &o.points_px,
            o.ids.as_deref(),
            o.sigma_px.as_deref(),
        ) {
            Ok(v) => v,
            Err(e) => {
                problems.push(FieldProblem::new(e.field, e.message).at(index));
                continue;
            }
        };
        if !seen.insert((link.link.0, time_ns)) {
            problems.push(
                FieldProblem::new(
                    "time",
                    format!(
                        "a second observation of `{}` at the same time in this batch",
                        link.name
                    ),
                )
                .at(index),
            );
            continue;
        }
        let cov = PoseCov {
            pose: solution.camera_from_marker,
            cov: solution.covariance,
        };
        poses.push(ObservedPoseOut {
            link: link.name.clone(),
            time: format_ns(time_ns),
            pose: PoseOut::from(&solution.camera_from_marker),
            sigma: SigmaOut::from(&cov),
            reprojection_rms_px: solution.rms_px,
            points: solution.points,
            ambiguity_ratio: solution.ambiguity_ratio,
            rejected_points: solution.rejected_points.clone(),
        });
        items.push(crate::intake::solved_item(
            index, link.link, time_ns, &solution,
        ));
    }
    if problems.is_empty() {
        Ok((items, poses))
    } else {
        Err(problems)
    }
}

/// `POST /api/v1/calibration/hand-eye`.
#[utoipa::path(post, path = "/calibration/hand-eye", tag = "calibration",
    request_body(content = HandEyeIn, description = "The motions of the station: `A_i X = X B_i`"),
    responses(
        (status = 200, description = "X with its residuals and the motions' spread", body = HandEyeOut),
        (status = 400, description = "Malformed JSON", body = ErrorBody),
        (status = 422, description = "An invalid pose, or motions that cannot determine X (too few, too small, inconsistent, parallel axes)", body = ErrorBody),
    ),
    security(("bearer" = ["admin"])))]
pub(crate) async fn post_hand_eye(
    State(app): State<AppState>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<HandEyeOut>, ApiError> {
    let bytes = read_body(body, &headers, app.limits.max_body_bytes).await?;
    let input: HandEyeIn = parse_json_body(&bytes)?;
    let out = blocking(move || input.solve()).await??;
    Ok(Json(out))
}
