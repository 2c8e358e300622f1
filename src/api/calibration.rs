//! `POST /api/v1/calibration/camera`: a camera's intrinsics and distortion from the plate
//! points detected in several views (computes, stores nothing, like hand-eye), one at a time,
//! stopped when its client leaves. The request and result are [`crate::wire`]'s.

use super::AppState;
use super::error::{ApiError, ErrorBody};
use super::ingest::read_body;
use super::parse_json_body;
use crate::wire::{CameraCalibrationIn, CameraCalibrationOut};
use axum::Json;
use axum::body::Body;
use axum::extract::State;
use axum::http::HeaderMap;

/// How long a calibration waits for the one running before it is answered 503 `busy`.
const CALIBRATION_WAIT: std::time::Duration = std::time::Duration::from_secs(30);

/// Sets its flag when dropped: the work of a request that is gone stops.
struct StopOnDrop(std::sync::Arc<std::sync::atomic::AtomicBool>);

impl Drop for StopOnDrop {
    fn drop(&mut self) {
        self.0.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}

/// `POST /api/v1/calibration/camera`.
#[utoipa::path(post, path = "/calibration/camera", tag = "calibration",
    request_body(content = CameraCalibrationIn, description = "The plate and the points found in each view"),
    responses(
        (status = 200, description = "The intrinsics with their sigmas, covariance, each view's fit and warnings", body = CameraCalibrationOut),
        (status = 400, description = "Malformed JSON", body = ErrorBody),
        (status = 422, description = "An invalid field (`invalid_request`), or views that cannot calibrate the camera (`calibration_refused`, with the reason: over 200 views or 40000 points among them)", body = ErrorBody),
        (status = 503, description = "Another calibration ran for 30 s while this one waited (`busy`)", body = ErrorBody),
    ),
    security(("bearer" = ["admin"])))]
pub(crate) async fn post_camera_calibration(
    State(app): State<AppState>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<CameraCalibrationOut>, ApiError> {
    let bytes = read_body(body, &headers, app.limits.max_body_bytes).await?;
    let input: CameraCalibrationIn = parse_json_body(&bytes)?;
    // One calibration at a time: each may hold a core for seconds.
    let _slot = super::take_slot(
        &app.calibration_slots,
        CALIBRATION_WAIT,
        "camera calibration",
    )
    .await?;
    // When the request is dropped (the client left, or its time ran out), the work stops.
    let cancel = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let _stop = StopOnDrop(std::sync::Arc::clone(&cancel));
    let (_, out) = super::vision::blocking(move || input.solve(Some(cancel))).await??;
    Ok(Json(out))
}
