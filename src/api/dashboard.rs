//! The web dashboard (`GET /` and `GET /assets/{file}`): the static files of `web/`, embedded in
//! the binary at compile time so the service needs no build step, no files beside it and no
//! internet (the charting library is vendored in `web/vendor/`).
//!
//! The files hold no data: they are open to all like `/healthz`, and the page asks for a token
//! when the API answers 401. Every answer carries a strict Content-Security-Policy (scripts,
//! styles and connections from this origin only) and an ETag, so a browser revalidates cheaply.

use super::error::{ApiError, ErrorBody};
use axum::extract::Path;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use sha2::{Digest, Sha256};
use std::sync::OnceLock;

/// One embedded file.
struct Asset {
    /// Its name under `/assets/` (`index.html` is served at `/`).
    name: &'static str,
    content_type: &'static str,
    bytes: &'static [u8],
}

/// One [`Asset`] from a file of `web/`.
macro_rules! asset {
    ($name:literal, $path:literal, $content_type:literal) => {
        Asset {
            name: $name,
            content_type: $content_type,
            bytes: include_bytes!(concat!("../../web/", $path)),
        }
    };
}

/// The page and what it loads: (name under `/assets/`, file of `web/`, content type). The
/// script is ES modules (`js/app.js` imports the others by relative path, so all are served
/// side by side under `/assets/`).
const ASSETS: &[Asset] = &[
    asset!("index.html", "index.html", "text/html; charset=utf-8"),
    asset!("app.js", "js/app.js", "text/javascript; charset=utf-8"),
    asset!(
        "acceptance.js",
        "js/acceptance.js",
        "text/javascript; charset=utf-8"
    ),
    asset!("util.js", "js/util.js", "text/javascript; charset=utf-8"),
    asset!("api.js", "js/api.js", "text/javascript; charset=utf-8"),
    asset!(
        "budget.js",
        "js/budget.js",
        "text/javascript; charset=utf-8"
    ),
    asset!("cards.js", "js/cards.js", "text/javascript; charset=utf-8"),
    asset!(
        "events.js",
        "js/events.js",
        "text/javascript; charset=utf-8"
    ),
    asset!(
        "history.js",
        "js/history.js",
        "text/javascript; charset=utf-8"
    ),
    asset!(
        "reference.js",
        "js/reference.js",
        "text/javascript; charset=utf-8"
    ),
    asset!(
        "alarms.js",
        "js/alarms.js",
        "text/javascript; charset=utf-8"
    ),
    asset!("chain.js", "js/chain.js", "text/javascript; charset=utf-8"),
    asset!("links.js", "js/links.js", "text/javascript; charset=utf-8"),
    asset!("fleet.js", "js/fleet.js", "text/javascript; charset=utf-8"),
    asset!(
        "cameras.js",
        "js/cameras.js",
        "text/javascript; charset=utf-8"
    ),
    asset!("style.css", "style.css", "text/css; charset=utf-8"),
    asset!(
        "uPlot.iife.min.js",
        "vendor/uplot/uPlot.iife.min.js",
        "text/javascript; charset=utf-8"
    ),
    asset!(
        "uPlot.min.css",
        "vendor/uplot/uPlot.min.css",
        "text/css; charset=utf-8"
    ),
    asset!(
        "uPlot.LICENSE",
        "vendor/uplot/LICENSE",
        "text/plain; charset=utf-8"
    ),
    asset!("favicon.svg", "favicon.svg", "image/svg+xml"),
];

/// Scripts, styles, images and connections from this origin only; no framing. uPlot sets
/// element styles from script (CSSOM), which `style-src 'self'` allows. A camera's calibration
/// report, fetched with the page's token and opened from a blob, takes this page's policy: its
/// one style sheet is admitted by its hash.
fn content_security_policy() -> &'static HeaderValue {
    static POLICY: OnceLock<HeaderValue> = OnceLock::new();
    POLICY.get_or_init(|| {
        let policy = format!(
            "default-src 'self'; script-src 'self'; style-src 'self' {}; \
             img-src 'self' data: blob:; connect-src 'self'; object-src 'none'; base-uri 'none'; \
             form-action 'self'; frame-ancestors 'none'",
            crate::report::style_hash_source()
        );
        // Base64 digits, quotes and ASCII words are always a valid header value.
        HeaderValue::from_str(&policy).unwrap_or(HeaderValue::from_static("default-src 'self'"))
    })
}

/// The strong ETag of each asset (a hash of its bytes), computed once.
fn etags() -> &'static [HeaderValue] {
    static ETAGS: OnceLock<Vec<HeaderValue>> = OnceLock::new();
    ETAGS.get_or_init(|| {
        ASSETS
            .iter()
            .map(|a| {
                let tag = format!("\"{}\"", &hex::encode(Sha256::digest(a.bytes))[..32]);
                // Quoted hex digits are always a valid header value.
                HeaderValue::from_str(&tag).unwrap_or(HeaderValue::from_static("\"\""))
            })
            .collect()
    })
}

fn serve(index: usize, headers: &HeaderMap) -> Response {
    let asset = &ASSETS[index];
    let etag = &etags()[index];
    let fresh = headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| {
            v.split(',')
                .any(|t| t.trim().as_bytes() == etag.as_bytes() || t.trim() == "*")
        });
    let common = [
        (header::ETAG, etag.clone()),
        (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
        (
            header::CONTENT_SECURITY_POLICY,
            content_security_policy().clone(),
        ),
        (
            header::X_CONTENT_TYPE_OPTIONS,
            HeaderValue::from_static("nosniff"),
        ),
    ];
    if fresh {
        return (StatusCode::NOT_MODIFIED, common).into_response();
    }
    (
        common,
        [(
            header::CONTENT_TYPE,
            HeaderValue::from_static(asset.content_type),
        )],
        asset.bytes,
    )
        .into_response()
}

/// `GET /`: the dashboard page.
#[utoipa::path(get, path = "/", tag = "dashboard",
    responses(
        (status = 200, description = "The dashboard (HTML)", content_type = "text/html", body = String),
        (status = 304, description = "Not modified since the ETag given in `If-None-Match`"),
    ),
    security(()))]
pub(super) async fn get_index(headers: HeaderMap) -> Response {
    serve(0, &headers)
}

/// `GET /assets/{file}`: a script, style sheet or licence of the dashboard.
#[utoipa::path(get, path = "/assets/{file}", tag = "dashboard",
    params(("file" = String, Path, description = "A file of the dashboard: `app.js` and the modules it imports, `style.css`, `uPlot.iife.min.js`, `uPlot.min.css`, `uPlot.LICENSE`, `favicon.svg`")),
    responses(
        (status = 200, description = "The file", content_type = "application/octet-stream", body = String),
        (status = 304, description = "Not modified since the ETag given in `If-None-Match`"),
        (status = 404, description = "No such file", body = ErrorBody),
    ),
    security(()))]
pub(super) async fn get_asset(
    Path(file): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let index = ASSETS
        .iter()
        .position(|a| a.name == file && a.name != "index.html")
        .ok_or_else(|| ApiError::not_found(format!("the dashboard has no file `{file}`")))?;
    Ok(serve(index, &headers))
}
