//! The API's one error type: a status code and the JSON body
//! `{"error": {"code": "...", "message": "...", "details": [...]}}`.

use crate::service::{ItemProblem, ServiceError};
use axum::Json;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::Serialize;

/// One detail of an error: the item and field concerned.
#[derive(Debug, Clone, PartialEq, Serialize, utoipa::ToSchema)]
pub struct ErrorDetail {
    /// Index of the item in the request (for NDJSON, the line's index among the items).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub index: Option<usize>,
    /// The field concerned, as a path (`pose.q_wxyz`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
    /// What is wrong.
    pub message: String,
}

impl From<ItemProblem> for ErrorDetail {
    fn from(p: ItemProblem) -> Self {
        Self {
            index: p.index,
            field: p.field,
            message: p.message,
        }
    }
}

/// At most this many details are listed in an error answer; the rest are counted
/// (`details_omitted`), so that a body of junk cannot make an answer larger than itself.
pub(super) const MAX_DETAILS: usize = 100;

/// The longest detail message (characters); a longer one is cut (it may quote a value sent).
const MAX_DETAIL_CHARS: usize = 300;

crate::words! {
    /// The stable machine-readable code of every error answer (`error.code`). Serialised as its
    /// snake_case name; `docs/interface.md` lists them all.
    #[derive()]
    pub enum ErrorCode("error code") {
        /// The request is not what the endpoint takes (a framework refusal without more to say).
        BadRequest = "bad_request",
        /// The request line or headers do not parse as HTTP.
        MalformedRequest = "malformed_request",
        /// The body is not JSON, or not UTF-8.
        MalformedJson = "malformed_json",
        /// The body is not in its stated encoding (a fleet upload that is not zstd or not its JSON).
        MalformedBody = "malformed_body",
        /// The body could not be read to its end (the client stopped sending).
        UnreadableBody = "unreadable_body",
        /// No token, or one the service does not know.
        Unauthorized = "unauthorized",
        /// The token lacks the scope, or does not speak for this site.
        Forbidden = "forbidden",
        /// The `Host` header is not one the service answers to.
        HostNotAllowed = "host_not_allowed",
        /// A browser request from another origin.
        OriginNotAllowed = "origin_not_allowed",
        /// No such route, target, link, camera, alarm or site.
        NotFound = "not_found",
        /// The route exists, the method does not.
        MethodNotAllowed = "method_not_allowed",
        /// The request's headers did not arrive in time.
        RequestTimeout = "request_timeout",
        /// The request contradicts what is stored (a duplicate with other values).
        Conflict = "conflict",
        /// The body exceeds its limit.
        PayloadTooLarge = "payload_too_large",
        /// More items than `[server] max_batch_samples`.
        BatchTooLarge = "batch_too_large",
        /// A `Content-Type` the endpoint does not take.
        UnsupportedMediaType = "unsupported_media_type",
        /// A field has a value the endpoint refuses; `details` name it.
        InvalidRequest = "invalid_request",
        /// Samples refused item by item; `details` name each.
        InvalidSamples = "invalid_samples",
        /// The calibration could not be computed from what was sent.
        CalibrationRefused = "calibration_refused",
        /// The link is measured, not calibrated.
        NotCalibrated = "not_calibrated",
        /// The request's headers exceed their limit.
        HeadersTooLarge = "headers_too_large",
        /// The database does not answer or a commit failed; nothing was stored.
        StorageUnavailable = "storage_unavailable",
        /// The database refused a value; nothing was stored.
        ValueRefused = "value_refused",
        /// Every slot for this kind of work is taken; retry shortly.
        Busy = "busy",
        /// A site's upload does not follow what the centre holds of its stream.
        OutboxChanged = "outbox_changed",
        /// A site's outbox generation descends from none the centre knows.
        GenerationUnknown = "generation_unknown",
        /// A site's commits went back within one generation (a restored copy).
        CommitsWentBack = "commits_went_back",
        /// A site uploads in an outbox generation that a later one, restored from a copy of
        /// its database, supersedes.
        GenerationSuperseded = "generation_superseded",
        /// The writer is not running.
        WriterStopped = "writer_stopped",
        /// The service is stopping.
        ShuttingDown = "shutting_down",
        /// A file the installation names (a camera's calibration report) cannot be read.
        FileUnavailable = "file_unavailable",
        /// The viewer could not be reached or written to.
        VisualisationFailed = "visualisation_failed",
        /// Something that should not fail did; the message says what.
        Internal = "internal",
    }
}

impl ErrorCode {
    /// Whether a server error of this code is the service failing, to be logged: `busy` is
    /// the service full, and a flood of them is no error.
    fn is_failure(self) -> bool {
        self != ErrorCode::Busy
    }

    /// Whether a server error's message of this code is written for the client (what is
    /// full, which camera's file cannot be read, never a server's path); other server errors
    /// say nothing of the internals.
    fn message_is_for_clients(self) -> bool {
        matches!(self, ErrorCode::Busy | ErrorCode::FileUnavailable)
    }
}

/// An error answer.
#[derive(Debug, Clone, PartialEq)]
pub struct ApiError {
    /// The HTTP status.
    pub status: StatusCode,
    /// A stable machine-readable code (`invalid_samples`, `conflict`, `not_found`, ...).
    pub code: ErrorCode,
    /// A sentence for people.
    pub message: String,
    /// The items and fields concerned (at most `MAX_DETAILS`, 100).
    pub details: Vec<ErrorDetail>,
    /// Details left out past `MAX_DETAILS`.
    pub details_omitted: usize,
}

/// The body of every error answer.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct ErrorBody {
    /// The error.
    pub error: ErrorContent,
}

/// What went wrong.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct ErrorContent {
    /// A stable machine-readable code (`invalid_samples`, `conflict`, `not_found`, ...).
    pub code: ErrorCode,
    /// A sentence for people.
    pub message: String,
    /// The items and fields concerned: the first hundred.
    pub details: Vec<ErrorDetail>,
    /// How many details were left out past the first hundred (absent when none).
    #[serde(skip_serializing_if = "is_zero")]
    pub details_omitted: usize,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// The most characters of an error's message: enough for every sentence the API makes,
/// short of a 60 KB name a request may carry and the message would echo.
pub(crate) const MAX_MESSAGE_CHARS: usize = 1000;

impl ApiError {
    /// A new error without details; a message that echoes a long name from a request is cut
    /// to a thousand characters.
    pub fn new(status: StatusCode, code: ErrorCode, message: impl Into<String>) -> Self {
        let mut message = message.into();
        if let Some((i, _)) = message.char_indices().nth(MAX_MESSAGE_CHARS) {
            message.truncate(i);
            message.push_str("...");
        }
        Self {
            status,
            code,
            message,
            details: Vec::new(),
            details_omitted: 0,
        }
    }

    /// Adds details: the first `MAX_DETAILS` (100), each message cut to a few hundred characters;
    /// the others are counted.
    pub fn with_details(mut self, mut details: Vec<ErrorDetail>) -> Self {
        if details.len() > MAX_DETAILS {
            self.details_omitted += details.len() - MAX_DETAILS;
            details.truncate(MAX_DETAILS);
        }
        for d in &mut details {
            if let Some((i, _)) = d.message.char_indices().nth(MAX_DETAIL_CHARS) {
                d.message.truncate(i);
                d.message.push_str("...");
            }
        }
        self.details = details;
        self
    }

    /// The message with its details, one line each (for the command line).
    pub fn describe(&self) -> String {
        let mut text = self.message.clone();
        for d in &self.details {
            text.push_str("\n  ");
            if let Some(i) = d.index {
                text.push_str(&format!("[{i}] "));
            }
            if let Some(f) = &d.field {
                text.push_str(&format!("{f}: "));
            }
            text.push_str(&d.message);
        }
        text
    }

    /// 400 Bad Request.
    pub fn bad_request(code: ErrorCode, message: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, code, message)
    }

    /// 500: something that should not fail did (the message says what).
    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            ErrorCode::Internal,
            message,
        )
    }

    /// 404 Not Found.
    pub fn not_found(message: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, ErrorCode::NotFound, message)
    }

    /// 422 with one detail naming a field.
    pub fn invalid_field(field: &str, message: impl Into<String>) -> Self {
        let message = message.into();
        Self::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            ErrorCode::InvalidRequest,
            format!("`{field}`: {message}"),
        )
        .with_details(vec![ErrorDetail {
            index: None,
            field: Some(field.to_owned()),
            message,
        }])
    }
}

/// A whole HTTP/1.1 response carrying the error envelope, for the answers the connection
/// layer writes itself (before any handler runs), closing the connection. The caller counts
/// it.
pub(crate) fn raw_response(
    status: StatusCode,
    code: ErrorCode,
    message: &str,
    field: Option<&str>,
) -> Vec<u8> {
    let body = serde_json::json!({"error": {
        "code": code.name(),
        "message": message,
        "details": field.map_or_else(Vec::new, |f| vec![serde_json::json!({"field": f, "message": message})]),
    }})
    .to_string();
    format!(
        "HTTP/1.1 {} {}\r\ncontent-type: application/json\r\ncontent-length: {}\r\nconnection: close\r\n\r\n{body}",
        status.as_str(),
        status.canonical_reason().unwrap_or(""),
        body.len()
    )
    .into_bytes()
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let failed = self.status.is_server_error() && self.code.is_failure();
        if failed {
            // Logged once here; the body says nothing of the internals.
            tracing::error!(code = self.code.name(), message = %self.message, "request failed");
        }
        let message = if failed && !self.code.message_is_for_clients() {
            "the service could not complete the request; nothing of it was stored".to_owned()
        } else {
            self.message
        };
        (
            self.status,
            Json(ErrorBody {
                error: ErrorContent {
                    code: self.code,
                    message,
                    details: self.details,
                    details_omitted: self.details_omitted,
                },
            }),
        )
            .into_response()
    }
}

impl From<ServiceError> for ApiError {
    fn from(e: ServiceError) -> Self {
        match e {
            ServiceError::Invalid { message, problems } => ApiError::new(
                StatusCode::UNPROCESSABLE_ENTITY,
                ErrorCode::InvalidRequest,
                message,
            )
            .with_details(problems.into_iter().map(Into::into).collect()),
            ServiceError::Conflict { message, problems } => {
                ApiError::new(StatusCode::CONFLICT, ErrorCode::Conflict, message)
                    .with_details(problems.into_iter().map(Into::into).collect())
            }
            ServiceError::NotFound(m) => ApiError::not_found(m),
            ServiceError::Storage(crate::store::StoreError::ValueRefused(m)) => ApiError::new(
                StatusCode::UNPROCESSABLE_ENTITY,
                ErrorCode::ValueRefused,
                format!("the database refuses a value of the request: {m}"),
            ),
            // The same upload is refused every time: the site must stop that stream, not retry.
            ServiceError::Storage(e @ crate::store::StoreError::UploadRefused(_)) => ApiError::new(
                StatusCode::UNPROCESSABLE_ENTITY,
                ErrorCode::InvalidRequest,
                e.to_string(),
            ),
            // Neither a corrupted row nor a defect goes away with a retry.
            ServiceError::Storage(
                e @ (crate::store::StoreError::Malformed(_) | crate::store::StoreError::Defect(_)),
            ) => ApiError::internal(e.to_string()),
            ServiceError::Storage(e) => ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                ErrorCode::StorageUnavailable,
                e.to_string(),
            ),
            ServiceError::CommitFailed(m) => ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                ErrorCode::StorageUnavailable,
                m,
            ),
            ServiceError::WriterStopped => ApiError::new(
                StatusCode::INTERNAL_SERVER_ERROR,
                ErrorCode::WriterStopped,
                "the writer stopped before answering",
            ),
            ServiceError::Viz(e) => ApiError::new(
                StatusCode::INTERNAL_SERVER_ERROR,
                ErrorCode::VisualisationFailed,
                e.to_string(),
            ),
            ServiceError::ShuttingDown => ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                ErrorCode::ShuttingDown,
                "the service is shutting down",
            ),
        }
    }
}

impl From<crate::store::StoreError> for ApiError {
    fn from(e: crate::store::StoreError) -> Self {
        ServiceError::Storage(e).into()
    }
}

/// The stable code of an error status that a layer below the handlers answered.
fn code_of(status: StatusCode) -> ErrorCode {
    match status.as_u16() {
        401 => ErrorCode::Unauthorized,
        403 => ErrorCode::Forbidden,
        404 => ErrorCode::NotFound,
        405 => ErrorCode::MethodNotAllowed,
        408 => ErrorCode::RequestTimeout,
        409 => ErrorCode::Conflict,
        413 => ErrorCode::PayloadTooLarge,
        415 => ErrorCode::UnsupportedMediaType,
        422 => ErrorCode::InvalidRequest,
        431 => ErrorCode::HeadersTooLarge,
        s if s >= 500 => ErrorCode::Internal,
        _ => ErrorCode::BadRequest,
    }
}

/// Puts every error answer into the one envelope: answers of the framework and its layers
/// (a query string that does not parse, a method not allowed, a body over the limit, a request
/// timeout) come with a plain-text or empty body; this rewrites them as `{"error": {...}}`.
/// Every refusal that passes (the handlers' and the framework's) is counted here, once. Query strings are read by [`super::query::Query`], whose
/// refusals are already ours.
pub(super) async fn json_envelope(
    axum::extract::State(metrics): axum::extract::State<std::sync::Arc<crate::service::Metrics>>,
    request: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    let response = next.run(request).await;
    let status = response.status();
    if status.is_client_error() || status.is_server_error() {
        metrics.count_rejection(status.as_u16());
    }
    let is_json = response
        .headers()
        .get(axum::http::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return response;
    }
    let allow = response.headers().get(axum::http::header::ALLOW).cloned();
    // These bodies are short texts written by the framework.
    let text = match axum::body::to_bytes(response.into_body(), 64 * 1024).await {
        Ok(b) => String::from_utf8_lossy(&b).trim().to_owned(),
        Err(_) => String::new(),
    };
    let message = if text.is_empty() {
        status
            .canonical_reason()
            .unwrap_or("the request failed")
            .to_owned()
    } else {
        text.clone()
    };
    let mut error = ApiError::new(status, code_of(status), message);
    if status == StatusCode::METHOD_NOT_ALLOWED {
        let allowed = allow
            .as_ref()
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_owned();
        error.message = format!("this path does not take that method (allowed: {allowed})");
    }
    let mut response = error.into_response();
    if let Some(allow) = allow {
        response
            .headers_mut()
            .insert(axum::http::header::ALLOW, allow);
    }
    response
}
