//! The OpenAPI document: served, complete (every routed operation appears, every documented one
//! is routed), and true about the scope each operation needs.

use super::access::with_tokens;
use super::helpers::TestApp;
use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use http_body_util::BodyExt;
use serde_json::Value;
use tower::ServiceExt;

/// Every `(METHOD, path template, operation)` of the document, with the server prefix kept.
fn operations(doc: &Value) -> Vec<(String, String, Value)> {
    let mut out = Vec::new();
    for (path, item) in doc["paths"].as_object().expect("paths") {
        for (method, op) in item.as_object().expect("path item") {
            if ["get", "post", "put", "delete", "patch"].contains(&method.as_str()) {
                out.push((method.to_uppercase(), path.clone(), op.clone()));
            }
        }
    }
    out
}

/// A concrete URI for a template: a known target or link where the template has `{name}`.
fn concrete(path: &str) -> String {
    let name = if path.starts_with("/api/v1/targets/") {
        "G"
    } else if path.contains("/calibration") {
        "C2_from_C1"
    } else {
        "C1_from_B"
    };
    path.replace("{name}", name)
        .replace("{file}", "app.js")
        .replace("{site}", "ship-1")
}

/// The status, and the JSON body unless the answer is an event stream (which never ends).
async fn call(app: &TestApp, method: &str, uri: &str, token: Option<&str>) -> (StatusCode, Value) {
    let mut builder = Request::builder().method(method).uri(uri);
    if let Some(t) = token {
        builder = builder.header(header::AUTHORIZATION, format!("Bearer {t}"));
    }
    let req = builder.body(Body::empty()).expect("request");
    let resp = app.router.clone().oneshot(req).await.expect("response");
    let status = resp.status();
    let streaming = resp
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(b"text/event-stream"));
    if streaming {
        return (status, Value::Null);
    }
    let bytes = resp.into_body().collect().await.expect("body").to_bytes();
    (
        status,
        serde_json::from_slice(&bytes).unwrap_or(Value::Null),
    )
}

#[tokio::test]
async fn the_document_is_served_and_is_the_generated_one() {
    let app = TestApp::start(None).await;
    let (status, served) = app.get("/api/v1/openapi.json").await;
    assert_eq!(status, StatusCode::OK);
    let generated = serde_json::to_value(brokenray::api::openapi()).expect("serialisable");
    assert_eq!(served, generated);
    assert!(
        served["openapi"]
            .as_str()
            .expect("version")
            .starts_with("3.")
    );
    // Every schema the operations refer to is defined.
    let text = served.to_string();
    let schemas = served["components"]["schemas"]
        .as_object()
        .expect("schemas");
    for piece in text.split("\"#/components/schemas/").skip(1) {
        let name = &piece[..piece.find('"').expect("closing quote")];
        assert!(schemas.contains_key(name), "undefined schema `{name}`");
    }
}

#[tokio::test]
async fn every_documented_operation_is_routed() {
    let app = TestApp::start(None).await;
    let doc = serde_json::to_value(brokenray::api::openapi()).expect("serialisable");
    let ops = operations(&doc);
    assert!(ops.len() >= 17, "only {} operations documented", ops.len());
    for (method, path, _) in &ops {
        let uri = concrete(path);
        let (status, body) = call(&app, method, &uri, None).await;
        assert_ne!(status, StatusCode::METHOD_NOT_ALLOWED, "{method} {uri}");
        let unrouted = status == StatusCode::NOT_FOUND
            && body["error"]["message"]
                .as_str()
                .is_some_and(|m| m.starts_with("no endpoint"));
        assert!(!unrouted, "{method} {uri} is documented but not routed");
    }
    // A method the document does not list on a routed path is refused.
    let (status, _) = call(&app, "DELETE", "/api/v1/targets", None).await;
    assert_eq!(status, StatusCode::METHOD_NOT_ALLOWED);
}

/// The router is built only from `routes!(...)` registrations, each of which adds its operation
/// to the document; a plain `.route(...)` would serve an undocumented endpoint. This reads the
/// API's sources for any.
#[test]
fn no_route_bypasses_the_document() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut offenders = Vec::new();
    let mut stack = vec![dir];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d).expect("source dir") {
            let path = entry.expect("entry").path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                let text = std::fs::read_to_string(&path).expect("source");
                for (i, line) in text.lines().enumerate() {
                    if line.contains(".route(") || line.contains("axum::routing::") {
                        offenders.push(format!("{}:{}: {}", path.display(), i + 1, line.trim()));
                    }
                }
            }
        }
    }
    assert!(
        offenders.is_empty(),
        "undocumented routes:\n{}",
        offenders.join("\n")
    );
}

#[tokio::test]
async fn each_operation_needs_the_scope_the_document_states() {
    let app = TestApp::start(Some(&with_tokens())).await;
    let doc = serde_json::to_value(brokenray::api::openapi()).expect("serialisable");
    // Tokens of `with_tokens`: one with each scope (the operator's has `read` too).
    let token_of = |scope: &str| match scope {
        "read" => "viewer-secret",
        "ingest" => "pipeline-secret",
        "admin" => "operator-secret",
        "sync" => "site-secret",
        other => panic!("unknown scope `{other}`"),
    };
    for (method, path, op) in operations(&doc) {
        let uri = concrete(&path);
        let security = op["security"]
            .as_array()
            .expect("every operation states its security");
        let scopes: Vec<&str> = security
            .iter()
            .filter_map(|s| s.get("bearer"))
            .flat_map(|s| s.as_array().expect("scopes").iter())
            .map(|s| s.as_str().expect("scope"))
            .collect();
        if scopes.is_empty() {
            // Open to all.
            let (status, _) = call(&app, &method, &uri, None).await;
            assert!(
                status.is_success(),
                "{method} {uri} is documented open: {status}"
            );
            continue;
        }
        assert_eq!(scopes.len(), 1, "{method} {uri}: {scopes:?}");
        let (status, _) = call(&app, &method, &uri, None).await;
        assert_eq!(
            status,
            StatusCode::UNAUTHORIZED,
            "{method} {uri} without a token"
        );
        let (status, _) = call(&app, &method, &uri, Some(token_of(scopes[0]))).await;
        assert!(
            status != StatusCode::UNAUTHORIZED && status != StatusCode::FORBIDDEN,
            "{method} {uri} with a `{}` token: {status}",
            scopes[0]
        );
        let others: &[&str] = match scopes[0] {
            "read" => &["ingest"],
            "ingest" => &["read"],
            // `admin` includes every scope but `sync`: only the site's own token uploads.
            "sync" => &["read", "ingest", "admin"],
            _ => &["read", "ingest"],
        };
        for other in others {
            let (status, _) = call(&app, &method, &uri, Some(token_of(other))).await;
            assert_eq!(
                status,
                StatusCode::FORBIDDEN,
                "{method} {uri} needs `{}`, a `{other}` token must not do",
                scopes[0]
            );
        }
    }
}

/// The row of `docs/interface.md`'s vocabulary table whose first cell is `what`: its words.
fn documented_words(what: &str) -> Vec<String> {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/interface.md"))
        .expect("docs/interface.md");
    let row = text
        .lines()
        .find(|l| l.starts_with(&format!("| {what} |")))
        .unwrap_or_else(|| panic!("no row `{what}` in docs/interface.md"));
    let words = row.split('|').nth(2).expect("a second cell");
    words
        .split(',')
        .map(|w| w.trim().trim_matches('`').to_owned())
        .collect()
}

/// The interface's list of error codes is the service's, word for word and in order; each code
/// is serialised as its name, and the OpenAPI document lists the same values.
#[test]
fn the_documented_error_codes_are_exactly_the_enums() {
    use brokenray::api::ErrorCode;
    let names: Vec<String> = ErrorCode::ALL.iter().map(|c| c.name().to_owned()).collect();
    assert_eq!(documented_words("error `code`"), names);
    for code in ErrorCode::ALL {
        assert_eq!(
            serde_json::to_value(code).unwrap(),
            Value::String(code.name().to_owned())
        );
    }
    let doc: Value = serde_json::to_value(brokenray::api::openapi()).unwrap();
    let listed: Vec<String> = doc["components"]["schemas"]["ErrorCode"]["enum"]
        .as_array()
        .expect("the document lists the codes")
        .iter()
        .map(|v| v.as_str().unwrap().to_owned())
        .collect();
    let mut sorted_names = names.clone();
    sorted_names.sort();
    let mut sorted_listed = listed;
    sorted_listed.sort();
    assert_eq!(sorted_listed, sorted_names);
}
