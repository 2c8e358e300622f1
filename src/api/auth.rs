//! Bearer tokens: `Authorization: Bearer <token>`, checked against the SHA-256 hashes of the
//! configuration, each with scopes `read`, `ingest`, `admin`. Without configured tokens every
//! request is accepted (the server then listens on loopback only; see [`crate::api::App`]).
//! `/healthz` is open to all: health checks carry no token, and it tells only whether the
//! service works. So are the dashboard's page and files (`/`, `/assets/...`): a browser cannot
//! put a token on a page load, and they hold no data (the page sends the token with its API
//! calls).

use super::error::ApiError;
use crate::config::{Scope, TokenSpec};
use axum::extract::Request;
use axum::http::{Method, StatusCode, header};
use axum::middleware::Next;
use axum::response::Response;
use sha2::{Digest, Sha256};
use std::sync::Arc;

/// The scope a request needs: `ingest` to post samples, `admin` to change references and
/// calibrations, `read` for the rest.
pub fn required_scope(method: &Method, path: &str) -> Scope {
    let is_write = matches!(
        *method,
        Method::POST | Method::PUT | Method::DELETE | Method::PATCH
    );
    if !is_write {
        Scope::Read
    } else if path.ends_with("/samples") || path.ends_with("/observations") {
        Scope::Ingest
    } else {
        Scope::Admin
    }
}

/// The lowercase hex SHA-256 of a token.
pub fn sha256_hex(token: &str) -> String {
    hex::encode(Sha256::digest(token.as_bytes()))
}

/// Checks the bearer token of a request against the configured tokens.
pub async fn require_token(
    tokens: Arc<Vec<TokenSpec>>,
    request: Request,
    next: Next,
) -> Result<Response, ApiError> {
    let path = request.uri().path();
    if tokens.is_empty() || path == "/healthz" || super::dashboard::is_dashboard_path(path) {
        return Ok(next.run(request).await);
    }
    let given = request
        .headers()
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "))
        .map(str::trim);
    let Some(given) = given else {
        return Err(ApiError::new(
            StatusCode::UNAUTHORIZED,
            "unauthorized",
            "this request needs `Authorization: Bearer <token>`",
        ));
    };
    let hash = sha256_hex(given);
    let Some(token) = tokens.iter().find(|t| t.sha256_hex == hash) else {
        return Err(ApiError::new(
            StatusCode::UNAUTHORIZED,
            "unauthorized",
            "the token is not known",
        ));
    };
    let needed = required_scope(request.method(), request.uri().path());
    if !token.scopes.contains(&needed) && !token.scopes.contains(&Scope::Admin) {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            "forbidden",
            format!(
                "token `{}` lacks the `{}` scope this request needs",
                token.name,
                match needed {
                    Scope::Read => "read",
                    Scope::Ingest => "ingest",
                    Scope::Admin => "admin",
                }
            ),
        ));
    }
    Ok(next.run(request).await)
}
