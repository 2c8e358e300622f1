//! `GET /metrics`: the Prometheus text exposition [`crate::telemetry`] writes.

use super::AppState;
use crate::telemetry::{Sources, render};
use axum::extract::State;
use axum::http::header;
use axum::response::IntoResponse;

/// `GET /metrics`.
#[utoipa::path(get, path = "/metrics", tag = "operations",
    responses((status = 200, description = "Prometheus text exposition", content_type = "text/plain; version=0.0.4", body = String)),
    security(("bearer" = ["read"])))]
pub(super) async fn get_metrics(State(app): State<AppState>) -> impl IntoResponse {
    let text = render(&Sources {
        service: &app.service,
        webhooks: &app.webhooks,
        outputs: &app.outputs.status(),
        archive: app.intake.archive(),
        upstream: app.upstream.as_deref(),
        cameras: &app.sources,
    });
    (
        [(
            header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        text,
    )
}
