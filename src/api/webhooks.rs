//! `GET /api/v1/webhooks`: each configured webhook's deliveries and failures (the deliveries
//! themselves are [`crate::notify`]'s).

use super::AppState;
use crate::clock::format_ns;
use crate::config::NotifyLevel;
use crate::notify::WebhookStatus;
use axum::Json;
use axum::extract::State;
use serde::Serialize;

/// A webhook as `GET /api/v1/webhooks` shows it.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct WebhookOut {
    /// Its position in `[[notify.webhooks]]`.
    pub index: usize,
    /// The URL's host and port (the rest may carry credentials).
    pub host: String,
    /// The lowest level it is told about.
    pub min_level: NotifyLevel,
    /// Notifications delivered.
    pub delivered: u64,
    /// Notifications given up after `max_attempts`, or refused by the receiver (4xx).
    pub failed: u64,
    /// Notifications dropped because the queue was full.
    pub dropped: u64,
    /// Attempts that failed (retried or given up).
    pub attempts_failed: u64,
    /// Notifications waiting or being retried.
    pub queued: u64,
    /// The last delivery (server clock).
    pub last_delivered: Option<String>,
    /// The newest attempt failed.
    pub failing: bool,
    /// The last failed attempt's error.
    pub last_error: Option<String>,
    /// When it happened (server clock).
    pub last_error_at: Option<String>,
}

impl From<WebhookStatus> for WebhookOut {
    fn from(w: WebhookStatus) -> Self {
        WebhookOut {
            index: w.index,
            host: w.host,
            min_level: w.min_level,
            delivered: w.delivered,
            failed: w.failed,
            dropped: w.dropped,
            attempts_failed: w.attempts_failed,
            queued: w.queued,
            last_delivered: w.last_delivered_ns.map(format_ns),
            failing: w.failing,
            last_error_at: w.last_error.as_ref().map(|(at, _)| format_ns(*at)),
            last_error: w.last_error.map(|(_, m)| m),
        }
    }
}

/// `GET /api/v1/webhooks`: each configured webhook's deliveries and failures.
#[utoipa::path(get, path = "/webhooks", tag = "alarms",
    responses((status = 200, description = "Each webhook's deliveries, failures and last error", body = [WebhookOut])),
    security(("bearer" = ["read"])))]
pub(super) async fn list_webhooks(State(app): State<AppState>) -> Json<Vec<WebhookOut>> {
    Json(app.webhooks.status().into_iter().map(Into::into).collect())
}
