//! A target's history: its statistics over a window (the repeatability, the expected rms) and
//! its series of results, thinned for a plot or whole as CSV.

use super::AppState;
use super::error::{ApiError, ErrorBody};
use super::query::Query;
use super::targets::target_index;
use crate::bank::ResultSource;
use crate::clock::format_ns;
use crate::model::TargetId;
use axum::Json;
use axum::extract::{Path, State};
use serde::{Deserialize, Serialize};

/// Query of `stats` and other windows.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub(super) struct WindowQuery {
    /// Start (RFC 3339 or integer ns); the beginning of time without it.
    pub from: Option<String>,
    /// End; the end of time without it.
    pub to: Option<String>,
    /// `raw` or `filtered` (default `filtered`).
    pub source: Option<String>,
}

/// Parses `from`, `to` and `source` of a window query.
pub(super) fn parse_window(q: &WindowQuery) -> Result<(i64, i64, ResultSource), ApiError> {
    let (from, to) = super::parse_query_range(q.from.as_deref(), q.to.as_deref())?;
    Ok((from, to, parse_source(q.source.as_deref())?))
}

/// A query's `source`: `raw` or `filtered` (the default).
pub(super) fn parse_source(source: Option<&str>) -> Result<ResultSource, ApiError> {
    super::query_choice(
        "source",
        source,
        ResultSource::Filtered,
        &[
            ("raw", ResultSource::Raw),
            ("filtered", ResultSource::Filtered),
        ],
    )
}

/// Three statistics.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct ComponentsOut {
    /// Minimum.
    pub min: [f64; 3],
    /// Maximum.
    pub max: [f64; 3],
    /// Mean.
    pub mean: [f64; 3],
    /// Population standard deviation.
    pub rms: [f64; 3],
    /// The rms the model expects from the results' random part (their noise); null when a
    /// result in the window was stored without it.
    pub expected_rms: Option<[f64; 3]>,
}

/// `GET .../stats`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct StatsOut {
    /// Target.
    pub target: String,
    /// The results it is computed from.
    pub source: ResultSource,
    /// Results in the window.
    pub count: usize,
    /// Window start (as asked, or the first result).
    pub from: Option<String>,
    /// Window end.
    pub to: Option<String>,
    /// Euler angles (degrees).
    pub euler_deg: Option<ComponentsOut>,
    /// Translation (mm).
    pub t_mm: Option<ComponentsOut>,
    /// The window's scatter against the results' random part (raw results only: filtered
    /// results are correlated in time); null for filtered results, fewer than two results, or
    /// results stored without their random part.
    pub repeatability: Option<RepeatabilityOut>,
}

/// The scatter of a window of raw results against their random covariance.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct RepeatabilityOut {
    /// `tr(R^-1 S)`: the scatter matrix `S` against the mean random covariance `R`.
    pub chi2: f64,
    /// Its degrees of freedom, `6 (count - 1)`.
    pub dof: usize,
    /// The chi-square quantile at 99.9 %: results whose noise the model describes stay under
    /// it.
    pub threshold: f64,
    /// True when the scatter exceeds the threshold: a `pixel_sigma` or a link's sigma set too
    /// small, or something that moves.
    pub exceeded: bool,
}

/// `GET /api/v1/targets/{name}/stats?from=&to=&source=raw|filtered`.
#[utoipa::path(get, path = "/targets/{name}/stats", tag = "targets",
    params(("name" = String, Path, description = "Target frame"), WindowQuery),
    responses(
        (status = 200, description = "Min, max, mean and RMS over the window", body = StatsOut),
        (status = 404, description = "Unknown target", body = ErrorBody),
        (status = 422, description = "Invalid window", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_stats(
    State(app): State<AppState>,
    Path(name): Path<String>,
    Query(q): Query<WindowQuery>,
) -> Result<Json<StatsOut>, ApiError> {
    let (ti, spec) = target_index(&app, &name)?;
    Ok(Json(
        stats_of(&app, app.service.store(), ti, spec.name, &q).await?,
    ))
}

/// The statistics of target `ti` of `store`, named `name`.
pub(super) async fn stats_of(
    app: &AppState,
    store: &crate::store::Store,
    ti: TargetId,
    name: String,
    q: &WindowQuery,
) -> Result<StatsOut, ApiError> {
    let (from, to, source) = parse_window(q)?;
    let _permit = app.service.heavy_read().await;
    let (stats, first_last) = store.pose_stats(ti, source, from, to).await?;
    let comp = |c: crate::stats::ComponentStats, expected: Option<[f64; 3]>| ComponentsOut {
        min: c.min,
        max: c.max,
        mean: c.mean,
        rms: c.rms,
        expected_rms: expected,
    };
    let repeatability = stats.and_then(|s| s.repeatability);
    Ok(StatsOut {
        target: name,
        source,
        count: stats.map_or(0, |s| s.count),
        from: first_last.map(|(first, _)| format_ns(if from == i64::MIN { first } else { from })),
        to: first_last.map(|(_, last)| format_ns(if to == i64::MAX { last } else { to })),
        euler_deg: stats
            .map(|s| comp(s.euler_deg, repeatability.map(|r| r.expected_euler_rms_deg))),
        t_mm: stats.map(|s| comp(s.t_mm, repeatability.map(|r| r.expected_t_rms_mm))),
        repeatability: repeatability
            .filter(|_| source == ResultSource::Raw)
            .map(|r| RepeatabilityOut {
                chi2: r.chi2,
                dof: r.dof,
                threshold: r.threshold,
                exceeded: r.exceeded(),
            }),
    })
}

/// Query of `history`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub(super) struct HistoryQuery {
    /// Start (RFC 3339 or integer ns); the first result without it.
    pub from: Option<String>,
    /// End; the last result without it.
    pub to: Option<String>,
    /// `raw` or `filtered` (default `filtered`).
    pub source: Option<String>,
    /// At most this many buckets (default 1000, at most 100000).
    pub max_points: Option<usize>,
    /// `json` (default) or `csv`.
    pub format: Option<String>,
    /// Only these components, comma-separated (`def_rx_arcsec,def_ry_arcsec`); all without it.
    pub components: Option<String>,
}

/// One component's series.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct SeriesOut {
    /// Minimum per bucket (`null` where the bucket has no value of it).
    pub min: Vec<Option<f64>>,
    /// Mean per bucket.
    pub mean: Vec<Option<f64>>,
    /// Maximum per bucket.
    pub max: Vec<Option<f64>>,
}

/// `GET .../history`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct HistoryOut {
    /// Target.
    pub target: String,
    /// The results it is built from.
    pub source: ResultSource,
    /// Window start.
    pub from: Option<String>,
    /// Window end.
    pub to: Option<String>,
    /// Width of each bucket (s).
    pub bucket_s: f64,
    /// What the buckets were built from: a rollup width (s), or `null` for the results
    /// themselves.
    pub resolution_s: Option<i64>,
    /// Bucket start times.
    pub time: Vec<String>,
    /// Results per bucket.
    pub count: Vec<i64>,
    /// Per component (`euler_x_deg`, `t_x_mm`, `def_rx_arcsec`, `sigma_tx_mm`, ...).
    pub series: std::collections::BTreeMap<&'static str, SeriesOut>,
}

/// `GET /api/v1/targets/{name}/history?from=&to=&source=&max_points=&format=csv`.
#[utoipa::path(get, path = "/targets/{name}/history", tag = "targets",
    params(("name" = String, Path, description = "Target frame"), HistoryQuery),
    responses(
        (status = 200, description = "Min, mean and max per time bucket (JSON), or one row per bucket (`format=csv`)", content(
            (HistoryOut = "application/json"),
            (String = "text/csv"),
        )),
        (status = 404, description = "Unknown target", body = ErrorBody),
        (status = 422, description = "Invalid query", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_history(
    State(app): State<AppState>,
    Path(name): Path<String>,
    Query(q): Query<HistoryQuery>,
) -> Result<axum::response::Response, ApiError> {
    let (ti, spec) = target_index(&app, &name)?;
    history_of(&app, app.service.store(), ti, &spec.name, q).await
}

/// The history of target `ti` of `store`, named `name`: JSON or CSV as the query asks.
pub(super) async fn history_of(
    app: &AppState,
    store: &crate::store::Store,
    ti: TargetId,
    name: &str,
    q: HistoryQuery,
) -> Result<axum::response::Response, ApiError> {
    use crate::store::rollup::{Bucket, COMPONENTS, N_COMPONENTS};
    use axum::response::IntoResponse;
    let (from_q, to_q, source) = parse_window(&WindowQuery {
        from: q.from.clone(),
        to: q.to.clone(),
        source: q.source.clone(),
    })?;
    let max_points = super::query_count(
        "max_points",
        q.max_points.map(|n| i64::try_from(n).unwrap_or(i64::MAX)),
        1000,
    )? as usize;
    let csv = super::query_choice(
        "format",
        q.format.as_deref(),
        false,
        &[("json", false), ("csv", true)],
    )?;
    let chosen: Vec<usize> = match q.components.as_deref() {
        None => (0..N_COMPONENTS).collect(),
        Some(list) => list
            .split(',')
            .map(|name| {
                let name = name.trim();
                COMPONENTS.iter().position(|c| *c == name).ok_or_else(|| {
                    ApiError::invalid_field(
                        "components",
                        format!(
                            "`{name}` is not a component; they are {}",
                            COMPONENTS.join(", ")
                        ),
                    )
                })
            })
            .collect::<Result<_, _>>()?,
    };
    // Reading every result of a long window is heavy: at most `max_heavy_reads` at once.
    let _permit = app.service.heavy_read().await;
    let history = store.history(ti, source, from_q, to_q, max_points).await?;
    let buckets = &history.buckets;
    let value = |b: &Bucket, i: usize, which: u8| -> Option<f64> {
        match which {
            0 => b.has(i).then(|| b.min[i]),
            1 => b.mean(i),
            _ => b.has(i).then(|| b.max[i]),
        }
    };
    if csv {
        let mut header = String::from("time,count");
        for &i in &chosen {
            let c = COMPONENTS[i];
            header.push_str(&format!(",{c}_min,{c}_mean,{c}_max"));
        }
        header.push('\n');
        let columns = chosen.clone();
        let lines = std::iter::once(header).chain(buckets.iter().map(move |b| {
            let mut line = format!("{},{}", format_ns(b.start_ns), b.n);
            for &i in &columns {
                for which in 0..3 {
                    match value(b, i, which) {
                        Some(v) => line.push_str(&format!(",{v}")),
                        None => line.push(','),
                    }
                }
            }
            line.push('\n');
            line
        }));
        let lines: Vec<Result<String, std::convert::Infallible>> = lines.map(Ok).collect();
        let body = axum::body::Body::from_stream(futures::stream::iter(lines));
        return Ok((
            [
                (
                    axum::http::header::CONTENT_TYPE,
                    "text/csv; charset=utf-8".to_owned(),
                ),
                (
                    axum::http::header::CONTENT_DISPOSITION,
                    format!("attachment; filename=\"{name}-history.csv\""),
                ),
            ],
            body,
        )
            .into_response());
    }
    let mut series = std::collections::BTreeMap::new();
    for &i in &chosen {
        series.insert(
            COMPONENTS[i],
            SeriesOut {
                min: buckets.iter().map(|b| value(b, i, 0)).collect(),
                mean: buckets.iter().map(|b| value(b, i, 1)).collect(),
                max: buckets.iter().map(|b| value(b, i, 2)).collect(),
            },
        );
    }
    Ok(Json(HistoryOut {
        target: name.to_owned(),
        source,
        from: history.window_ns.map(|(from, _)| format_ns(from)),
        to: history.window_ns.map(|(_, to)| format_ns(to)),
        bucket_s: history.bucket_ns as f64 / 1e9,
        resolution_s: history.resolution_s,
        time: buckets.iter().map(|b| format_ns(b.start_ns)).collect(),
        count: buckets.iter().map(|b| b.n).collect(),
        series,
    })
    .into_response())
}
