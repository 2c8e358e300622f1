//! `POST /api/v1/frames`: one camera frame in; its disc targets detected, each marker the
//! camera sees through a measured link identified and solved, and the found ones ingested as
//! link samples exactly as `/observations` does (atomic, durable before the answer).
//!
//! The frame's way in is [`crate::intake`], which camera sources take too; this module reads
//! the request, decodes the frame (on the blocking pool, in one of the intake's slots) and
//! shapes the answer.

use super::AppState;
use super::error::{ApiError, ErrorBody};
use super::ingest::{IngestResponse, read_body};
use super::query::Query;
use crate::api::error::ErrorCode;
use crate::clock::format_ns;
use crate::geometry::PoseCov;
use crate::imagefile::{FrameFileError, FrameFormat, decode};
use crate::intake::{IntakeError, MarkerTaken, TakenFrame};
use crate::model::NotFound;
use crate::wire::{PoseOut, SigmaOut};
use axum::Json;
use axum::body::Body;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode, header};
use serde::{Deserialize, Serialize};

/// Query of `POST /frames`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub(super) struct FrameQuery {
    /// The camera's frame (required).
    pub camera: Option<String>,
    /// The frame's measurement time, RFC 3339 or integer nanoseconds (required).
    pub time: Option<String>,
}

crate::words! {
    /// Why a marker was not found, as a stable code.
    pub enum NotFoundCode("reason code") {
        /// The marker declares no disc target.
        NoTarget = "no_target",
        /// No filtered or nominal pose to predict its points from.
        NoPrediction = "no_prediction",
        /// Not in front of the camera at the predicted pose.
        NotInView = "not_in_view",
        /// Too few points found near their predictions.
        TooFewPoints = "too_few_points",
        /// PnP refused the matched points.
        PnpRefused = "pnp_refused",
        /// Searched with no prior, no identification used every visible point.
        NotIdentified = "not_identified",
        /// Searched with no prior, two contradicting identifications fit.
        Ambiguous = "ambiguous",
        /// A disc was found as a point of two markers.
        SharedPoints = "shared_points",
        /// Not found near its predictions; lost, it is searched for in the whole frame again
        /// once its interval has passed.
        SearchPaced = "search_paced",
    }
}

impl From<&NotFound> for NotFoundCode {
    fn from(n: &NotFound) -> Self {
        match n {
            NotFound::NoTarget => NotFoundCode::NoTarget,
            NotFound::NoPrediction => NotFoundCode::NoPrediction,
            NotFound::NotInView => NotFoundCode::NotInView,
            NotFound::TooFewPoints { .. } => NotFoundCode::TooFewPoints,
            NotFound::Pnp(_) => NotFoundCode::PnpRefused,
            NotFound::NotIdentified { .. } => NotFoundCode::NotIdentified,
            NotFound::Ambiguous { .. } => NotFoundCode::Ambiguous,
            NotFound::SharedPoints { .. } => NotFoundCode::SharedPoints,
            NotFound::SearchPaced { .. } => NotFoundCode::SearchPaced,
        }
    }
}

/// What the frame showed of one marker.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub(super) struct FrameMarkerOut {
    /// The marker's frame.
    pub marker: String,
    /// The measured link `<camera>_from_<marker>`.
    pub link: String,
    /// Whether its pose was measured (and ingested).
    pub found: bool,
    /// The images of the disc centres, eccentricity corrected (px).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub points_px: Option<Vec<[f64; 2]>>,
    /// The point id of each.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ids: Option<Vec<u32>>,
    /// Each point's standard deviation from the detector (px).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma_px: Option<Vec<f64>>,
    /// `camera_from_marker`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pose: Option<PoseOut>,
    /// Its sigmas.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma: Option<SigmaOut>,
    /// Each point of `ids` projected with the solved pose (px): `points_px` minus these are
    /// the residuals.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reprojected_px: Option<Vec<[f64; 2]>>,
    /// Reprojection RMS (px).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reprojection_rms_px: Option<f64>,
    /// Indices (into `points_px`) left out by robust estimation.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rejected_points: Option<Vec<usize>>,
    /// Why it was not found (a sentence).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Why it was not found (a stable code).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason_code: Option<NotFoundCode>,
}

/// The answer to a frame.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub(super) struct FrameOut {
    /// The camera.
    pub camera: String,
    /// The frame's time (RFC 3339).
    pub time: String,
    /// Discs detected in the searched part of the frame.
    pub blobs: usize,
    /// The share of the frame searched (only where the predicted marker points' gates reach),
    /// summed over the polarities searched.
    pub searched_fraction: f64,
    /// Each marker of a measured link of the camera, in installation order.
    pub markers: Vec<FrameMarkerOut>,
    /// What ingesting the found markers' samples did.
    pub ingest: IngestResponse,
}

/// How long a frame waits for a decoding slot before it is answered 503 `busy`.
const DECODE_WAIT: std::time::Duration = std::time::Duration::from_secs(5);

/// `POST /api/v1/frames`.
#[utoipa::path(post, path = "/frames", tag = "ingest",
    params(FrameQuery),
    request_body(content = Vec<u8>, description = "The frame: PNG, JPEG, TIFF or binary PGM, 8 or 16 bit (colour taken as its luma), the camera's size",
        content_type = "image/png"),
    responses(
        (status = 200, description = "Markers found or not (each with the reason); found ones durably stored as samples", body = FrameOut),
        (status = 409, description = "A sample differs from the one stored at the same link and time", body = ErrorBody),
        (status = 413, description = "Body over `max_body_bytes`", body = ErrorBody),
        (status = 415, description = "Not PNG, JPEG, TIFF or PGM", body = ErrorBody),
        (status = 422, description = "Unknown camera, missing or unbelievable time, undecodable data or a size other than the camera's (each named); nothing was stored", body = ErrorBody),
        (status = 503, description = "The writer is not available, or every decoding slot stayed taken for 5 s (`busy`)", body = ErrorBody),
    ),
    security(("bearer" = ["ingest"])))]
pub(super) async fn post_frame(
    State(app): State<AppState>,
    Query(q): Query<FrameQuery>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<FrameOut>, ApiError> {
    let content_type = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    let format = FrameFormat::from_content_type(content_type).ok_or_else(|| {
        let accepted: Vec<&str> = FrameFormat::ALL.iter().map(|f| f.content_type()).collect();
        ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            ErrorCode::UnsupportedMediaType,
            format!(
                "a frame is sent as {}, not `{content_type}`",
                accepted.join(", ")
            ),
        )
    })?;
    let camera = q.camera.ok_or_else(|| {
        ApiError::invalid_field("camera", "the query names no camera (`?camera=C1`)")
    })?;
    let q_camera = camera.clone();
    let size = app
        .service
        .observer()
        .camera(&camera)
        .map(|c| (c.width_px, c.height_px))
        .map_err(|e| ApiError::invalid_field(e.field, e.message))?;
    let text = q.time.ok_or_else(|| {
        ApiError::invalid_field("time", "the query gives no measurement time (`&time=...`)")
    })?;
    let latest = crate::clock::latest_accepted_ns(
        app.service.now_ns(),
        app.service.installation().server.max_future_s,
    );
    let time_ns = crate::clock::parse_query_time(&text)
        .and_then(|t| crate::clock::accepted_time(t, latest))
        .map_err(|m| ApiError::invalid_field("time", m))?;
    let bytes = read_body(body, &headers, app.limits.max_body_bytes).await?;
    // At most a frame a core in decoding and search; the rest wait a little, then 503.
    let slot = app.intake.decode_slot(DECODE_WAIT).await?;
    let image = super::vision::blocking(move || {
        decode(&bytes, format, Some(size)).map_err(|e| {
            ApiError::invalid_field(
                "body",
                match e {
                    FrameFileError::WrongSize {
                        width_px,
                        height_px,
                        ..
                    } => format!(
                        "the frame is {width_px} x {height_px} px but camera {camera} is {} x {} px",
                        size.0, size.1
                    ),
                    other => other.to_string(),
                },
            )
        })
    })
    .await??;
    let frame = app.intake.take(&q_camera, time_ns, image, slot).await?;
    Ok(Json(FrameOut::from(&*frame)))
}

impl From<IntakeError> for ApiError {
    fn from(e: IntakeError) -> Self {
        match e {
            IntakeError::Refused { field, message } => ApiError::invalid_field(field, message),
            IntakeError::Busy => ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                ErrorCode::Busy,
                IntakeError::Busy.to_string(),
            ),
            IntakeError::Failed(m) => ApiError::internal(m),
            IntakeError::Ingest(e) => e.into(),
        }
    }
}

impl From<&MarkerTaken> for FrameMarkerOut {
    fn from(m: &MarkerTaken) -> Self {
        let found = m.result.as_ref().ok();
        let why = m.result.as_ref().err();
        FrameMarkerOut {
            marker: m.marker.clone(),
            link: m.link.clone(),
            found: found.is_some(),
            points_px: found.map(|f| f.points_px.clone()),
            ids: found.map(|f| f.ids.clone()),
            sigma_px: found.map(|f| f.sigma_px.clone()),
            pose: found.map(|f| PoseOut::from(&f.solution.camera_from_marker)),
            sigma: found.map(|f| {
                SigmaOut::from(&PoseCov {
                    pose: f.solution.camera_from_marker,
                    cov: f.solution.covariance,
                })
            }),
            reprojected_px: found.map(|f| f.reprojected_px.clone()),
            reprojection_rms_px: found.map(|f| f.solution.rms_px),
            rejected_points: found.map(|f| f.solution.rejected_points.clone()),
            reason: why.map(ToString::to_string),
            reason_code: why.map(NotFoundCode::from),
        }
    }
}

impl From<&TakenFrame> for FrameOut {
    fn from(f: &TakenFrame) -> Self {
        FrameOut {
            camera: f.camera.clone(),
            time: format_ns(f.time_ns),
            blobs: f.blobs,
            searched_fraction: f.searched_fraction,
            markers: f.markers.iter().map(FrameMarkerOut::from).collect(),
            ingest: f.ingest.clone().into(),
        }
    }
}
