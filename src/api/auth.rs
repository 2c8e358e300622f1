//! Bearer tokens: `Authorization: Bearer <token>`, checked against the SHA-256 hashes of the
//! configuration, each with scopes `read`, `ingest`, `admin`, `sync` (a site's uploads to the
//! centre, for the token's own site only; `admin` does not include it). Without configured tokens every
//! request is accepted (the server then listens on loopback only; see [`crate::app::App`]).
//! The scope each route needs is declared once, in its OpenAPI annotation, and enforced from
//! the document ([`ScopeTable`]). `/healthz` is open to all (`security(())`): health checks carry
//! no token, and it tells only whether the service works and how old each target's data is. So
//! are the dashboard's page and files (`/`, `/assets/...`): a browser cannot put a token on a
//! page load, and they hold no data (the page sends the token with its API calls).

use super::error::ApiError;
use crate::api::error::ErrorCode;
use crate::config::{Scope, TokenSpec};
use axum::extract::Request;
use axum::http::{Method, StatusCode, header};
use axum::middleware::Next;
use axum::response::Response;
use std::collections::HashMap;
use std::sync::Arc;

/// The scope of every operation, read from the OpenAPI document: each handler declares its
/// scope once, in its `#[utoipa::path(security(...))]`, and this table is what the middleware
/// enforces (`security(())` means open to all: the health check and the dashboard's files),
/// looked up by the method and the route axum matched.
#[derive(Debug, Clone, Default)]
pub(crate) struct ScopeTable {
    /// By method and route template (`/api/v1/targets/{name}`): the scope (`None`: open).
    routes: HashMap<(Method, String), Option<Scope>>,
}

impl ScopeTable {
    /// The table of an OpenAPI document. An operation whose scope is not one of ours is a
    /// defect of its declaration: it needs `admin`.
    pub(crate) fn from_openapi(doc: &utoipa::openapi::OpenApi) -> Self {
        let mut routes = HashMap::new();
        for (template, item) in &doc.paths.paths {
            for (method, op) in [
                (Method::GET, &item.get),
                (Method::PUT, &item.put),
                (Method::POST, &item.post),
                (Method::DELETE, &item.delete),
                (Method::PATCH, &item.patch),
                (Method::OPTIONS, &item.options),
                (Method::HEAD, &item.head),
                (Method::TRACE, &item.trace),
            ] {
                if let Some(op) = op {
                    let scope = declared_scope(op.security.as_deref().unwrap_or_default());
                    routes.insert((method, template.clone()), scope);
                }
            }
        }
        Self { routes }
    }

    /// The scope a request needs, from its method and the route it matched (none: no route
    /// did); `None` when it is open to all. A request no operation has (a 404 or 405 to come)
    /// needs `read`, or `admin` to change something.
    pub(crate) fn required(&self, method: &Method, route: Option<&str>) -> Option<Scope> {
        if let Some(scope) = route.and_then(|r| self.routes.get(&(method.clone(), r.to_owned()))) {
            return *scope;
        }
        Some(if is_write(method) {
            Scope::Admin
        } else {
            Scope::Read
        })
    }
}

/// The scope of an operation's security requirements: none when one of them is empty (open
/// to all) and no scope is named, else the first scope named (`admin` for a word that is not
/// a scope).
fn declared_scope(
    requirements: &[utoipa::openapi::security::SecurityRequirement],
) -> Option<Scope> {
    // A requirement's scheme-to-scopes map is private to utoipa; its JSON form is the map.
    let maps: Vec<serde_json::Map<String, serde_json::Value>> = requirements
        .iter()
        .filter_map(|r| match serde_json::to_value(r) {
            Ok(serde_json::Value::Object(m)) => Some(m),
            _ => None,
        })
        .collect();
    let first = maps
        .iter()
        .flat_map(|m| m.values())
        .filter_map(|scopes| scopes.as_array())
        .flatten()
        .find_map(|v| v.as_str());
    let open = maps.iter().any(serde_json::Map::is_empty);
    match first {
        None if open => None,
        Some(word) => Some(Scope::parse(word).unwrap_or(Scope::Admin)),
        None => Some(Scope::Admin),
    }
}

/// True for the methods that change something.
fn is_write(method: &Method) -> bool {
    matches!(
        *method,
        Method::POST | Method::PUT | Method::DELETE | Method::PATCH
    )
}

/// Who made a request, for handlers that check more than a scope: set by [`require_token`].
#[derive(Debug, Clone)]
pub(crate) struct Caller {
    /// False when no tokens are configured (every request is local) or the route is open.
    pub authenticated: bool,
    /// The site a `sync` token uploads for.
    pub site: Option<crate::config::SiteName>,
    /// The token's name, when a token was given.
    pub name: Option<String>,
}

/// Checks the bearer token of a request against the configured tokens.
pub(crate) async fn require_token(
    tokens: Arc<Vec<TokenSpec>>,
    scopes: Arc<ScopeTable>,
    request: Request,
    next: Next,
) -> Result<Response, ApiError> {
    let route = request
        .extensions()
        .get::<axum::extract::MatchedPath>()
        .map(|m| m.as_str().to_owned());
    let needed = scopes.required(request.method(), route.as_deref());
    let Some(needed) = needed.filter(|_| !tokens.is_empty()) else {
        let mut request = request;
        request.extensions_mut().insert(Caller {
            authenticated: false,
            site: None,
            name: None,
        });
        return Ok(next.run(request).await);
    };
    let given = request
        .headers()
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| {
            // The scheme is case-insensitive (RFC 9110, section 11.1).
            let (scheme, token) = v.trim_start().split_once(' ')?;
            scheme.eq_ignore_ascii_case("bearer").then_some(token)
        })
        .map(str::trim);
    let Some(given) = given else {
        return Err(ApiError::new(
            StatusCode::UNAUTHORIZED,
            ErrorCode::Unauthorized,
            "this request needs `Authorization: Bearer <token>`",
        ));
    };
    let hash = crate::config::sha256_hex(given);
    let Some(token) = tokens.iter().find(|t| t.sha256_hex == hash) else {
        return Err(ApiError::new(
            StatusCode::UNAUTHORIZED,
            ErrorCode::Unauthorized,
            "the token is not known",
        ));
    };
    // `admin` may do everything but upload for a site: only that site's `sync` token may.
    let admin_may = needed != Scope::Sync && token.scopes.contains(&Scope::Admin);
    if !token.scopes.contains(&needed) && !admin_may {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            ErrorCode::Forbidden,
            format!(
                "token `{}` lacks the `{}` scope this request needs",
                token.name,
                needed.name()
            ),
        ));
    }
    let mut request = request;
    request.extensions_mut().insert(Caller {
        authenticated: true,
        site: token.site.clone(),
        name: Some(token.name.clone()),
    });
    Ok(next.run(request).await)
}

/// The guard of a service without tokens, which then listens on loopback only. A web page in
/// the operator's browser can still reach loopback: it could post a `text/plain` form (no CORS
/// preflight) or, through DNS rebinding, read answers under a name of its own. So, without
/// tokens: a request's `Host` must be `localhost`, an IP address or a configured name
/// (`[server] allowed_hosts`); an `Origin`, when sent, must name such a host too; and writes
/// must be JSON or NDJSON, which a page cannot send cross-site without a preflight.
#[derive(Debug, Clone)]
pub(crate) struct LocalOnly {
    allowed_hosts: Vec<String>,
}

impl LocalOnly {
    /// The guard, with extra host names (with or without a port) from the configuration.
    pub(crate) fn new(allowed_hosts: &[String]) -> Self {
        Self {
            allowed_hosts: allowed_hosts
                .iter()
                .map(|h| host_name(h).to_ascii_lowercase())
                .collect(),
        }
    }

    /// True for a host (without port) this service answers to.
    fn allows(&self, host: &str) -> bool {
        let host = host.to_ascii_lowercase();
        let bare = host.trim_start_matches('[').trim_end_matches(']');
        host == "localhost"
            || bare.parse::<std::net::IpAddr>().is_ok()
            || self.allowed_hosts.contains(&host)
    }
}

/// The host part of `host[:port]` or `[v6]:port`.
fn host_name(authority: &str) -> &str {
    let authority = authority.trim();
    if let Some(rest) = authority.strip_prefix('[') {
        return rest.split(']').next().unwrap_or(rest);
    }
    match authority.rsplit_once(':') {
        Some((host, port)) if port.chars().all(|c| c.is_ascii_digit()) && !host.contains(':') => {
            host
        }
        _ => authority,
    }
}

/// Applies [`LocalOnly`] when it is given (no tokens configured).
pub(crate) async fn local_only(
    guard: Option<Arc<LocalOnly>>,
    request: Request,
    next: Next,
) -> Result<Response, ApiError> {
    let Some(guard) = guard else {
        return Ok(next.run(request).await);
    };
    let headers = request.headers();
    let host = headers
        .get(header::HOST)
        .and_then(|v| v.to_str().ok())
        .map(host_name)
        .or_else(|| request.uri().host());
    if let Some(host) = host
        && !guard.allows(host)
    {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            ErrorCode::HostNotAllowed,
            format!(
                "`Host: {host}` is not a name of this service; without tokens it answers only to \
                 localhost, IP addresses and `[server] allowed_hosts`"
            ),
        ));
    }
    if let Some(origin) = headers.get(header::ORIGIN) {
        let text = origin.to_str().unwrap_or("");
        let origin_host = text
            .split_once("://")
            .map(|(_, rest)| host_name(rest.split('/').next().unwrap_or("")));
        if !origin_host.is_some_and(|h| guard.allows(h)) {
            return Err(ApiError::new(
                StatusCode::FORBIDDEN,
                ErrorCode::OriginNotAllowed,
                format!(
                    "requests from the web origin `{text}` are refused: without tokens only pages \
                     of this service may call it"
                ),
            ));
        }
    }
    if is_write(request.method()) {
        let content_type = headers
            .get(header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .map(|v| {
                v.split(';')
                    .next()
                    .unwrap_or("")
                    .trim()
                    .to_ascii_lowercase()
            });
        let has_body = headers.contains_key(header::TRANSFER_ENCODING)
            || headers
                .get(header::CONTENT_LENGTH)
                .and_then(|v| v.to_str().ok())
                .is_some_and(|v| v.trim() != "0");
        // A body must be declared JSON (or a frame's image type: like JSON, none of them is a
        // type a cross-site form may send without asking first); a write without a body (and
        // without a type) passes (a browser sends an `Origin` with it, checked above).
        let refused = match content_type.as_deref() {
            Some(t) => {
                !matches!(
                    t,
                    "application/json" | "application/x-ndjson" | "application/jsonl"
                ) && crate::imagefile::FrameFormat::from_content_type(t).is_none()
            }
            None => has_body,
        };
        if refused {
            return Err(ApiError::new(
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                ErrorCode::UnsupportedMediaType,
                format!(
                    "a write must be sent as `Content-Type: application/json` (or \
                     application/x-ndjson; a frame as image/png, image/tiff or \
                     image/x-portable-graymap), not `{}`",
                    content_type.unwrap_or_else(|| "none".into())
                ),
            ));
        }
    }
    Ok(next.run(request).await)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn host_names_are_taken_from_authorities() {
        assert_eq!(host_name("localhost:7878"), "localhost");
        assert_eq!(host_name("[::1]:7878"), "::1");
        assert_eq!(host_name("127.0.0.1"), "127.0.0.1");
        assert_eq!(host_name("ship.example:80"), "ship.example");
    }

    #[test]
    fn the_scope_table_follows_the_declarations_of_the_document() {
        let doc: utoipa::openapi::OpenApi = serde_json::from_value(serde_json::json!({
            "openapi": "3.1.0",
            "info": {"title": "t", "version": "1"},
            "paths": {
                "/healthz": {"get": {"security": [{}], "responses": {}}},
                "/api/v1/samples": {"post": {"security": [{"bearer": ["ingest"]}], "responses": {}}},
                "/api/v1/targets/{name}/reference": {
                    "get": {"security": [{"bearer": ["read"]}], "responses": {}},
                    "post": {"security": [{"bearer": ["admin"]}], "responses": {}}
                },
                "/api/v1/odd": {"get": {"security": [{"bearer": ["superuser"]}], "responses": {}}},
                "/api/v1/undeclared": {"get": {"responses": {}}}
            }
        }))
        .unwrap();
        let t = ScopeTable::from_openapi(&doc);
        assert_eq!(t.required(&Method::GET, Some("/healthz")), None);
        assert_eq!(
            t.required(&Method::POST, Some("/api/v1/samples")),
            Some(Scope::Ingest)
        );
        assert_eq!(
            t.required(&Method::GET, Some("/api/v1/targets/{name}/reference")),
            Some(Scope::Read)
        );
        assert_eq!(
            t.required(&Method::POST, Some("/api/v1/targets/{name}/reference")),
            Some(Scope::Admin)
        );
        // No route matched: read to look, admin to change; a method the route does not have
        // likewise; an unknown scope, or none declared, is admin's.
        assert_eq!(t.required(&Method::GET, None), Some(Scope::Read));
        assert_eq!(t.required(&Method::POST, None), Some(Scope::Admin));
        assert_eq!(
            t.required(&Method::DELETE, Some("/healthz")),
            Some(Scope::Admin)
        );
        assert_eq!(
            t.required(&Method::GET, Some("/api/v1/odd")),
            Some(Scope::Admin)
        );
        assert_eq!(
            t.required(&Method::GET, Some("/api/v1/undeclared")),
            Some(Scope::Admin)
        );
    }

    #[test]
    fn only_local_and_configured_hosts_are_allowed() {
        let g = LocalOnly::new(&["bridge.local:7878".to_owned()]);
        assert!(g.allows("localhost"));
        assert!(g.allows("127.0.0.1"));
        assert!(g.allows("::1"));
        assert!(g.allows("bridge.local"));
        assert!(!g.allows("evil.example"));
    }
}
