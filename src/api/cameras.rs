//! What the cameras see: the newest frame of every camera and what was found in it, kept in
//! memory (`GET /api/v1/cameras`, `/cameras/{name}/frame`, `/cameras/{name}/detections`).
//!
//! `POST /frames` hands each frame it answered to [`LatestFrames::offer`], which keeps it when
//! it is the camera's newest by measurement time: a move of the decoded frame and the answer,
//! nothing encoded. The PNG a client asks for is encoded once per frame, on the first request,
//! off the async workers, and cached beside the frame. Memory is bounded by the installation:
//! one slot per configured camera, each holding one frame, its answer and at most one PNG.

use super::AppState;
use super::error::{ApiError, ErrorBody};
use super::frames::{FrameOut, NotFoundCode};
use crate::clock::format_ns;
use crate::imagefile::{FrameFormat, encode};
use crate::vision::GreyImage;
use axum::Json;
use axum::body::{Body, Bytes};
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use std::sync::{Arc, Mutex, OnceLock};

/// A camera's newest frame.
struct Latest {
    time_ns: i64,
    image: GreyImage,
    answer: FrameOut,
    /// The frame as PNG, encoded on the first request for it.
    png: OnceLock<Result<Bytes, String>>,
}

/// The newest frame of every configured camera.
pub struct LatestFrames {
    slots: Vec<(String, Mutex<Option<Arc<Latest>>>)>,
}

impl LatestFrames {
    /// Empty slots for `cameras`.
    pub fn new<'a>(cameras: impl IntoIterator<Item = &'a str>) -> Self {
        Self {
            slots: cameras
                .into_iter()
                .map(|c| (c.to_owned(), Mutex::new(None)))
                .collect(),
        }
    }

    fn slot(&self, camera: &str) -> Option<&Mutex<Option<Arc<Latest>>>> {
        self.slots.iter().find(|(c, _)| c == camera).map(|(_, s)| s)
    }

    fn get(&self, camera: &str) -> Option<Arc<Latest>> {
        self.slot(camera)
            .and_then(|s| s.lock().unwrap_or_else(|p| p.into_inner()).clone())
    }

    /// Keeps a frame `POST /frames` answered when it is its camera's newest by measurement
    /// time (a late frame does not hide a newer one).
    pub(super) fn offer(&self, camera: &str, time_ns: i64, image: GreyImage, answer: FrameOut) {
        let Some(slot) = self.slot(camera) else {
            return;
        };
        let mut held = slot.lock().unwrap_or_else(|p| p.into_inner());
        if held.as_ref().is_some_and(|l| l.time_ns > time_ns) {
            return;
        }
        *held = Some(Arc::new(Latest {
            time_ns,
            image,
            answer,
            png: OnceLock::new(),
        }));
    }
}

/// One marker in a camera's newest frame, in short.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct CameraMarkerOut {
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
pub struct CameraFrameOut {
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
pub struct CameraOut {
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
}

/// Every camera.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct CamerasOut {
    /// In installation order.
    pub cameras: Vec<CameraOut>,
}

/// `GET /api/v1/cameras`.
#[utoipa::path(get, path = "/cameras", tag = "cameras",
    responses((status = 200, description = "Every camera with its newest frame's time and what was found in it", body = CamerasOut)),
    security(("bearer" = ["read"])))]
pub async fn list_cameras(State(app): State<AppState>) -> Json<CamerasOut> {
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
            frame: app.latest_frames.get(&c.frame).map(|l| CameraFrameOut {
                time: format_ns(l.time_ns),
                age_s: (now_ns - l.time_ns) as f64 / 1e9,
                blobs: l.answer.blobs,
                markers: l
                    .answer
                    .markers
                    .iter()
                    .map(|m| CameraMarkerOut {
                        marker: m.marker.clone(),
                        link: m.link.clone(),
                        found: m.found,
                        reason_code: m.reason_code,
                        reason: m.reason.clone(),
                        reprojection_rms_px: m.reprojection_rms_px,
                    })
                    .collect(),
            }),
        })
        .collect();
    Json(CamerasOut { cameras })
}

/// The newest frame of a known camera, or a 404 naming what is missing.
fn latest_of(app: &AppState, name: &str) -> Result<Arc<Latest>, ApiError> {
    if app.service.installation().model.camera(name).is_none() {
        return Err(ApiError::not_found(format!("no camera `{name}`")));
    }
    app.latest_frames
        .get(name)
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
pub async fn get_frame(
    State(app): State<AppState>,
    Path(name): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let latest = latest_of(&app, &name)?;
    let etag = HeaderValue::from_str(&format!("\"{name}-{}\"", latest.time_ns))
        .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", e.to_string()))?;
    if headers
        .get(header::IF_NONE_MATCH)
        .is_some_and(|v| v.as_bytes() == etag.as_bytes())
    {
        return Ok((StatusCode::NOT_MODIFIED, [(header::ETAG, etag)]).into_response());
    }
    let held = Arc::clone(&latest);
    let png = super::vision::blocking(move || {
        held.png
            .get_or_init(|| {
                encode(&held.image, FrameFormat::Png)
                    .map(Bytes::from)
                    .map_err(|e| e.to_string())
            })
            .clone()
            .map_err(|e| {
                ApiError::new(
                    StatusCode::INTERNAL_SERVER_ERROR,
                    "internal",
                    format!("encoding the frame failed: {e}"),
                )
            })
    })
    .await??;
    let time = HeaderValue::from_str(&format_ns(latest.time_ns))
        .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", e.to_string()))?;
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
pub async fn get_detections(
    State(app): State<AppState>,
    Path(name): Path<String>,
) -> Result<Response, ApiError> {
    let latest = latest_of(&app, &name)?;
    Ok(Json(&latest.answer).into_response())
}
