//! `GET /api/v1/events`: Server-Sent Events. Each new filtered result (at most
//! `server.events_max_hz` per target) arrives as an event `result` whose data is the
//! compensation JSON; each alarm transition arrives as an event `alarm`. A client that falls more than a few hundred events behind is dropped:
//! publishing never waits for subscribers.

use super::AppState;
use crate::service::LiveEvent;
use axum::extract::State;
use axum::response::sse::{Event, KeepAlive, Sse};
use futures::Stream;
use std::convert::Infallible;
use tokio::sync::broadcast::error::RecvError;

/// `GET /api/v1/events`.
#[utoipa::path(get, path = "/events", tag = "events",
    responses((status = 200, description = "Server-Sent Events: `result` (data: a compensation, as `GET /targets/{name}/compensation`) and `alarm` (data: an alarm transition)", content_type = "text/event-stream", body = String)),
    security(("bearer" = ["read"])))]
pub(super) async fn get_events(
    State(app): State<AppState>,
) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let rx = app.service.subscribe();
    let stop = app.service.stopping();
    let stream = futures::stream::unfold((rx, app, stop), |(mut rx, app, mut stop)| async move {
        // The stream ends when shutdown begins, so that an open dashboard never holds the
        // process.
        let received = tokio::select! {
            r = rx.recv() => r,
            _ = stop.wait_for(|s| *s) => return None,
        };
        match received {
            Ok(LiveEvent::Result {
                target,
                estimate,
                reference,
            }) => {
                let spec = app.service.installation().model.targets[target.0].clone();
                let body = super::targets::live_compensation(
                    &app.service,
                    &spec,
                    target,
                    &estimate,
                    reference.as_ref(),
                );
                let event = Event::default()
                    .event("result")
                    .json_data(body)
                    .unwrap_or_else(|_| Event::default().event("error").data("unencodable result"));
                Some((Ok(event), (rx, app, stop)))
            }
            Ok(LiveEvent::Alarm(alarm)) => {
                Some((Ok(alarm_event(&app, "alarm", &alarm)), (rx, app, stop)))
            }
            Ok(LiveEvent::Acknowledged(alarm)) => Some((
                Ok(alarm_event(&app, "acknowledgement", &alarm)),
                (rx, app, stop),
            )),
            // Too slow: drop the client rather than hold anything back.
            Err(RecvError::Lagged(_)) | Err(RecvError::Closed) => None,
        }
    });
    Sse::new(stream).keep_alive(KeepAlive::default())
}

/// An alarm transition (or its acknowledgement) as the event `kind`, the alarm as
/// `GET /api/v1/alarms` shows it.
fn alarm_event(app: &AppState, kind: &'static str, alarm: &crate::store::StoredAlarm) -> Event {
    let name = app.service.installation().model.targets[alarm.target.0]
        .name
        .clone();
    Event::default()
        .event(kind)
        .json_data(super::alarms::AlarmOut::new(name, alarm))
        .unwrap_or_else(|_| Event::default().event("error").data("unencodable alarm"))
}
