//! Links: list with counters, stored samples, calibrations.

use super::AppState;
use super::error::{ApiError, ErrorBody};
use super::query::Query;
use crate::api::error::ErrorCode;
use crate::bank::MeasurementUncertainty;
use crate::chain::LinkId;
use crate::clock::{format_ns, parse_json_time};
use crate::geometry::PoseCov;
use crate::model::{LinkKind, LinkSpec};
use crate::wire::{PoseIn, PoseOut, SigmaIn, SigmaOut, covariance_from};
use axum::Json;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use serde::{Deserialize, Serialize};

fn link_spec(app: &AppState, name: &str) -> Result<LinkSpec, ApiError> {
    app.service
        .installation()
        .model
        .link_by_name(name)
        .cloned()
        .ok_or_else(|| ApiError::not_found(format!("unknown link `{name}`")))
}

/// A link as listed.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct LinkOut {
    /// `<parent>_from_<child>`.
    pub name: String,
    /// `measured` or `calibrated`.
    pub kind: super::vocab::LinkKindName,
    /// Parent frame.
    pub parent: String,
    /// Child frame.
    pub child: String,
    /// Filter model (measured links).
    pub model: Option<crate::filter::MotionModel>,
    /// Samples received.
    pub n_samples: u64,
    /// Of which outliers.
    pub n_outliers: u64,
    /// Samples whose measurement group left memory without a raw result of any target the
    /// link serves, since the service started (exposures not within `[filter]
    /// group_tolerance_ms` of the other links').
    pub n_ungrouped: u64,
    /// Filter restarts after consistent outlier runs.
    pub n_reinitializations: u64,
    /// Newest sample time.
    pub last_time: Option<String>,
    /// Seconds from the newest sample's time to now on the server's clock (negative when the
    /// sender's clock is ahead); absent before any sample.
    pub age_s: Option<f64>,
    /// Observed rate over recent samples (Hz).
    pub rate_hz: Option<f64>,
    /// Configured rate (Hz).
    pub expected_rate_hz: Option<f64>,
    /// `ok`; `stale` when its newest sample is older than its staleness limit
    /// (`stale_after_periods` of its expected period) on the server's clock, plus `[server]
    /// clock_tolerance_s`, or behind the newest link's sample by more than the limit;
    /// `no_data` before its first sample (and after a reset); `calibrated`.
    pub status: crate::service::LinkState,
    /// The newest manual restart of the link's filter, if any.
    pub last_reset: Option<LinkResetOut>,
}

/// A manual restart of a link's filter.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub(super) struct LinkResetOut {
    /// The link.
    pub link: String,
    /// When it was asked for (server clock).
    pub at: String,
    /// Who asked, as they said.
    pub by: Option<String>,
    /// Why, as they said.
    pub note: Option<String>,
}

/// Body of `POST .../reset` (optional).
#[derive(Debug, Default, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct LinkResetIn {
    /// Who asks (a name for the record).
    pub by: Option<String>,
    /// Why (for the record).
    pub note: Option<String>,
}

/// `POST /api/v1/links/{name}/reset`: restarts a measured link's filter from its next sample,
/// whatever that sample's time: the way back from a sample stamped far ahead (after which every
/// correct sample is out of order) or from a station that moved. Recorded, and listed with the
/// link.
#[utoipa::path(post, path = "/links/{name}/reset", tag = "links",
    params(("name" = String, Path, description = "Measured link name")),
    request_body(content = LinkResetIn, description = "Optional: who asks and why"),
    responses(
        (status = 200, description = "The filter restarts from the next sample", body = LinkResetOut),
        (status = 400, description = "Malformed JSON", body = ErrorBody),
        (status = 404, description = "Unknown link", body = ErrorBody),
        (status = 422, description = "A calibrated link, or a malformed body", body = ErrorBody),
    ),
    security(("bearer" = ["admin"])))]
pub(super) async fn post_reset(
    State(app): State<AppState>,
    Path(name): Path<String>,
    body: axum::body::Bytes,
) -> Result<Json<LinkResetOut>, ApiError> {
    let spec = link_spec(&app, &name)?;
    if !matches!(spec.kind, LinkKind::Measured(_)) {
        return Err(ApiError::invalid_field(
            "name",
            format!("`{name}` is a calibrated link: it has no filter to reset"),
        ));
    }
    let r: LinkResetIn = if body.iter().all(u8::is_ascii_whitespace) {
        LinkResetIn::default()
    } else {
        super::parse_json_body(&body)?
    };
    super::check_texts(&[("by", r.by.as_deref()), ("note", r.note.as_deref())])?;
    let at = app
        .service
        .reset_link(spec.id, r.by.clone(), r.note.clone())
        .await?;
    Ok(Json(LinkResetOut {
        link: spec.name,
        at: format_ns(at),
        by: r.by,
        note: r.note,
    }))
}

/// `GET /api/v1/links`.
#[utoipa::path(get, path = "/links", tag = "links",
    responses((status = 200, description = "Every link with its counters, rate and status", body = [LinkOut])),
    security(("bearer" = ["read"])))]
pub(super) async fn list_links(
    State(app): State<AppState>,
) -> Result<Json<Vec<LinkOut>>, ApiError> {
    let inst = app.service.installation();
    let resets = app.service.store().last_link_resets().await?;
    let snapshot = app.service.snapshot();
    let bank = &snapshot.bank;
    let now_ns = app.service.now_ns();
    let tolerance_s = inst.server.clock_tolerance_s;
    Ok(Json(
        inst.model
            .links
            .iter()
            .map(|l| {
                let ends = inst.model.topology.link(l.id);
                let st = bank.link_status(l.id);
                let status = snapshot.link_state(l.id, now_ns, tolerance_s);
                let (kind, model, expected) = match &l.kind {
                    LinkKind::Calibrated { .. } => {
                        (super::vocab::LinkKindName::Calibrated, None, None)
                    }
                    LinkKind::Measured(m) => (
                        super::vocab::LinkKindName::Measured,
                        Some(m.tuning.model),
                        Some(m.expected_rate_hz),
                    ),
                };
                LinkOut {
                    name: l.name.clone(),
                    kind,
                    parent: inst.model.topology.frame_name(ends.parent).to_owned(),
                    child: inst.model.topology.frame_name(ends.child).to_owned(),
                    model,
                    n_samples: st.n_samples,
                    n_outliers: st.n_outliers,
                    n_ungrouped: st.n_ungrouped,
                    n_reinitializations: st.n_reinitializations,
                    last_time: st.last_time_ns.map(format_ns),
                    age_s: st.last_time_ns.map(|t| (now_ns - t) as f64 / 1e9),
                    rate_hz: bank.observed_rate_hz(l.id),
                    expected_rate_hz: expected,
                    status,
                    last_reset: resets
                        .iter()
                        .find(|r| r.0 == l.id)
                        .map(|(_, at, by, note)| LinkResetOut {
                            link: l.name.clone(),
                            at: format_ns(*at),
                            by: by.clone(),
                            note: note.clone(),
                        }),
                }
            })
            .collect(),
    ))
}

/// Query of `samples`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub(super) struct SamplesQuery {
    /// Start.
    pub from: Option<String>,
    /// End.
    pub to: Option<String>,
    /// At most this many (default 1000, at most 100000).
    pub limit: Option<i64>,
}

/// A stored sample as answered.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct SampleOut {
    /// Measurement time.
    pub time: String,
    /// The measured pose.
    pub pose: PoseOut,
    /// Sigmas as given (absent when the link's default applied or a covariance was given).
    pub sigma: Option<SigmaOut>,
    /// Covariance as given (36 numbers, row-major).
    pub covariance: Option<Vec<f64>>,
    /// Reprojection RMS (px).
    pub reprojection_rms_px: Option<f64>,
    /// Points used.
    pub points: Option<u32>,
    /// Flagged as an outlier.
    pub outlier: bool,
    /// What the filter did: `initialized`, `fused`, `outlier`, `reinitialized`, `out_of_order`.
    pub disposition: crate::filter::DispositionKind,
    /// Normalised innovation squared.
    pub nis: Option<f64>,
    /// When the service received it.
    pub received: String,
}

/// `GET .../samples`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct SamplesOut {
    /// Link.
    pub link: String,
    /// Samples, oldest first.
    pub samples: Vec<SampleOut>,
}

/// `GET /api/v1/links/{name}/samples?from=&to=&limit=`.
#[utoipa::path(get, path = "/links/{name}/samples", tag = "links",
    params(("name" = String, Path, description = "Link name, `<parent>_from_<child>`"), SamplesQuery),
    responses(
        (status = 200, description = "Stored raw samples with their outlier flag", body = SamplesOut),
        (status = 404, description = "Unknown link", body = ErrorBody),
        (status = 422, description = "Invalid query", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn list_samples(
    State(app): State<AppState>,
    Path(name): Path<String>,
    Query(q): Query<SamplesQuery>,
) -> Result<Json<SamplesOut>, ApiError> {
    let spec = link_spec(&app, &name)?;
    let (from, to) = super::parse_query_range(q.from.as_deref(), q.to.as_deref())?;
    let limit = super::query_count("limit", q.limit, 1000)?;
    let stored = app
        .service
        .store()
        .samples(spec.id, from, to, limit)
        .await?;
    Ok(Json(SamplesOut {
        link: spec.name,
        samples: stored
            .into_iter()
            .map(|s| {
                let (sigma, covariance) = match s.values.uncertainty {
                    MeasurementUncertainty::Default => (None, None),
                    MeasurementUncertainty::Sigmas(sg) => (Some(sg.into()), None),
                    MeasurementUncertainty::Covariance(c) => {
                        (None, Some(c.transpose().as_slice().to_vec()))
                    }
                };
                SampleOut {
                    time: format_ns(s.time_ns),
                    pose: (&s.values.pose).into(),
                    sigma,
                    covariance,
                    reprojection_rms_px: s.values.quality.reprojection_rms_px,
                    points: s.values.quality.points,
                    outlier: s.outlier,
                    disposition: s.disposition,
                    nis: s.nis,
                    received: format_ns(s.received_ns),
                }
            })
            .collect(),
    }))
}

/// Body of `PUT .../calibration`.
#[derive(Debug, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct CalibrationIn {
    /// `parent_from_child`.
    pub pose: PoseIn,
    /// Its sigmas (or `covariance`).
    pub sigma: Option<SigmaIn>,
    /// Its covariance, 36 numbers row-major.
    pub covariance: Option<Vec<f64>>,
    /// From when it is valid (RFC 3339 or ns); now when absent.
    #[schema(schema_with = crate::wire::time_schema)]
    pub valid_from: Option<serde_json::Value>,
}

/// A calibration as answered.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct CalibrationOut {
    /// Link.
    pub link: String,
    /// Version (0: the installation file's).
    pub version: i64,
    /// From when it is valid (absent: always, the installation file's).
    pub valid_from: Option<String>,
    /// `parent_from_child`.
    pub pose: Option<PoseOut>,
    /// Its sigmas.
    pub sigma: Option<SigmaOut>,
    /// When it was stored.
    pub created: Option<String>,
}

fn calibrated(spec: &LinkSpec) -> Result<PoseCov, ApiError> {
    match &spec.kind {
        LinkKind::Calibrated { parent_from_child } => Ok(*parent_from_child),
        LinkKind::Measured(_) => Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            ErrorCode::NotCalibrated,
            format!(
                "`{}` is a measured link; only calibrated links take calibrations",
                spec.name
            ),
        )),
    }
}

/// `PUT /api/v1/links/{name}/calibration`.
#[utoipa::path(put, path = "/links/{name}/calibration", tag = "links",
    params(("name" = String, Path, description = "Calibrated link name")),
    request_body(content = CalibrationIn, description = "The new `parent_from_child` and its uncertainty"),
    responses(
        (status = 201, description = "The new calibration version", body = CalibrationOut),
        (status = 400, description = "Malformed JSON", body = ErrorBody),
        (status = 404, description = "Unknown link", body = ErrorBody),
        (status = 422, description = "Invalid calibration, or a measured link", body = ErrorBody),
    ),
    security(("bearer" = ["admin"])))]
pub(super) async fn put_calibration(
    State(app): State<AppState>,
    Path(name): Path<String>,
    body: axum::body::Bytes,
) -> Result<(StatusCode, Json<CalibrationOut>), ApiError> {
    let spec = link_spec(&app, &name)?;
    calibrated(&spec)?;
    let c: CalibrationIn = super::parse_json_body(&body)?;
    let pose = c.pose.to_pose("pose").map_err(ApiError::from)?;
    let cov = match (&c.sigma, &c.covariance) {
        (Some(s), None) => {
            let sigmas = s.to_sigmas("sigma").map_err(ApiError::from)?;
            PoseCov::from_reported_sigmas(pose, &sigmas).cov
        }
        (None, Some(values)) => covariance_from("covariance", values).map_err(ApiError::from)?,
        _ => {
            return Err(ApiError::invalid_field(
                "sigma",
                "give the calibration's uncertainty as `sigma` or `covariance` (one of them)",
            ));
        }
    };
    let valid_from_ns = match &c.valid_from {
        Some(v) => parse_json_time(v).map_err(|m| ApiError::invalid_field("valid_from", m))?,
        None => app.service.now_ns(),
    };
    let version = app
        .service
        .add_calibration(spec.id, valid_from_ns, PoseCov { pose, cov })
        .await?;
    Ok((
        StatusCode::CREATED,
        Json(CalibrationOut {
            link: spec.name,
            version,
            valid_from: Some(format_ns(valid_from_ns)),
            pose: Some((&pose).into()),
            sigma: Some((&PoseCov { pose, cov }).into()),
            created: Some(format_ns(app.service.now_ns())),
        }),
    ))
}

/// `GET .../calibrations`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct CalibrationsOut {
    /// Link.
    pub link: String,
    /// The installation file's (version 0), then every stored version.
    pub calibrations: Vec<CalibrationOut>,
}

/// `GET /api/v1/links/{name}/calibrations`.
#[utoipa::path(get, path = "/links/{name}/calibrations", tag = "links",
    params(("name" = String, Path, description = "Calibrated link name")),
    responses(
        (status = 200, description = "The installation file's calibration, then every stored version", body = CalibrationsOut),
        (status = 404, description = "Unknown link", body = ErrorBody),
        (status = 422, description = "A measured link", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn list_calibrations(
    State(app): State<AppState>,
    Path(name): Path<String>,
) -> Result<Json<CalibrationsOut>, ApiError> {
    let spec = link_spec(&app, &name)?;
    let original = calibrated(&spec)?;
    let link: LinkId = spec.id;
    let mut out = vec![CalibrationOut {
        link: spec.name.clone(),
        version: 0,
        valid_from: None,
        pose: Some((&original.pose).into()),
        sigma: Some((&original).into()),
        created: None,
    }];
    for c in app.service.store().calibrations(link).await? {
        out.push(CalibrationOut {
            link: spec.name.clone(),
            version: c.version,
            valid_from: Some(format_ns(c.valid_from_ns)),
            pose: Some((&c.parent_from_child.pose).into()),
            sigma: Some((&c.parent_from_child).into()),
            created: Some(format_ns(c.created_ns)),
        });
    }
    Ok(Json(CalibrationsOut {
        link: spec.name,
        calibrations: out,
    }))
}
