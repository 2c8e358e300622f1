//! `POST /api/v1/samples`: a JSON batch `{"samples": [...]}` or NDJSON (one sample a line).
//!
//! Parsing collects every problem of every item before answering: a syntax error names the
//! item and field it fell in, a type error its path, a semantic problem (unknown link, bad
//! rotation, bad time, duplicate inside the batch, ...) its field. Nothing of a refused batch is
//! stored. A 200 answer means the whole batch is on disk.

use super::AppState;
use super::dto::{SampleIn, invalid};
use super::error::{ApiError, ErrorBody, ErrorDetail};
use crate::api::error::ErrorCode;
use crate::bank::{MeasurementUncertainty, Sample};
use crate::clock::{latest_accepted_ns, parse_measurement_time};
use crate::config::Installation;
use crate::model::LinkKind;
use crate::service::{IngestItem, IngestReport};
use crate::store::Quality;
use crate::wire::json::{item_index, offset_of, path_at};
use crate::wire::{FieldProblem, covariance_from};
use axum::Json;
use axum::body::Body;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode, header};
use serde::Serialize;
use serde_json::value::RawValue;
use std::collections::HashSet;

/// The answer to an accepted batch.
#[derive(Debug, Default, Clone, Serialize, utoipa::ToSchema)]
pub(crate) struct IngestResponse {
    /// Samples in the batch, all durably stored.
    pub accepted: usize,
    /// Newly stored.
    pub stored: usize,
    /// Identical to samples already stored (retries).
    pub duplicates: usize,
    /// Flagged as outliers.
    pub outliers: usize,
    /// Older than their link's filter: stored, not fused.
    pub out_of_order: usize,
    /// Filter restarts after runs of consistent outliers.
    pub reinitialized: usize,
    /// Raw results completed.
    pub raw_results: usize,
    /// Filtered results produced.
    pub filtered_results: usize,
    /// Targets some of whose results were not finite numbers and were not stored (their
    /// configuration gives numbers out of range), each with what was not finite.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub unusable_results: Vec<UnusableResult>,
}

/// A target whose results could not be stored.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub(crate) struct UnusableResult {
    /// The target.
    pub target: String,
    /// What was not finite: `pose`, `covariance`, `sigma`, `age` or `deformation`.
    pub what: String,
    /// What to do.
    pub message: String,
}

impl From<IngestReport> for IngestResponse {
    fn from(r: IngestReport) -> Self {
        Self {
            accepted: r.accepted,
            stored: r.stored,
            duplicates: r.duplicates,
            outliers: r.outliers,
            out_of_order: r.out_of_order,
            reinitialized: r.reinitialized,
            raw_results: r.raw_results,
            filtered_results: r.filtered_results,
            unusable_results: r
                .unusable
                .into_iter()
                .map(|(target, what)| UnusableResult {
                    message: format!(
                        "a result of target `{target}` has a {what} that is not a finite number \
                         and was not stored: check its filter tuning, its links' sigmas and its \
                         cameras' calibrations"
                    ),
                    target,
                    what: what.to_owned(),
                })
                .collect(),
        }
    }
}

/// A JSON batch of samples.
#[derive(serde::Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct SamplesBatch {
    /// The samples, each stored or none.
    pub samples: Vec<SampleIn>,
}

/// What a batch's slow path collected: the items that parsed, the first
/// [`super::error::MAX_DETAILS`] problems, and how many there were in all.
#[derive(Default)]
struct Collected {
    items: Vec<(usize, SampleIn)>,
    problems: Vec<ErrorDetail>,
    n_problems: usize,
}

impl Collected {
    fn take(&mut self, index: usize, parsed: Result<SampleIn, FieldProblem>) {
        match parsed {
            Ok(s) => {
                if self.n_problems == 0 {
                    self.items.push((index, s));
                }
            }
            Err(p) => self.problem(ErrorDetail {
                index: Some(index),
                field: Some(p.field).filter(|f| !f.is_empty()),
                message: p.message,
            }),
        }
    }

    fn problem(&mut self, detail: ErrorDetail) {
        self.n_problems += 1;
        // Once a problem is found the batch is refused: the items are no longer needed.
        self.items = Vec::new();
        if self.problems.len() < super::error::MAX_DETAILS {
            self.problems.push(detail);
        }
    }
}

/// `{"samples": [...]}` read item by item: each is parsed as it is met, so a body of junk
/// costs no more memory than its first problems (nothing is held per bad item).
struct BatchSeed<'c>(&'c mut Collected);

impl<'de> serde::de::DeserializeSeed<'de> for BatchSeed<'_> {
    type Value = ();
    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_map(self)
    }
}

impl<'de> serde::de::Visitor<'de> for BatchSeed<'_> {
    type Value = ();
    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("{\"samples\": [...]}")
    }
    fn visit_map<A: serde::de::MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        let mut seen = false;
        while let Some(key) = map.next_key::<std::borrow::Cow<'de, str>>()? {
            if key != "samples" {
                return Err(serde::de::Error::unknown_field(&key, &["samples"]));
            }
            if seen {
                return Err(serde::de::Error::duplicate_field("samples"));
            }
            seen = true;
            map.next_value_seed(ItemsSeed(&mut *self.0))?;
        }
        if !seen {
            return Err(serde::de::Error::missing_field("samples"));
        }
        Ok(())
    }
}

struct ItemsSeed<'c>(&'c mut Collected);

impl<'de> serde::de::DeserializeSeed<'de> for ItemsSeed<'_> {
    type Value = ();
    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_seq(self)
    }
}

impl<'de> serde::de::Visitor<'de> for ItemsSeed<'_> {
    type Value = ();
    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("an array of samples")
    }
    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
        let mut index = 0;
        while let Some(raw) = seq.next_element::<&'de RawValue>()? {
            self.0.take(index, parse_item(raw.get()));
            index += 1;
        }
        Ok(())
    }
}

/// Reads the body up to the limit: 413 past it.
pub(super) async fn read_body(
    body: Body,
    headers: &HeaderMap,
    limit: usize,
) -> Result<bytes::Bytes, ApiError> {
    let too_large = || {
        ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            ErrorCode::PayloadTooLarge,
            format!("the request body exceeds the limit of {limit} bytes; send smaller batches"),
        )
    };
    if let Some(len) = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<usize>().ok())
        && len > limit
    {
        return Err(too_large());
    }
    axum::body::to_bytes(body, limit).await.map_err(|e| {
        let is_limit = std::error::Error::source(&e)
            .is_some_and(|s| s.is::<http_body_util::LengthLimitError>())
            || e.to_string().contains("length limit");
        if is_limit {
            too_large()
        } else {
            ApiError::bad_request(
                ErrorCode::UnreadableBody,
                format!("the request body could not be read: {e}"),
            )
        }
    })
}

fn syntax_problem(
    text: &str,
    e: &serde_json::Error,
    prefix: &str,
) -> (Option<usize>, String, String) {
    let offset = offset_of(text, e.line(), e.column());
    let path = path_at(text, offset);
    let index = item_index(&path, "samples");
    let field = if prefix.is_empty() {
        path
    } else {
        format!("{prefix}{path}")
    };
    (
        index,
        field,
        format!(
            "malformed JSON at line {}, column {}: {e}",
            e.line(),
            e.column()
        ),
    )
}

/// Parses one item, naming the field of a type error.
fn parse_item(text: &str) -> Result<SampleIn, FieldProblem> {
    let mut de = serde_json::Deserializer::from_str(text);
    serde_path_to_error::deserialize::<_, SampleIn>(&mut de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        let field = if path == "." { String::new() } else { path };
        FieldProblem::new(field, inner.to_string())
    })
}

/// Converts parsed items into validated samples, listing every problem.
pub(super) fn validate_samples(
    installation: &Installation,
    items: Vec<(usize, SampleIn)>,
    latest_ns: i64,
) -> Result<Vec<IngestItem>, Vec<FieldProblem>> {
    let mut problems = Vec::new();
    let mut out = Vec::with_capacity(items.len());
    let mut seen: HashSet<(usize, i64)> = HashSet::new();
    for (index, s) in items {
        let mut item_problems = Vec::new();
        let link = match installation.model.link_by_name(&s.link) {
            None => {
                item_problems.push(FieldProblem::new(
                    "link",
                    format!("unknown link `{}`", s.link),
                ));
                None
            }
            Some(spec) if matches!(spec.kind, LinkKind::Calibrated { .. }) => {
                item_problems.push(FieldProblem::new(
                    "link",
                    format!(
                        "`{}` is a calibrated link; samples are for measured links",
                        s.link
                    ),
                ));
                None
            }
            Some(spec) => Some(spec.id),
        };
        let time_ns = match parse_measurement_time(&s.time, latest_ns) {
            Ok(t) => Some(t),
            Err(m) => {
                item_problems.push(FieldProblem::new("time", m));
                None
            }
        };
        let pose = match s.pose.to_pose("pose") {
            Ok(p) => Some(p),
            Err(p) => {
                item_problems.push(p);
                None
            }
        };
        let uncertainty = match (&s.sigma, &s.covariance) {
            (Some(_), Some(_)) => {
                item_problems.push(FieldProblem::new(
                    "sigma",
                    "give `sigma` or `covariance`, not both",
                ));
                None
            }
            (Some(sig), None) => match sig.to_sigmas("sigma") {
                Ok(s) => Some(MeasurementUncertainty::Sigmas(s)),
                Err(p) => {
                    item_problems.push(p);
                    None
                }
            },
            (None, Some(c)) => match covariance_from("covariance", c) {
                Ok(m) => Some(MeasurementUncertainty::Covariance(m)),
                Err(p) => {
                    item_problems.push(p);
                    None
                }
            },
            (None, None) => Some(MeasurementUncertainty::Default),
        };
        let quality = match &s.quality {
            None => Some(Quality::default()),
            Some(q) => match q.reprojection_rms_px {
                Some(v) if !(v.is_finite() && v >= 0.0) => {
                    item_problems.push(FieldProblem::new(
                        "quality.reprojection_rms_px",
                        format!("must be a non-negative number, not {v}"),
                    ));
                    None
                }
                _ => Some(Quality {
                    reprojection_rms_px: q.reprojection_rms_px,
                    points: q.points,
                }),
            },
        };
        if let (Some(link), Some(time_ns)) = (link, time_ns)
            && !seen.insert((link.0, time_ns))
        {
            item_problems.push(FieldProblem::new(
                "time",
                format!(
                    "a second sample of `{}` at the same time in this batch",
                    s.link
                ),
            ));
        }
        match (
            link,
            time_ns,
            pose,
            uncertainty,
            quality,
            item_problems.is_empty(),
        ) {
            (Some(link), Some(time_ns), Some(pose), Some(uncertainty), Some(quality), true) => {
                out.push(IngestItem {
                    index,
                    sample: Sample {
                        link,
                        time_ns,
                        parent_from_child: pose,
                        uncertainty,
                    },
                    quality,
                });
            }
            _ => problems.extend(item_problems.into_iter().map(|p| p.at(index))),
        }
    }
    if problems.is_empty() {
        Ok(out)
    } else {
        Err(problems)
    }
}

fn is_ndjson(headers: &HeaderMap) -> bool {
    headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| {
            let v = v.to_ascii_lowercase();
            v.starts_with("application/x-ndjson") || v.starts_with("application/jsonl")
        })
}

/// Parses a request body into items, every problem listed (the first
/// [`super::error::MAX_DETAILS`] of them in the details, with the count in the message).
pub(super) fn parse_batch(text: &str, ndjson: bool) -> Result<Vec<(usize, SampleIn)>, ApiError> {
    let mut c = Collected::default();
    if ndjson {
        for (index, line) in text.lines().filter(|l| !l.trim().is_empty()).enumerate() {
            if let Err(e) = serde_json::from_str::<&RawValue>(line) {
                let (_, field, message) = syntax_problem(line, &e, "");
                c.problem(ErrorDetail {
                    index: Some(index),
                    field: Some(field).filter(|f| !f.is_empty()),
                    message,
                });
                continue;
            }
            c.take(index, parse_item(line));
        }
    } else {
        // Fast path: one typed pass. Only a batch with a problem takes the slower path that
        // reads item by item to name every problem.
        if let Ok(batch) = serde_json::from_str::<SamplesBatch>(text) {
            return Ok(batch.samples.into_iter().enumerate().collect());
        }
        let mut de = serde_json::Deserializer::from_str(text);
        let read = serde::de::DeserializeSeed::deserialize(BatchSeed(&mut c), &mut de)
            .and_then(|()| de.end());
        read.map_err(|e| {
            if e.is_syntax() || e.is_eof() {
                let (index, field, message) = syntax_problem(text, &e, "");
                ApiError::bad_request(ErrorCode::MalformedJson, message).with_details(vec![
                    ErrorDetail {
                        index,
                        field: Some(field).filter(|f| !f.is_empty()),
                        message: "malformed JSON here".into(),
                    },
                ])
            } else {
                ApiError::new(
                    StatusCode::UNPROCESSABLE_ENTITY,
                    ErrorCode::InvalidRequest,
                    format!("the body must be {{\"samples\": [...]}}: {e}"),
                )
            }
        })?;
    }
    if c.n_problems > 0 {
        let listed = c.problems.len();
        let mut e = ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            ErrorCode::InvalidSamples,
            format!(
                "{} sample(s) could not be read; nothing was stored",
                c.n_problems
            ),
        )
        .with_details(c.problems);
        e.details_omitted += c.n_problems - listed;
        return Err(e);
    }
    Ok(c.items)
}

/// Refuses an empty batch (422) and one over the limit (413); `what` names the items.
pub(super) fn check_batch_size(what: &str, len: usize, limit: usize) -> Result<(), ApiError> {
    if len == 0 {
        return Err(ApiError::invalid_field(what, "the batch is empty"));
    }
    if len > limit {
        return Err(ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            ErrorCode::BatchTooLarge,
            format!("the batch has {len} {what}, more than the limit of {limit}; split it"),
        ));
    }
    Ok(())
}

/// `POST /api/v1/samples`.
#[utoipa::path(post, path = "/samples", tag = "ingest",
    request_body(content(
        (SamplesBatch = "application/json"),
        (SampleIn = "application/x-ndjson"),
    ), description = "A batch `{\"samples\": [...]}`, or NDJSON with one sample a line"),
    responses(
        (status = 200, description = "The whole batch is durably stored", body = IngestResponse),
        (status = 400, description = "Malformed JSON (the item and field are named)", body = ErrorBody),
        (status = 409, description = "A sample differs from the one stored at the same link and time", body = ErrorBody),
        (status = 413, description = "Body or batch over the limit", body = ErrorBody),
        (status = 422, description = "Invalid samples; nothing was stored", body = ErrorBody),
        (status = 503, description = "The writer is not available", body = ErrorBody),
    ),
    security(("bearer" = ["ingest"])))]
pub(super) async fn post_samples(
    State(app): State<AppState>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<IngestResponse>, ApiError> {
    let bytes = read_body(body, &headers, app.limits.max_body_bytes).await?;
    let text = std::str::from_utf8(&bytes).map_err(|e| {
        ApiError::bad_request(
            ErrorCode::MalformedJson,
            format!("the body is not UTF-8: {e}"),
        )
    })?;
    let items = parse_batch(text, is_ndjson(&headers))?;
    check_batch_size("samples", items.len(), app.limits.max_batch_samples)?;
    let n = items.len();
    let latest = latest_accepted_ns(
        app.service.now_ns(),
        app.service.installation().server.max_future_s,
    );
    let valid = validate_samples(app.service.installation(), items, latest).map_err(|p| {
        invalid(
            format!("{} problem(s) in the batch; nothing was stored", p.len()),
            p,
        )
    })?;
    debug_assert_eq!(valid.len(), n);
    let report = app.service.ingest(valid).await?;
    Ok(Json(report.into()))
}
