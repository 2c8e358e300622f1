//! An observation: one camera image of one marker, the pixel of each marker point found. The
//! detector (`brokenray detect`) writes it, `POST /observations` reads it, the simulator's
//! feed posts it (`docs/interface.md`, "HTTP API", `POST /api/v1/observations`).

use super::time_schema;
use serde::{Deserialize, Serialize};
use serde_json::Value;

/// One camera image of one marker: the measured pixel of each marker point.
#[derive(Debug, Clone, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ObservationIn {
    /// The camera's frame.
    pub camera: String,
    /// The marker's frame.
    pub marker: String,
    /// RFC 3339 text or integer nanoseconds.
    #[schema(schema_with = time_schema)]
    pub time: Value,
    /// Pixels `[u, v]`, in the marker's point order (or paired with `ids`).
    pub points_px: Vec<[f64; 2]>,
    /// The marker point id of each pixel, when not all points are seen or the order differs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ids: Option<Vec<u32>>,
    /// Each pixel's standard deviation (px), when a detector measured it: the point is
    /// weighted by it, the camera's `pixel_sigma` added in quadrature.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma_px: Option<Vec<f64>>,
}
