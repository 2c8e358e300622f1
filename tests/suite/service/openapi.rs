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

/// The rows of `docs/interface.md`'s vocabulary table: each first cell and its words.
fn documented_vocabularies() -> Vec<(String, Vec<String>)> {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/interface.md"))
        .expect("docs/interface.md");
    let section = text
        .split("## Vocabularies")
        .nth(1)
        .and_then(|rest| rest.split("\n## ").next())
        .expect("a Vocabularies section");
    section
        .lines()
        .filter(|l| l.starts_with("| ") && !l.starts_with("| where") && !l.starts_with("|---"))
        .map(|row| {
            let cells: Vec<&str> = row.split(" | ").collect();
            let what = cells[0].trim_start_matches("| ").to_owned();
            let words = cells[1]
                .trim_end_matches(" |")
                .split(',')
                .map(|w| w.trim().trim_matches('`').to_owned())
                .collect();
            (what, words)
        })
        .collect()
}

/// The words of a vocabulary, in order.
fn words_of<W: brokenray::words::Word>() -> Vec<String> {
    W::words().into_iter().map(str::to_owned).collect()
}

/// `docs/interface.md`'s vocabulary table is the code's, row for row and word for word in
/// order: every row is one enum, every vocabulary the API sends is listed in the OpenAPI
/// document with the same words, and each value is serialised as its word.
#[test]
fn the_documented_vocabularies_are_exactly_the_enums() {
    use brokenray::api::ErrorCode;
    use brokenray::api::vocab::{
        CompensationSource, ContributorKind, HealthStatus, LinkKindName, NotFoundCode,
        RawRequestState, ReferenceOriginKind, UncertaintyPart,
    };
    let emit: Vec<String> = <brokenray::feed::Emit as clap::ValueEnum>::value_variants()
        .iter()
        .filter_map(clap::ValueEnum::to_possible_value)
        .map(|v| v.get_name().to_owned())
        .collect();
    // Each row: the table's first cell, the enum's words, and its schema in the API's document
    // (None: not an API vocabulary).
    let expected: Vec<(&str, Vec<String>, Option<&str>)> = vec![
        (
            "target `status` (compensation, stored results, `/healthz`)",
            words_of::<brokenray::bank::TargetStatus>(),
            Some("TargetStatus"),
        ),
        (
            "`/healthz` `status`",
            words_of::<HealthStatus>(),
            Some("HealthStatus"),
        ),
        (
            "link `kind` (`GET /api/v1/links`)",
            words_of::<LinkKindName>(),
            Some("LinkKindName"),
        ),
        (
            "link `status` (`GET /api/v1/links`)",
            words_of::<brokenray::service::LinkState>(),
            Some("LinkState"),
        ),
        (
            "what the filter did with a sample (`disposition`)",
            words_of::<brokenray::filter::DispositionKind>(),
            Some("DispositionKind"),
        ),
        (
            "result `source` (stats, history)",
            words_of::<brokenray::bank::ResultSource>(),
            Some("ResultSource"),
        ),
        (
            "compensation `source`",
            words_of::<CompensationSource>(),
            Some("CompensationSource"),
        ),
        (
            "reference `origin`",
            words_of::<ReferenceOriginKind>(),
            Some("ReferenceOriginKind"),
        ),
        (
            "uncertainty contributor `kind` (`budget`)",
            words_of::<ContributorKind>(),
            Some("ContributorKind"),
        ),
        (
            "uncertainty `part` (`budget`)",
            words_of::<UncertaintyPart>(),
            Some("UncertaintyPart"),
        ),
        (
            "acceptance `standing` (`GET /api/v1/acceptance`)",
            words_of::<brokenray::acceptance::Standing>(),
            Some("Standing"),
        ),
        (
            "acceptance run `phase`",
            words_of::<brokenray::acceptance::Phase>(),
            Some("Phase"),
        ),
        (
            "acceptance step `kind`",
            words_of::<brokenray::acceptance::StepKind>(),
            Some("StepKind"),
        ),
        (
            "alarm `kind`",
            words_of::<brokenray::alarms::AlarmKind>(),
            Some("AlarmKind"),
        ),
        (
            "alarm level (`from`, `to`, a target's `alarm`)",
            words_of::<brokenray::alarms::Level>(),
            Some("Level"),
        ),
        (
            "alarm `unit`",
            words_of::<brokenray::alarms::ValueUnit>(),
            Some("ValueUnit"),
        ),
        (
            "filter `model`",
            words_of::<brokenray::filter::MotionModel>(),
            Some("MotionModel"),
        ),
        (
            "camera source `status` (`GET /api/v1/cameras`)",
            words_of::<brokenray::acquire::SourceStatus>(),
            Some("SourceStatus"),
        ),
        (
            "camera source `trigger` (`[cameras.source]`, `GET /api/v1/cameras`)",
            words_of::<brokenray::config::TriggerMode>(),
            Some("TriggerMode"),
        ),
        (
            "camera source `timestamp` (`[cameras.source]`, `GET /api/v1/cameras`)",
            words_of::<brokenray::config::TimestampMode>(),
            Some("TimestampMode"),
        ),
        (
            "camera source `pixel_format` (`[cameras.source]`)",
            words_of::<brokenray::config::PixelFormat>(),
            None,
        ),
        (
            "token `scopes`",
            words_of::<brokenray::config::Scope>(),
            None,
        ),
        (
            "upload `tier` (fleet)",
            words_of::<brokenray::store::outbox::Tier>(),
            Some("Tier"),
        ),
        (
            "upload `outcome` (fleet)",
            words_of::<brokenray::fleet::protocol::Outcome>(),
            Some("Outcome"),
        ),
        (
            "raw request `state` (fleet)",
            words_of::<RawRequestState>(),
            Some("RawRequestState"),
        ),
        (
            "webhook `min_level`",
            words_of::<brokenray::config::NotifyLevel>(),
            Some("NotifyLevel"),
        ),
        (
            "output `kind` (`GET /api/v1/outputs`, `/healthz`)",
            words_of::<brokenray::outputs::OutputKind>(),
            Some("OutputKind"),
        ),
        (
            "`[rerun] mode`",
            words_of::<brokenray::config::RerunMode>(),
            None,
        ),
        (
            "why a marker was not found in a frame (`reason_code`)",
            words_of::<NotFoundCode>(),
            Some("NotFoundCode"),
        ),
        (
            "why an archived frame was kept (`reason`)",
            words_of::<brokenray::archive::ArchiveReason>(),
            Some("ArchiveReason"),
        ),
        (
            "marker target and plate `polarity`",
            words_of::<brokenray::vision::Polarity>(),
            None,
        ),
        (
            "intrinsics (`fix`, `parameters`, `correlations`)",
            words_of::<brokenray::vision::Intrinsic>(),
            Some("Intrinsic"),
        ),
        (
            "camera calibration lens `model` (`--model`)",
            words_of::<brokenray::vision::LensModel>(),
            None,
        ),
        (
            "camera calibration warning `kind`",
            words_of::<brokenray::vision::WarningKind>(),
            Some("WarningKind"),
        ),
        ("what `simulate` and `demo` send (`--emit`)", emit, None),
        ("error `code`", words_of::<ErrorCode>(), Some("ErrorCode")),
    ];
    let documented = documented_vocabularies();
    let rows: Vec<&str> = documented.iter().map(|(w, _)| w.as_str()).collect();
    let known: Vec<&str> = expected.iter().map(|(w, _, _)| *w).collect();
    assert_eq!(
        rows, known,
        "the table's rows are the code's vocabularies, in order"
    );
    for ((what, words), (_, enum_words, _)) in documented.iter().zip(&expected) {
        assert_eq!(words, enum_words, "{what}");
    }
    let doc: Value = serde_json::to_value(brokenray::api::openapi()).unwrap();
    for (what, words, schema) in &expected {
        let Some(schema) = schema else { continue };
        let listed: Vec<String> = doc["components"]["schemas"][schema]["enum"]
            .as_array()
            .unwrap_or_else(|| panic!("the document lists the words of {schema} ({what})"))
            .iter()
            .map(|v| v.as_str().unwrap().to_owned())
            .collect();
        assert_eq!(&listed, words, "{schema}");
    }
    for code in ErrorCode::ALL {
        assert_eq!(
            serde_json::to_value(code).unwrap(),
            Value::String(code.name().to_owned())
        );
    }
}
