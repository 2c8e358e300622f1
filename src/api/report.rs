//! `GET /api/v1/report`: a period's report as a self-contained HTML page (see
//! [`crate::report::period`]).

use super::AppState;
use super::error::{ApiError, ErrorBody};
use super::query::Query;
use axum::body::Body;
use axum::extract::State;
use axum::http::{HeaderValue, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;

/// The period when the query names no start: the 30 days before its end.
const DEFAULT_PERIOD_NS: i64 = 30 * 86_400 * 1_000_000_000;

/// The longest period one report covers (a year and a day): its pictures stay readable and
/// its statistics one pass over the results.
const MAX_PERIOD_NS: i64 = 366 * 86_400 * 1_000_000_000;

/// The silence between raw results counted as a gap when the query does not say.
const DEFAULT_MIN_GAP_S: f64 = 60.0;

/// Query of `report`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub(super) struct ReportQuery {
    /// Start (RFC 3339 or integer ns); 30 days before the end without it.
    pub from: Option<String>,
    /// End; now without it.
    pub to: Option<String>,
    /// A silence between raw results longer than this many seconds is listed as a gap
    /// (default 60).
    pub min_gap_s: Option<f64>,
}

/// The window a report query asks for, its ends defaulted against `now_ns`.
pub(super) fn report_window(
    q: &ReportQuery,
    now_ns: i64,
) -> Result<crate::service::ReportWindow, ApiError> {
    let (from, to) = super::parse_query_range(q.from.as_deref(), q.to.as_deref())?;
    let to_ns = if to == i64::MAX { now_ns } else { to };
    let from_ns = if from == i64::MIN {
        to_ns.saturating_sub(DEFAULT_PERIOD_NS)
    } else {
        from
    };
    if from_ns >= to_ns {
        return Err(ApiError::invalid_field(
            "to",
            "the period is empty: `to` must be after `from` (now, without `to`)",
        ));
    }
    if to_ns.saturating_sub(from_ns) > MAX_PERIOD_NS {
        return Err(ApiError::invalid_field(
            "from",
            "a report covers at most 366 days: ask for several",
        ));
    }
    let min_gap_s = q.min_gap_s.unwrap_or(DEFAULT_MIN_GAP_S);
    if !(min_gap_s.is_finite() && min_gap_s > 0.0 && min_gap_s <= 86_400.0) {
        return Err(ApiError::invalid_field(
            "min_gap_s",
            format!("must be a number of seconds over 0 and at most 86400, not {min_gap_s}"),
        ));
    }
    Ok(crate::service::ReportWindow {
        from_ns,
        to_ns,
        min_gap_ns: (min_gap_s * 1e9).round() as i64,
    })
}

/// `GET /api/v1/report?from=&to=&min_gap_s=`.
#[utoipa::path(get, path = "/report", tag = "targets",
    params(ReportQuery),
    responses(
        (status = 200, description = "The period's report: a self-contained HTML page (pictures in SVG, no script) of the installation, its calibrations and, per target, its deformation, statistics, trend, alarms, gaps and uncertainty budget; served with a policy that lets it run no script and load nothing", content_type = "text/html"),
        (status = 422, description = "An invalid period or `min_gap_s`", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_report(
    State(app): State<AppState>,
    Query(q): Query<ReportQuery>,
) -> Result<Response, ApiError> {
    let window = report_window(&q, app.service.now_ns())?;
    let report = app.service.period_report(window).await?;
    let page = crate::report::period::render(&report);
    let name = format!(
        "inline; filename=\"brokenray-report-{}.html\"",
        crate::clock::format_ns(window.to_ns).replace(':', "-")
    );
    Ok(report_page(Body::from(page), Some(&name)))
}

/// A report's page as served: HTML under the reports' content policy (its own style and
/// SVG, no script, nothing loaded), not cached, not sniffed; `disposition` its
/// `Content-Disposition` when given.
pub(super) fn report_page(page: Body, disposition: Option<&str>) -> Response {
    let mut response = (
        [
            (
                header::CONTENT_TYPE,
                HeaderValue::from_static("text/html; charset=utf-8"),
            ),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
            (
                header::CONTENT_SECURITY_POLICY,
                HeaderValue::from_static(crate::report::CONTENT_SECURITY_POLICY),
            ),
            (
                header::X_CONTENT_TYPE_OPTIONS,
                HeaderValue::from_static("nosniff"),
            ),
        ],
        page,
    )
        .into_response();
    if let Some(value) = disposition.and_then(|d| HeaderValue::from_str(d).ok()) {
        response
            .headers_mut()
            .insert(header::CONTENT_DISPOSITION, value);
    }
    response
}
