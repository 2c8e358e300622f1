//! What the cameras see: the newest frame of every camera and what was found in it, kept in
//! memory (`GET /api/v1/cameras`, `/cameras/{name}/frame`, `/cameras/{name}/detections`), and
//! the frames the archive keeps (`/cameras/{name}/frames`, [`crate::archive`]).
//!
//! The newest frame of each camera is the intake's ([`crate::intake::Intake::latest`]): one
//! slot per configured camera, each holding one frame, what was found in it and at most one
//! PNG, encoded on the first request, off the async workers.

use super::AppState;
use super::error::{ApiError, ErrorBody, ErrorCode};
use super::frames::{FrameOut, NotFoundCode};
use crate::archive::{ArchiveReason, FrameArchive};
use crate::clock::format_ns;
use crate::intake::LatestFrame;
use axum::Json;
use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use std::sync::Arc;

/// One marker in a camera's newest frame, in short.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct CameraMarkerOut {
    /// The marker's frame.
    pub marker: String,
    /// The measured link `<camera>_from_<marker>`.
    pub link: String,
    /// Whether its pose was measured.
    pub found: bool,
    /// Why it was not found (a stable code).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason_code: Option<NotFoundCode>,
    /// Why it was not found (a sentence).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Reprojection RMS when found (px).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reprojection_rms_px: Option<f64>,
}

/// A camera's newest frame, in short.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct CameraFrameOut {
    /// Measurement time (RFC 3339).
    pub time: String,
    /// How long before the server's clock now it was taken (s).
    pub age_s: f64,
    /// Discs detected in the searched part of the frame.
    pub blobs: usize,
    /// Each marker of a measured link of the camera.
    pub markers: Vec<CameraMarkerOut>,
}

/// A camera and its newest frame.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct CameraOut {
    /// The camera's frame.
    pub name: String,
    /// Image width (px).
    pub width_px: u32,
    /// Image height (px).
    pub height_px: u32,
    /// The markers it sees through measured links.
    pub markers: Vec<String>,
    /// Its newest frame; absent before the first.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frame: Option<CameraFrameOut>,
    /// When the service takes its frames itself (`[cameras.source]`): the source's state.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub source: Option<super::sources::SourceOut>,
    /// When the installation names the camera's calibration report (`calibration_report`):
    /// where to fetch it, `/api/v1/cameras/{name}/calibration-report`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calibration_report: Option<String>,
}

/// Every camera.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct CamerasOut {
    /// In installation order.
    pub cameras: Vec<CameraOut>,
}

/// `GET /api/v1/cameras`.
#[utoipa::path(get, path = "/cameras", tag = "cameras",
    responses((status = 200, description = "Every camera with its newest frame's time and what was found in it", body = CamerasOut)),
    security(("bearer" = ["read"])))]
pub(super) async fn list_cameras(State(app): State<AppState>) -> Json<CamerasOut> {
    let now_ns = app.service.now_ns();
    let observer = app.service.observer();
    let cameras = app
        .service
        .installation()
        .model
        .cameras
        .iter()
        .map(|c| CameraOut {
            name: c.frame.clone(),
            width_px: c.intrinsics.width_px,
            height_px: c.intrinsics.height_px,
            markers: observer
                .links()
                .filter(|l| l.camera_frame == c.frame)
                .map(|l| l.marker_frame.clone())
                .collect(),
            source: app
                .sources
                .iter()
                .find(|s| s.source.camera == c.frame)
                .map(|s| s.report().into()),
            calibration_report: report_file(&app, &c.frame)
                .map(|_| format!("/api/v1/cameras/{}/calibration-report", c.frame)),
            frame: app.intake.latest(&c.frame).map(|l| CameraFrameOut {
                time: format_ns(l.frame.time_ns),
                age_s: (now_ns - l.frame.time_ns) as f64 / 1e9,
                blobs: l.frame.blobs,
                markers: (l.frame.markers.iter())
                    .map(|m| {
                        let why = m.result.as_ref().err();
                        CameraMarkerOut {
                            marker: m.marker.clone(),
                            link: m.link.clone(),
                            found: why.is_none(),
                            reason_code: why.map(NotFoundCode::from),
                            reason: why.map(ToString::to_string),
                            reprojection_rms_px: (m.result.as_ref().ok())
                                .map(|f| f.solution.rms_px),
                        }
                    })
                    .collect(),
            }),
        })
        .collect();
    Json(CamerasOut { cameras })
}

/// The calibration report the installation names for `camera`.
fn report_file(app: &AppState, camera: &str) -> Option<std::path::PathBuf> {
    app.service
        .installation()
        .calibration_reports
        .iter()
        .find(|r| r.camera == camera)
        .map(|r| r.path.clone())
}

/// The largest calibration report served: far above a real one (its largest picture draws a
/// line a point), so a file named by mistake is not read whole.
const MAX_REPORT_BYTES: u64 = 64 << 20;

/// `GET /api/v1/cameras/{name}/calibration-report`.
#[utoipa::path(get, path = "/cameras/{name}/calibration-report", tag = "cameras",
    params(("name" = String, Path, description = "The camera's frame")),
    responses(
        (status = 200, description = "The HTML page `calibrate-camera --report` wrote for the camera's calibration, as the installation names it (`calibration_report`); served with a policy that lets it run no script and load nothing", content_type = "text/html"),
        (status = 404, description = "Unknown camera, or no report named for it", body = ErrorBody),
        (status = 503, description = "The page the installation names cannot be read", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_calibration_report(
    State(app): State<AppState>,
    Path(name): Path<String>,
) -> Result<Response, ApiError> {
    if app.service.installation().model.camera(&name).is_none() {
        return Err(ApiError::not_found(format!("no camera `{name}`")));
    }
    let path = report_file(&app, &name).ok_or_else(|| {
        ApiError::not_found(format!(
            "the installation names no calibration report for camera `{name}` (`calibration_report` in its `[[cameras]]`)"
        ))
    })?;
    // The server's paths are not told (`check-config` names the file).
    let unreadable = |reason: String| {
        ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            ErrorCode::FileUnavailable,
            format!(
                "camera `{name}`'s calibration report, the file its `calibration_report` names, cannot be read: {reason}"
            ),
        )
    };
    let size = tokio::fs::metadata(&path)
        .await
        .map_err(|e| unreadable(e.to_string()))?
        .len();
    if size > MAX_REPORT_BYTES {
        return Err(unreadable(format!(
            "it is {size} bytes, over the {MAX_REPORT_BYTES} served"
        )));
    }
    let page = tokio::fs::read(&path)
        .await
        .map_err(|e| unreadable(e.to_string()))?;
    Ok(super::report::report_page(Body::from(page), None))
}

/// The newest frame of a known camera, or a 404 naming what is missing.
fn latest_of(app: &AppState, name: &str) -> Result<Arc<LatestFrame>, ApiError> {
    if app.service.installation().model.camera(name).is_none() {
        return Err(ApiError::not_found(format!("no camera `{name}`")));
    }
    app.intake
        .latest(name)
        .ok_or_else(|| ApiError::not_found(format!("camera `{name}` has sent no frame yet")))
}

/// `GET /api/v1/cameras/{name}/frame`.
#[utoipa::path(get, path = "/cameras/{name}/frame", tag = "cameras",
    params(("name" = String, Path, description = "The camera's frame")),
    responses(
        (status = 200, description = "The newest frame as PNG (8 or 16 bit grey, as it came); `ETag` changes with each frame, `X-Frame-Time` is its measurement time", content_type = "image/png"),
        (status = 304, description = "The frame named by `If-None-Match` is still the newest"),
        (status = 404, description = "Unknown camera, or no frame yet", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_frame(
    State(app): State<AppState>,
    Path(name): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let latest = latest_of(&app, &name)?;
    let time_ns = latest.frame.time_ns;
    let etag = HeaderValue::from_str(&format!("\"{name}-{time_ns}\""))
        .map_err(|e| ApiError::internal(e.to_string()))?;
    if headers
        .get(header::IF_NONE_MATCH)
        .is_some_and(|v| v.as_bytes() == etag.as_bytes())
    {
        return Ok((StatusCode::NOT_MODIFIED, [(header::ETAG, etag)]).into_response());
    }
    let png = super::vision::blocking(move || {
        (latest.png()).map_err(|e| ApiError::internal(format!("encoding the frame failed: {e}")))
    })
    .await??;
    let time = HeaderValue::from_str(&format_ns(time_ns))
        .map_err(|e| ApiError::internal(e.to_string()))?;
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("image/png")),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
            (header::ETAG, etag),
            (header::HeaderName::from_static("x-frame-time"), time),
        ],
        Body::from(png),
    )
        .into_response())
}

/// `GET /api/v1/cameras/{name}/detections`.
#[utoipa::path(get, path = "/cameras/{name}/detections", tag = "cameras",
    params(("name" = String, Path, description = "The camera's frame")),
    responses(
        (status = 200, description = "The answer `POST /frames` gave for the newest frame", body = FrameOut),
        (status = 404, description = "Unknown camera, or no frame yet", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_detections(
    State(app): State<AppState>,
    Path(name): Path<String>,
) -> Result<Response, ApiError> {
    let latest = latest_of(&app, &name)?;
    Ok(Json(FrameOut::from(&*latest.frame)).into_response())
}

/// Query of `GET /cameras/{name}/frames`.
#[derive(Debug, serde::Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub(super) struct ArchivedQuery {
    /// First measurement time (RFC 3339 or integer nanoseconds); default: the oldest.
    pub from: Option<String>,
    /// Last measurement time; default: the newest.
    pub to: Option<String>,
    /// Most frames listed (default 1000, at most 10000), oldest first.
    pub limit: Option<usize>,
}

/// One archived frame.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct ArchivedOut {
    /// Measurement time (RFC 3339).
    pub time: String,
    /// Why it was kept.
    pub reason: ArchiveReason,
    /// Its size (bytes).
    pub bytes: u64,
    /// Where to fetch it: `/api/v1/cameras/{name}/frames/{time}` with the time in nanoseconds.
    pub url: String,
    /// The file in the archive directory (`<camera>/<time>_<reason>.png`).
    pub file: String,
}

/// A camera's archived frames.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct ArchivedListOut {
    /// The camera.
    pub camera: String,
    /// Oldest first.
    pub frames: Vec<ArchivedOut>,
    /// Whether more frames lie in the period than were listed.
    pub truncated: bool,
}

/// The archive, or a 404 saying none is configured; the camera must be known.
fn archive_of<'a>(app: &'a AppState, name: &str) -> Result<&'a FrameArchive, ApiError> {
    if app.service.installation().model.camera(name).is_none() {
        return Err(ApiError::not_found(format!("no camera `{name}`")));
    }
    app.intake.archive().ok_or_else(|| {
        ApiError::not_found("no frame archive is configured (`[frames] archive_dir`)")
    })
}

/// `GET /api/v1/cameras/{name}/frames`.
#[utoipa::path(get, path = "/cameras/{name}/frames", tag = "cameras",
    params(("name" = String, Path, description = "The camera's frame"), ArchivedQuery),
    responses(
        (status = 200, description = "The camera's archived frames in the period, oldest first", body = ArchivedListOut),
        (status = 404, description = "Unknown camera, or no archive configured", body = ErrorBody),
        (status = 422, description = "An unreadable time or limit", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn list_archived(
    State(app): State<AppState>,
    Path(name): Path<String>,
    super::query::Query(q): super::query::Query<ArchivedQuery>,
) -> Result<Json<ArchivedListOut>, ApiError> {
    let archive = archive_of(&app, &name)?;
    let time = |field: &str, text: &Option<String>, default: i64| match text {
        None => Ok(default),
        Some(t) => crate::clock::parse_query_time(t).map_err(|m| ApiError::invalid_field(field, m)),
    };
    let from_ns = time("from", &q.from, i64::MIN)?;
    let to_ns = time("to", &q.to, i64::MAX)?;
    if from_ns > to_ns {
        return Err(ApiError::invalid_field("from", "`from` is after `to`"));
    }
    let limit = q.limit.unwrap_or(1000);
    if limit == 0 || limit > 10_000 {
        return Err(ApiError::invalid_field(
            "limit",
            format!("limit is 1 to 10000, not {limit}"),
        ));
    }
    let mut found = archive.list(&name, from_ns, to_ns, limit + 1);
    let truncated = found.len() > limit;
    found.truncate(limit);
    Ok(Json(ArchivedListOut {
        frames: found
            .into_iter()
            .map(|f| ArchivedOut {
                time: format_ns(f.time_ns),
                reason: f.reason,
                bytes: f.bytes,
                url: format!("/api/v1/cameras/{name}/frames/{}", f.time_ns),
                file: format!(
                    "{name}/{}",
                    f.path
                        .file_name()
                        .and_then(|n| n.to_str())
                        .unwrap_or_default()
                ),
            })
            .collect(),
        camera: name,
        truncated,
    }))
}

/// `GET /api/v1/cameras/{name}/frames/{time}`.
#[utoipa::path(get, path = "/cameras/{name}/frames/{time}", tag = "cameras",
    params(
        ("name" = String, Path, description = "The camera's frame"),
        ("time" = String, Path, description = "The frame's measurement time, RFC 3339 or integer nanoseconds"),
    ),
    responses(
        (status = 200, description = "The archived frame as PNG", content_type = "image/png"),
        (status = 404, description = "Unknown camera, no archive, or no frame archived at that time", body = ErrorBody),
        (status = 422, description = "An unreadable time", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_archived(
    State(app): State<AppState>,
    Path((name, time)): Path<(String, String)>,
) -> Result<Response, ApiError> {
    let archive = archive_of(&app, &name)?;
    let time_ns =
        crate::clock::parse_query_time(&time).map_err(|m| ApiError::invalid_field("time", m))?;
    let frame = archive.get(&name, time_ns).ok_or_else(|| {
        ApiError::not_found(format!(
            "no frame of camera `{name}` at {} in the archive",
            format_ns(time_ns)
        ))
    })?;
    let bytes = tokio::fs::read(&frame.path).await.map_err(|e| {
        // The server's paths are its own business: the file's name only, and the cause in
        // the log.
        tracing::warn!(path = %frame.path.display(), error = %e, "an archived frame cannot be read");
        ApiError::not_found(format!(
            "the archived frame {} of camera `{name}` cannot be read (removed to stay under \
             the cap?)",
            frame
                .path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default()
        ))
    })?;
    Ok((
        [
            (header::CONTENT_TYPE, HeaderValue::from_static("image/png")),
            (
                header::CACHE_CONTROL,
                HeaderValue::from_static("max-age=3600"),
            ),
        ],
        Body::from(bytes),
    )
        .into_response())
}
