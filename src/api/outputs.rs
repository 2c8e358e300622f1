//! `GET /api/v1/outputs`: each output on the plant's buses (MQTT, Modbus, NMEA) and what it
//! did (the outputs themselves are [`crate::outputs`]'s).

use super::AppState;
use crate::clock::format_ns;
use crate::outputs::{OutputKind, OutputStatus};
use axum::Json;
use axum::extract::State;
use serde::Serialize;

/// An output as `GET /api/v1/outputs` and `/healthz` show it.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub struct OutputOut {
    /// `mqtt`, `modbus` or `nmea`.
    pub kind: OutputKind,
    /// The broker (`host:port`), the address listened on, or the receiver.
    pub address: String,
    /// MQTT: connected to the broker; Modbus: listening; NMEA: the last send succeeded.
    pub connected: bool,
    /// Messages published (MQTT), register reads answered (Modbus), sentences sent (NMEA).
    pub sent: u64,
    /// Alarm transitions dropped because the output's queue was full, plus live events missed
    /// when the outputs fell behind them.
    pub dropped: u64,
    /// Messages waiting to be delivered.
    pub queued: u64,
    /// Modbus: clients connected now.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub clients: Option<u64>,
    /// When something was last sent (server clock).
    pub last_sent: Option<String>,
    /// The last error.
    pub last_error: Option<String>,
    /// When it happened (server clock).
    pub last_error_at: Option<String>,
}

impl From<OutputStatus> for OutputOut {
    fn from(o: OutputStatus) -> Self {
        OutputOut {
            kind: o.kind,
            address: o.address,
            connected: o.connected,
            sent: o.sent,
            dropped: o.dropped,
            queued: o.queued,
            clients: o.clients,
            last_sent: o.last_sent_ns.map(format_ns),
            last_error_at: o.last_error.as_ref().map(|(at, _)| format_ns(*at)),
            last_error: o.last_error.map(|(_, m)| m),
        }
    }
}

/// What is wrong with the outputs, for `/healthz`: those not connected, and those that dropped
/// alarm transitions.
pub(super) fn problem(outputs: &[OutputStatus]) -> Option<String> {
    use crate::words::Word as _;
    let problems: Vec<String> = outputs
        .iter()
        .filter(|o| !o.connected || o.dropped > 0)
        .map(|o| {
            let mut what = format!("{} output {}", o.kind.word(), o.address);
            if !o.connected {
                what.push_str(" is not connected");
                if let Some((_, e)) = &o.last_error {
                    what.push_str(&format!(" ({e})"));
                }
            }
            if o.dropped > 0 {
                what.push_str(&format!(
                    "{} dropped {} alarm transitions or live events",
                    if o.connected { "" } else { " and" },
                    o.dropped
                ));
            }
            what
        })
        .collect();
    (!problems.is_empty()).then(|| problems.join("; "))
}

/// `GET /api/v1/outputs`: each output and what it did.
#[utoipa::path(get, path = "/outputs", tag = "operations",
    responses((status = 200, description = "Each output on the plant's buses: connected, sent, dropped, last error", body = [OutputOut])),
    security(("bearer" = ["read"])))]
pub(super) async fn list_outputs(State(app): State<AppState>) -> Json<Vec<OutputOut>> {
    Json(app.outputs.status().into_iter().map(Into::into).collect())
}
