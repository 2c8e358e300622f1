//! `GET /api/v1/targets/{name}/budget`: where the uncertainty of a target's newest result
//! comes from, contributor by contributor (each measured link's noise, each camera's
//! intrinsics, each calibrated link), in the axes' units and as a share of each axis'
//! variance, the largest first (`docs/method.md`, "Uncertainty").

use super::AppState;
use super::error::{ApiError, ErrorBody};
use super::query::Query;
use super::targets::target_index;
use crate::bank::ResultSource;
use crate::chain::{Budget, ContributorKind, UncertaintyPart, budget_sigmas};
use crate::clock::format_ns;
use axum::Json;
use axum::extract::{Path, State};
use serde::{Deserialize, Serialize};

/// Query of `budget`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub(super) struct BudgetQuery {
    /// `filtered` (default: the compensation's result) or `raw` (one measurement group).
    pub source: Option<String>,
}

/// Per axis, rotation about x, y, z (arc-seconds) and translation x, y, z (mm).
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub(super) struct AxesOut {
    /// Rotation about x, y, z (arc-seconds, or a fraction).
    pub rotation: [f64; 3],
    /// Translation x, y, z (mm, or a fraction).
    pub translation: [f64; 3],
}

impl AxesOut {
    fn of(values: [f64; 6]) -> Self {
        Self {
            rotation: [values[0], values[1], values[2]],
            translation: [values[3], values[4], values[5]],
        }
    }
}

/// One contributor's share.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct ContributionOut {
    /// What kind of contributor.
    pub kind: ContributorKind,
    /// The link (`noise`, `calibration`) or the camera (`intrinsics`).
    pub name: String,
    /// `random` or `systematic`.
    pub part: UncertaintyPart,
    /// Its standard deviation on each axis (arc-seconds, mm): the square root of its
    /// variance, the sigma the result would have from it alone.
    pub sigma: AxesOut,
    /// Its share of each axis' variance (0 to 1; the shares of an axis add up to 1).
    pub share: AxesOut,
    /// Its largest share over the six axes: what the list is sorted by.
    pub largest_share: f64,
}

/// `GET .../budget`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct BudgetOut {
    /// Target.
    pub target: String,
    /// The result it describes: `filtered` (the compensation's) or `raw`.
    pub source: ResultSource,
    /// That result's time.
    pub time: String,
    /// The whole sigma on each axis (arc-seconds, mm): the square root of the summed variance.
    pub sigma: AxesOut,
    /// The random part of `sigma`.
    pub sigma_random: AxesOut,
    /// The systematic part of `sigma`.
    pub sigma_systematic: AxesOut,
    /// Every contributor, the largest share first.
    pub contributions: Vec<ContributionOut>,
}

/// The answer for a budget of `model`'s target.
fn budget_out(
    target: String,
    source: ResultSource,
    time_ns: i64,
    budget: &Budget,
    model: &crate::model::Model,
) -> BudgetOut {
    let contributions = budget
        .lines_by_share()
        .into_iter()
        .map(|(line, share)| ContributionOut {
            kind: line.contributor.kind(),
            name: model.contributor_name(line.contributor).to_owned(),
            part: line.contributor.part(),
            sigma: AxesOut::of(budget_sigmas(line.variance)),
            largest_share: share.iter().copied().fold(0.0, f64::max),
            share: AxesOut::of(share),
        })
        .collect();
    BudgetOut {
        target,
        source,
        time: format_ns(time_ns),
        sigma: AxesOut::of(budget_sigmas(budget.total)),
        sigma_random: AxesOut::of(budget_sigmas(budget.part_variance(UncertaintyPart::Random))),
        sigma_systematic: AxesOut::of(budget_sigmas(
            budget.part_variance(UncertaintyPart::Systematic),
        )),
        contributions,
    }
}

/// `GET /api/v1/targets/{name}/budget?source=filtered|raw`.
#[utoipa::path(get, path = "/targets/{name}/budget", tag = "targets",
    params(("name" = String, Path, description = "Target frame"), BudgetQuery),
    responses(
        (status = 200, description = "Every contribution to the uncertainty of the target's newest result, in the axes' units and as a share of each axis' variance, the largest first", body = BudgetOut),
        (status = 404, description = "Unknown target, or no result yet", body = ErrorBody),
        (status = 422, description = "An unknown `source`", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_budget(
    State(app): State<AppState>,
    Path(name): Path<String>,
    Query(q): Query<BudgetQuery>,
) -> Result<Json<BudgetOut>, ApiError> {
    let (ti, _) = target_index(&app, &name)?;
    let source = super::history::parse_source(q.source.as_deref())?;
    let snapshot = app.service.snapshot();
    let (time_ns, budget) = snapshot.bank.budget(ti, source).ok_or_else(|| {
        ApiError::not_found(format!(
            "target `{name}` has no result yet: its budget comes with its first measurement group"
        ))
    })?;
    Ok(Json(budget_out(
        name,
        source,
        time_ns,
        &budget,
        snapshot.bank.model(),
    )))
}
