//! The bodies only `POST /samples` reads, and a list of field problems as the API answers it.

use super::error::{ApiError, ErrorDetail};
use crate::api::error::ErrorCode;
use crate::wire::{FieldProblem, PoseIn, Rejection, SigmaIn, time_schema};
use serde::Deserialize;
use serde_json::Value;

/// Pose-estimation quality as sent.
#[derive(Debug, Clone, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(crate) struct QualityIn {
    /// Reprojection RMS (px).
    pub reprojection_rms_px: Option<f64>,
    /// Number of points.
    pub points: Option<u32>,
}

/// One sample as sent.
#[derive(Debug, Clone, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(crate) struct SampleIn {
    /// The measured link's name.
    pub link: String,
    /// RFC 3339 text or integer nanoseconds.
    #[schema(schema_with = time_schema)]
    pub time: Value,
    /// The measured `parent_from_child`.
    pub pose: PoseIn,
    /// Per-axis sigmas (optional).
    pub sigma: Option<SigmaIn>,
    /// A full covariance, 36 numbers row-major, `[rho_mm; phi_rad]` (optional).
    pub covariance: Option<Vec<f64>>,
    /// Quality (optional).
    pub quality: Option<QualityIn>,
}

/// Turns a list of field problems into a 422.
pub(crate) fn invalid(message: impl Into<String>, problems: Vec<FieldProblem>) -> ApiError {
    ApiError::new(
        axum::http::StatusCode::UNPROCESSABLE_ENTITY,
        ErrorCode::InvalidRequest,
        message,
    )
    .with_details(
        problems
            .into_iter()
            .map(|p| ErrorDetail {
                index: p.index,
                field: Some(p.field),
                message: p.message,
            })
            .collect(),
    )
}

/// A document's rejection as an answer: text that is no JSON (400 `malformed_json`), its invalid
/// fields (422 `invalid_request`), or a computation it cannot make (422 `calibration_refused`,
/// with the reason).
impl From<Rejection> for ApiError {
    fn from(r: Rejection) -> Self {
        match r {
            Rejection::Malformed(m) => ApiError::bad_request(ErrorCode::MalformedJson, m),
            Rejection::Invalid { message, problems } => invalid(message, problems),
            e @ Rejection::Refused(_) => ApiError::new(
                axum::http::StatusCode::UNPROCESSABLE_ENTITY,
                ErrorCode::CalibrationRefused,
                e.to_string(),
            ),
        }
    }
}

/// One field's problem as an answer (422 `invalid_request`, the field named).
impl From<FieldProblem> for ApiError {
    fn from(p: FieldProblem) -> Self {
        let mut e = ApiError::invalid_field(&p.field, p.message);
        if let Some(detail) = e.details.first_mut() {
            detail.index = p.index;
        }
        e
    }
}
