//! The HTTP API (`/api/v1`, `docs/interface.md`, "HTTP API"): routes, request and response bodies,
//! errors, authentication, and the server's start and graceful stop.
//!
//! Handlers are thin: read the request, convert it to domain types (the documents shared with
//! the CLI and the feed are [`crate::wire`]'s, the rest are each endpoint's own), call the
//! [`crate::service`], convert the answer back. Every error is one [`ApiError`] with the body
//! `{"error": {"code", "message", "details": [{"index", "field", "message"}]}}`.

mod acceptance;
mod alarms;
mod auth;
mod budget;
mod calibration;
mod cameras;
mod dashboard;
mod drain;
mod dto;
mod error;
mod events;
mod fleet;
mod frames;
mod history;
mod ingest;
mod links;
mod metrics;
mod outputs;
mod query;
mod report;
mod sites;
mod sources;
mod targets;
mod vision;
pub mod vocab;
pub use targets::output_encoders;
mod webhooks;

pub(crate) use error::raw_response;
pub use error::{ApiError, ErrorCode, ErrorDetail};

use crate::service::Service;
use axum::Router;
use axum::http::StatusCode;
use serde::de::DeserializeOwned;
use std::sync::{Arc, OnceLock};
use std::time::Duration;
use tower_http::compression::CompressionLayer;
use tower_http::timeout::TimeoutLayer;
use tower_http::trace::TraceLayer;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

/// Request size limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Largest request body (bytes).
    pub max_body_bytes: usize,
    /// Most samples in one batch.
    pub max_batch_samples: usize,
}

/// What handlers share.
#[derive(Clone)]
pub struct AppState {
    /// The service.
    pub service: Service,
    /// Size limits.
    pub limits: Limits,
    /// Alarm notifications.
    pub webhooks: crate::notify::Webhooks,
    /// Frames' way in: the search's slots, the archive, the newest frame of every camera.
    pub intake: Arc<crate::intake::Intake>,
    /// The centre's side of the fleet, when this service is a centre.
    pub centre: Option<Arc<crate::fleet::Centre>>,
    /// This site's uploads, when it pushes to a centre.
    pub upstream: Option<Arc<crate::fleet::Upstream>>,
    /// Camera calibrations run at once (one: each holds a core).
    pub calibration_slots: Arc<tokio::sync::Semaphore>,
    /// The cameras the service takes frames from itself (`[cameras.source]`); empty unless
    /// `crate::app::App` started them.
    pub sources: Arc<[Arc<crate::acquire::SourceState>]>,
    /// The plant's buses (`[outputs]`); none unless `crate::app::App` started them.
    pub outputs: Arc<crate::outputs::Outputs>,
}

/// Waits up to `wait` for one of `slots`, or answers 503 `busy` naming `what`.
pub(crate) async fn take_slot(
    slots: &Arc<tokio::sync::Semaphore>,
    wait: std::time::Duration,
    what: &str,
) -> Result<tokio::sync::OwnedSemaphorePermit, ApiError> {
    match tokio::time::timeout(wait, Arc::clone(slots).acquire_owned()).await {
        Ok(Ok(permit)) => Ok(permit),
        _ => Err(ApiError::new(
            axum::http::StatusCode::SERVICE_UNAVAILABLE,
            ErrorCode::Busy,
            format!("every slot for {what} is taken; retry shortly"),
        )),
    }
}

impl AppState {
    /// The state of the HTTP adapter over `service`: starts delivering alarm transitions to the
    /// configured webhooks, and opens the frame archive when one is configured.
    pub fn new(service: Service) -> Result<Self, crate::archive::ArchiveError> {
        let server = &service.installation().server;
        let limits = Limits {
            max_body_bytes: server.max_body_bytes,
            max_batch_samples: server.max_batch_samples,
        };
        let site = &service.installation().fleet;
        Ok(Self {
            intake: Arc::new(crate::intake::Intake::new(service.clone())?),
            webhooks: crate::notify::Webhooks::start(&service, alarms::encode_alarm),
            centre: None,
            calibration_slots: Arc::new(tokio::sync::Semaphore::new(1)),
            upstream: (site.site.clone())
                .zip(site.upstream.clone())
                .map(|(site, settings)| Arc::new(crate::fleet::Upstream::new(site, settings))),
            sources: Arc::new([]),
            outputs: Arc::default(),
            service,
            limits,
        })
    }
}

/// Parses a JSON body, naming the field of any problem (400 for malformed JSON, 422 for a
/// well-formed body of the wrong shape).
pub(crate) fn parse_json_body<T: DeserializeOwned>(body: &[u8]) -> Result<T, ApiError> {
    crate::wire::parse(body).map_err(ApiError::from)
}

/// `GET /healthz`.
#[derive(Debug, serde::Serialize, utoipa::ToSchema)]
pub struct HealthOut {
    /// `ok` or `unavailable`.
    pub status: vocab::HealthStatus,
    /// The database answers.
    pub database: bool,
    /// The single writer (the pipeline task) runs and its last commit succeeded.
    pub writer: bool,
    /// What is wrong, when something is (a failing commit, a removed database file, ...).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub problem: Option<String>,
    /// On a fleet's site, what is wrong with the uploads to the centre (a stream the centre
    /// refused). The site keeps measuring and keeping what it has not sent: the answer stays
    /// 200.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub upstream_problem: Option<String>,
    /// The last time the disk budget (`[retention] disk_budget_mb`) removed rows younger than
    /// their retention, and what (rows the centre had not acknowledged among them). History
    /// was lost; the service works on: the answer stays 200.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub storage_problem: Option<String>,
    /// Why the last scheduled report (`[reports]`) could not be filed (a folder that cannot
    /// be written, a store that does not answer); tried again every ten minutes. The service
    /// works on: the answer stays 200.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reports_problem: Option<String>,
    /// What is wrong with the rig's acceptance when the installation states a procedure
    /// (`[acceptance]`): none recorded, the latest failed, due for reverification, or no longer
    /// holding after a calibration or a reset. The service works on: the answer stays 200.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub acceptance_problem: Option<String>,
    /// On a fleet's centre, the sites whose last upkeep (retention, partitions) failed, and
    /// why; the other sites' went on. The answer stays 200.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub centre_problem: Option<String>,
    /// Measured links most of whose samples never make a measurement group with the other
    /// links of their targets (exposures farther apart than `[filter] group_tolerance_ms`):
    /// no raw results are formed from them. The filtered results go on: the answer stays 200.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub grouping_problem: Option<String>,
    /// Targets whose filter no longer fits its data: the mean normalised innovation of its
    /// recent results is outside the band a fitting filter stays in (a motion model that
    /// does not suit the structure, or measurement sigmas set too small). The results go on,
    /// their sigmas not to be trusted: the answer stays 200.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub filter_problem: Option<String>,
    /// The background tasks (uploader, webhook delivery, retention, liveness, the centre's
    /// upkeep) that stopped while the service runs, and why. The service must be restarted:
    /// the answer is 503.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tasks_problem: Option<String>,
    /// True on a fleet's centre (it serves `GET /api/v1/sites`); absent otherwise. The
    /// dashboard reads it to show the fleet.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub centre: bool,
    /// The outputs on the plant's buses that are not connected or dropped alarm transitions,
    /// and why. The service measures on: the answer stays 200.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub output_problem: Option<String>,
    /// Each output on the plant's buses (`[outputs]`); absent when none is configured.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub outputs: Vec<outputs::OutputOut>,
    /// Each target's status and age now, by name. A stale target does not make the service
    /// unhealthy (the answer stays 200): alert on `targets.*.status == "stale"` or on
    /// `brokenray_target_age_seconds` instead.
    pub targets: std::collections::BTreeMap<String, TargetHealthOut>,
}

/// A target in `/healthz`.
#[derive(Debug, serde::Serialize, utoipa::ToSchema)]
pub struct TargetHealthOut {
    /// As in the target's compensation: `ok`, `stale`, `degraded`, `initializing`, ...
    pub status: crate::bank::TargetStatus,
    /// Seconds from its newest result to now on the server's clock; null before any result.
    pub age_s: Option<f64>,
}

/// `GET /healthz`: open to all (no token), for container health checks and load balancers; it
/// tells nothing but whether the service works.
#[utoipa::path(get, path = "/healthz", tag = "operations",
    responses(
        (status = 200, description = "The database answers and the writer runs", body = HealthOut),
        (status = 503, description = "The database or the writer is in trouble (the last commit failed, the database file was removed or replaced, it does not answer; `problem` says what), or a background task stopped (`tasks_problem` says which and why)", body = HealthOut),
    ),
    security(()))]
async fn healthz(
    axum::extract::State(app): axum::extract::State<AppState>,
) -> (StatusCode, axum::Json<HealthOut>) {
    let health = app.service.store().health().await;
    let alive = app.service.pipeline_alive();
    let database = health.reachable;
    let writer = alive && health.writer_ok;
    let ok = database && writer;
    let tasks_problem = app.service.tasks_problem();
    let ok = ok && tasks_problem.is_none();
    let problem = if alive {
        health.problem
    } else {
        Some("the writer is not running".to_owned())
    };
    let output_status = app.outputs.status();
    let targets = (app.service.targets_now().into_iter())
        .map(|(name, now)| {
            let health = TargetHealthOut {
                status: now.status,
                age_s: now.age_s,
            };
            (name, health)
        })
        .collect();
    (
        if ok {
            StatusCode::OK
        } else {
            StatusCode::SERVICE_UNAVAILABLE
        },
        axum::Json(HealthOut {
            status: if ok {
                vocab::HealthStatus::Ok
            } else {
                vocab::HealthStatus::Unavailable
            },
            database,
            writer,
            problem,
            upstream_problem: app.upstream.as_ref().and_then(|u| u.problem()),
            storage_problem: app.service.storage_problem(),
            reports_problem: app.service.report_problem(),
            acceptance_problem: app.service.acceptance_problem().await,
            tasks_problem,
            grouping_problem: app.service.grouping_problem(),
            filter_problem: app.service.filter_problem(),
            centre_problem: app.centre.as_ref().and_then(|c| c.upkeep_problem()),
            centre: app.centre.is_some(),
            output_problem: outputs::problem(&output_status),
            outputs: output_status.into_iter().map(Into::into).collect(),
            targets,
        }),
    )
}

/// `GET /api/v1/openapi.json`: this API's OpenAPI 3.1 document, generated from the handlers.
#[utoipa::path(get, path = "/openapi.json", tag = "operations",
    responses((status = 200, description = "The OpenAPI document of this API", body = Object)),
    security(("bearer" = ["read"])))]
async fn openapi_json() -> axum::response::Response {
    use axum::response::IntoResponse;
    (
        [(axum::http::header::CONTENT_TYPE, "application/json")],
        openapi_text(),
    )
        .into_response()
}

/// Parses the optional `from` and `to` of a query into `[from, to]` (open ends unbounded),
/// refusing a `to` before `from`.
pub fn parse_query_range(
    from: Option<&str>,
    to: Option<&str>,
) -> Result<(i64, i64), error::ApiError> {
    use error::ApiError;
    let from = match from {
        Some(f) => {
            crate::clock::parse_query_time(f).map_err(|m| ApiError::invalid_field("from", m))?
        }
        None => i64::MIN,
    };
    let to = match to {
        Some(t) => {
            crate::clock::parse_query_time(t).map_err(|m| ApiError::invalid_field("to", m))?
        }
        None => i64::MAX,
    };
    if from > to {
        return Err(ApiError::invalid_field("to", "`to` is before `from`"));
    }
    Ok((from, to))
}

/// Refuses free texts a person gave (who, a note) longer than 1000 characters, naming the
/// field.
pub fn check_texts(texts: &[(&str, Option<&str>)]) -> Result<(), ApiError> {
    for (field, text) in texts {
        if text.is_some_and(|t| t.chars().count() > 1000) {
            return Err(ApiError::invalid_field(field, "at most 1000 characters"));
        }
    }
    Ok(())
}

/// A count of a query (`limit`, `max_points`): `default` when absent, else 1 to 100000.
pub fn query_count(field: &str, value: Option<i64>, default: i64) -> Result<i64, ApiError> {
    let n = value.unwrap_or(default);
    if !(1..=100_000).contains(&n) {
        return Err(ApiError::invalid_field(
            field,
            "must be between 1 and 100000",
        ));
    }
    Ok(n)
}

/// A query parameter with a few allowed values (`source=raw|filtered`, `format=json|csv`, ...):
/// `default` when absent, else the value of the matching name; any other is refused, naming the
/// field and the choices.
pub fn query_choice<T: Copy>(
    field: &str,
    value: Option<&str>,
    default: T,
    choices: &[(&str, T)],
) -> Result<T, ApiError> {
    let Some(value) = value else {
        return Ok(default);
    };
    if let Some((_, v)) = choices.iter().find(|(name, _)| *name == value) {
        return Ok(*v);
    }
    let names: Vec<String> = choices.iter().map(|(n, _)| format!("`{n}`")).collect();
    let listed = match names.split_last() {
        Some((last, [])) => last.clone(),
        Some((last, rest)) => format!("{} or {last}", rest.join(", ")),
        None => String::new(),
    };
    Err(ApiError::invalid_field(
        field,
        format!("`{value}` is not {listed}"),
    ))
}

async fn api_not_found(uri: axum::http::Uri) -> ApiError {
    ApiError::not_found(format!("no endpoint at `{}`", uri.path()))
}

#[derive(utoipa::OpenApi)]
#[openapi(
    info(
        title = "brokenray",
        description = "Broken-ray videometrics: link poses in, filtered chain, deformation and \
                       compensation out. Units are in the field names (`_mm`, `_deg`, `_arcsec`); \
                       `a_from_b` maps frame b coordinates into frame a; quaternions are \
                       `[w, x, y, z]`; times are RFC 3339 UTC."
    ),
    modifiers(&BearerAuth),
    tags(
        (name = "ingest", description = "Link samples and raw marker observations from the measurement pipeline"),
        (name = "calibration", description = "Camera calibration (intrinsics from plate views) and station calibration (hand-eye)"),
        (name = "cameras", description = "Each camera's newest frame and what was found in it"),
        (name = "targets", description = "Compensation, history, statistics and references"),
        (name = "links", description = "Links, their samples and calibrations"),
        (name = "alarms", description = "Alarm transitions"),
        (name = "acceptance", description = "The acceptance procedure and the recorded acceptances"),
        (name = "events", description = "Live results and alarms"),
        (name = "fleet", description = "Sites uploading to a centre, and the centre's view of its fleet"),
        (name = "operations", description = "Health, metrics, this document"),
        (name = "dashboard", description = "The web dashboard's page and files (open: they hold no data)"),
    )
)]
struct ApiDoc;

/// Declares the bearer scheme the operations' `security` refers to; its scopes are `read`,
/// `ingest` and `admin`.
struct BearerAuth;

impl utoipa::Modify for BearerAuth {
    fn modify(&self, openapi: &mut utoipa::openapi::OpenApi) {
        use utoipa::openapi::security::{HttpAuthScheme, HttpBuilder, SecurityScheme};
        openapi
            .components
            .get_or_insert_default()
            .add_security_scheme(
                "bearer",
                SecurityScheme::Http(
                    HttpBuilder::new()
                        .scheme(HttpAuthScheme::Bearer)
                        .description(Some(
                            "A token from the configuration's [[auth.tokens]]; the scope each \
                         operation needs is listed in its `security`",
                        ))
                        .build(),
                ),
            );
    }
}

/// Every route, each registered with its OpenAPI operation: a handler cannot be routed without
/// appearing in the document.
fn routes() -> OpenApiRouter<AppState> {
    let api = OpenApiRouter::new()
        .routes(routes!(ingest::post_samples))
        .routes(routes!(vision::post_observations))
        .routes(routes!(frames::post_frame))
        .routes(routes!(cameras::list_cameras))
        .routes(routes!(cameras::get_frame))
        .routes(routes!(cameras::get_detections))
        .routes(routes!(cameras::get_calibration_report))
        .routes(routes!(cameras::list_archived))
        .routes(routes!(cameras::get_archived))
        .routes(routes!(vision::post_hand_eye))
        .routes(routes!(calibration::post_camera_calibration))
        .routes(routes!(targets::list_targets))
        .routes(routes!(targets::get_compensation))
        .routes(routes!(history::get_stats))
        .routes(routes!(history::get_history))
        .routes(routes!(targets::get_reference, targets::post_reference))
        .routes(routes!(targets::get_filter))
        .routes(routes!(budget::get_budget))
        .routes(routes!(report::get_report))
        .routes(routes!(acceptance::list_acceptances))
        .routes(routes!(acceptance::get_acceptance))
        .routes(routes!(acceptance::get_certificate))
        .routes(routes!(
            acceptance::post_run,
            acceptance::get_run,
            acceptance::delete_run
        ))
        .routes(routes!(acceptance::post_ready))
        .routes(routes!(targets::list_references))
        .routes(routes!(events::get_events))
        .routes(routes!(alarms::list_alarms))
        .routes(routes!(alarms::post_ack))
        .routes(routes!(webhooks::list_webhooks))
        .routes(routes!(outputs::list_outputs))
        .routes(routes!(links::list_links))
        .routes(routes!(links::list_samples))
        .routes(routes!(links::put_calibration))
        .routes(routes!(links::post_reset))
        .routes(routes!(links::list_calibrations))
        .routes(routes!(fleet::post_sync))
        .routes(routes!(fleet::list_sites))
        .routes(routes!(fleet::get_upstream))
        .routes(routes!(fleet::post_raw_request, fleet::list_raw_requests))
        .routes(routes!(fleet::cancel_raw_request))
        .routes(routes!(sites::list_site_targets))
        .routes(routes!(sites::get_site_compensation))
        .routes(routes!(sites::get_site_stats))
        .routes(routes!(sites::get_site_history))
        .routes(routes!(sites::get_site_reference))
        .routes(routes!(sites::list_site_references))
        .routes(routes!(sites::list_site_alarms))
        .routes(routes!(openapi_json));
    OpenApiRouter::with_openapi(<ApiDoc as utoipa::OpenApi>::openapi())
        .nest("/api/v1", api)
        .routes(routes!(healthz))
        .routes(routes!(metrics::get_metrics))
        .routes(routes!(dashboard::get_index))
        .routes(routes!(dashboard::get_asset))
}

/// The document, set by the first [`router`] (or [`openapi`]) from the same registrations.
static DOC: OnceLock<utoipa::openapi::OpenApi> = OnceLock::new();

/// The OpenAPI document of the API.
pub fn openapi() -> &'static utoipa::openapi::OpenApi {
    DOC.get_or_init(|| routes().split_for_parts().1)
}

/// The document as served: rendered once.
fn openapi_text() -> &'static str {
    static TEXT: OnceLock<String> = OnceLock::new();
    TEXT.get_or_init(|| {
        openapi()
            .to_pretty_json()
            .unwrap_or_else(|e| format!("{{\"error\": \"{e}\"}}"))
    })
}

/// The router of the whole service.
pub fn router(state: AppState) -> Router {
    let tokens = Arc::new(state.service.installation().auth.tokens.clone());
    let local_only = tokens.is_empty().then(|| {
        Arc::new(auth::LocalOnly::new(
            &state.service.installation().server.allowed_hosts,
        ))
    });
    let (router, doc) = routes().split_for_parts();
    // The routes are the same every time: keep the first document.
    let _ = DOC.set(doc);
    // Each operation's scope as its annotation declares it: the one source of truth.
    let scopes = Arc::new(auth::ScopeTable::from_openapi(openapi()));
    router
        .fallback(api_not_found)
        .layer(axum::middleware::from_fn(move |req, next| {
            auth::require_token(Arc::clone(&tokens), Arc::clone(&scopes), req, next)
        }))
        .layer(axum::middleware::from_fn(move |req, next| {
            auth::local_only(local_only.clone(), req, next)
        }))
        .layer(axum::extract::DefaultBodyLimit::max(
            state.limits.max_body_bytes,
        ))
        .layer(TimeoutLayer::with_status_code(
            StatusCode::REQUEST_TIMEOUT,
            Duration::from_secs(60),
        ))
        // Outside every refusal (the token's, the handler's): what a refused request did not
        // send yet is read, so that its client reads the answer instead of a broken pipe.
        .layer(axum::middleware::from_fn({
            let limit = state.limits.max_body_bytes;
            move |req, next| drain::drain_unread(limit, req, next)
        }))
        // Outside the timeout, so that its 408 gets the envelope too.
        .layer(axum::middleware::from_fn_with_state(
            state.service.metrics_handle(),
            error::json_envelope,
        ))
        .layer((
            TraceLayer::new_for_http(),
            // gzip when the client accepts it (history JSON shrinks about threefold); never the
            // event stream, whose events must not wait in a compressor's buffer.
            CompressionLayer::new(),
        ))
        .with_state(state)
}
