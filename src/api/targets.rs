//! Targets: list, compensation, statistics, references.

use super::AppState;
use super::error::{ApiError, ErrorBody};
use super::query::Query;
use crate::bank::{TargetEstimate, TargetStatus};
use crate::clock::{format_ns, parse_query_time};
use crate::deformation::{MeasuredPose, ReferenceOrigin, ReferenceVersion};
use crate::model::TargetId;
use crate::model::TargetSpec;
use crate::service::ReferenceRequest;
pub(super) use crate::service::{CompensationSource, Evaluated};
use crate::wire::{PoseIn, PoseOut, SigmaOut, rotation_vector_arcsec};
use axum::Json;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use serde::{Deserialize, Serialize};

pub(super) fn target_index(app: &AppState, name: &str) -> Result<(TargetId, TargetSpec), ApiError> {
    app.service
        .installation()
        .model
        .target_ids()
        .find(|(_, t)| t.name == name)
        .map(|(i, t)| (i, t.clone()))
        .ok_or_else(|| ApiError::not_found(format!("unknown target `{name}`")))
}

pub(super) use crate::fleet::protocol::{PathOut, ThresholdsOut};

/// A target as listed.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct TargetOut {
    /// Its name (frame).
    pub name: String,
    /// Its base frame.
    pub base: String,
    /// Current status.
    pub status: TargetStatus,
    /// Time of the newest filtered result.
    pub time: Option<String>,
    /// Independent paths (fused).
    pub paths: Vec<PathOut>,
    /// Further paths sharing a link with one above (not fused).
    pub dependent_paths: Vec<PathOut>,
    /// Its alarm thresholds.
    pub alarms: ThresholdsOut,
}

/// `GET /api/v1/targets`.
#[utoipa::path(get, path = "/targets", tag = "targets",
    responses((status = 200, description = "Every target with its paths and status", body = [TargetOut])),
    security(("bearer" = ["read"])))]
pub(super) async fn list_targets(State(app): State<AppState>) -> Json<Vec<TargetOut>> {
    let snapshot = app.service.snapshot();
    Json(
        crate::fleet::protocol::describe_targets(&app.service.installation().model)
            .into_iter()
            .enumerate()
            .map(|(i, d)| {
                let latest = snapshot.targets[i].latest.as_ref();
                TargetOut::new(
                    d,
                    latest.map_or(TargetStatus::Initializing, |l| l.status),
                    latest.map(|l| l.time_ns),
                )
            })
            .collect(),
    )
}

impl TargetOut {
    /// A target as its installation describes it, with its status and newest result's time.
    pub(super) fn new(
        d: crate::fleet::protocol::TargetDescription,
        status: TargetStatus,
        time_ns: Option<i64>,
    ) -> Self {
        TargetOut {
            name: d.name,
            base: d.base,
            status,
            time: time_ns.map(format_ns),
            paths: d.paths,
            dependent_paths: d.dependent_paths,
            alarms: d.alarms,
        }
    }
}

/// A reference as answered.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct ReferenceOut {
    /// Translation of `G0_from_B` (mm).
    pub t_mm: [f64; 3],
    /// Rotation (quaternion).
    pub q_wxyz: [f64; 4],
    /// Rotation (Euler, degrees).
    pub euler_deg: [f64; 3],
    /// When it was set.
    pub since: String,
    /// Its version.
    pub version: i64,
    /// `explicit` or `window`.
    pub origin: super::vocab::ReferenceOriginKind,
    /// The averaged window, for a `window` reference.
    pub window: Option<WindowOut>,
    /// Its own uncertainty (zero for an explicit one).
    pub sigma: SigmaOut,
    /// The part of `sigma` from the noise of the averaged results.
    pub sigma_random: SigmaOut,
    /// The part of `sigma` from calibrations (it cancels in a deformation measured with the
    /// same calibrations).
    pub sigma_systematic: SigmaOut,
}

/// A reference's window.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct WindowOut {
    /// Start.
    pub from: String,
    /// End.
    pub to: String,
    /// Results averaged.
    pub count: usize,
}

impl From<&ReferenceVersion> for ReferenceOut {
    fn from(r: &ReferenceVersion) -> Self {
        let p = PoseOut::from(r.reference.g0_from_b.pose());
        let sigmas = r.reference.g0_from_b.sigmas();
        let (origin, window) = match r.reference.origin {
            ReferenceOrigin::Explicit => (super::vocab::ReferenceOriginKind::Explicit, None),
            ReferenceOrigin::Window {
                from_ns,
                to_ns,
                count,
            } => (
                super::vocab::ReferenceOriginKind::Window,
                Some(WindowOut {
                    from: format_ns(from_ns),
                    to: format_ns(to_ns),
                    count,
                }),
            ),
        };
        Self {
            t_mm: p.t_mm,
            q_wxyz: p.q_wxyz,
            euler_deg: p.euler_deg,
            since: format_ns(r.created_ns),
            version: r.version,
            origin,
            window,
            sigma: sigmas.whole.into(),
            sigma_random: sigmas.random.into(),
            sigma_systematic: sigmas.systematic.into(),
        }
    }
}

/// A deformation as answered (`G0_from_G`).
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct DeformationOut {
    /// Rotation vector (arc-seconds, reference target axes).
    pub rotation_arcsec: [f64; 3],
    /// Translation (mm, reference target coordinates).
    pub translation_mm: [f64; 3],
    /// Their sigmas: the whole uncertainty.
    pub sigma: SigmaOut,
    /// The part of `sigma` from the noise of the result and of the reference.
    pub sigma_random: SigmaOut,
    /// The part of `sigma` from calibrations: zero when the reference was measured with the
    /// same calibrations as the result (their error cancels), both parts after a calibration
    /// changed.
    pub sigma_systematic: SigmaOut,
}

/// A correction as answered (`G_from_G0`).
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct CorrectionOut {
    /// Rotation (quaternion).
    pub q_wxyz: [f64; 4],
    /// Translation (mm).
    pub t_mm: [f64; 3],
    /// Rotation vector (arc-seconds).
    pub rotation_arcsec: [f64; 3],
    /// Sigmas.
    pub sigma: SigmaOut,
}

/// Redundant paths' agreement.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct ConsistencyOut {
    /// Chi-square of the paths' disagreement.
    pub chi2: f64,
    /// Degrees of freedom.
    pub dof: usize,
    /// The threshold.
    pub threshold: f64,
}

/// `GET .../compensation`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct CompensationOut {
    /// Target name.
    pub target: String,
    /// Base frame.
    pub base: String,
    /// Time of the result.
    pub time: Option<String>,
    /// Live: seconds from the result's time to now on the server's clock. For a time asked
    /// for: seconds from the newest sample behind it to that time. Null before any result.
    pub age_s: Option<f64>,
    /// `ok`, `stale`, `degraded`, `initializing` or `predicted`.
    pub status: TargetStatus,
    /// Where the value comes from.
    pub source: CompensationSource,
    /// `G_from_B`.
    pub pose: Option<PoseOut>,
    /// Its sigmas: the whole uncertainty (the truth lies within it).
    pub sigma: Option<SigmaOut>,
    /// The part of `sigma` from the samples' noise: what the filter averages down, the
    /// repeatability.
    pub sigma_random: Option<SigmaOut>,
    /// The part of `sigma` from the cameras' intrinsics and the calibrated links: the same in
    /// every result, so no filtering reduces it.
    pub sigma_systematic: Option<SigmaOut>,
    /// The current reference.
    pub reference: Option<ReferenceOut>,
    /// `G0_from_G`.
    pub deformation: Option<DeformationOut>,
    /// `G_from_G0`.
    pub correction: Option<CorrectionOut>,
    /// `none`, `warn` or `alarm`: live, the target's alarm state (hysteresis, dwell, rate,
    /// stale); for another time, the deformation against the thresholds.
    pub alarm: crate::alarms::Level,
    /// Redundant paths' agreement, where several were fused.
    pub consistency: Option<ConsistencyOut>,
}

/// Whose compensation is answered: a target's name, base frame and thresholds.
pub(super) struct Described<'a> {
    /// The target.
    pub name: &'a str,
    /// Its base frame.
    pub base: &'a str,
    /// Its deformation thresholds.
    pub thresholds: crate::alarms::AlarmThresholds,
}

impl<'a> Described<'a> {
    /// A target of this service's installation.
    fn of(service: &'a crate::service::Service, spec: &'a TargetSpec) -> Self {
        Described {
            name: &spec.name,
            base: service.installation().model.topology.frame_name(spec.base),
            thresholds: spec.alarms,
        }
    }
}

pub(super) fn compensation_out(
    target: &Described<'_>,
    e: Evaluated,
    reference: Option<&ReferenceVersion>,
) -> CompensationOut {
    let deformation = e.deformation(reference);
    let sigmas = e.estimate.as_ref().map(MeasuredPose::sigmas);
    CompensationOut {
        target: target.name.to_owned(),
        base: target.base.to_owned(),
        time: e.time_ns.map(format_ns),
        age_s: e.age_s,
        status: e.status,
        source: e.source,
        pose: e.estimate.as_ref().map(|e| e.pose().into()),
        sigma: sigmas.map(|s| s.whole.into()),
        sigma_random: sigmas.map(|s| s.random.into()),
        sigma_systematic: sigmas.map(|s| s.systematic.into()),
        reference: reference.map(Into::into),
        deformation: deformation.map(|d| {
            let m = d.deformation();
            let parts = d.g0_from_g.sigmas();
            DeformationOut {
                rotation_arcsec: m.rotation_arcsec,
                translation_mm: m.translation_mm,
                sigma: m.sigmas.into(),
                sigma_random: parts.random.into(),
                sigma_systematic: parts.systematic.into(),
            }
        }),
        correction: deformation.map(|d| {
            let c = d.correction();
            let p = PoseOut::from(&d.g_from_g0.pose);
            CorrectionOut {
                q_wxyz: p.q_wxyz,
                t_mm: p.t_mm,
                rotation_arcsec: rotation_vector_arcsec(&d.g_from_g0.pose),
                sigma: c.sigmas.into(),
            }
        }),
        alarm: deformation.map_or(crate::alarms::Level::None, |d| {
            let m = d.deformation();
            crate::alarms::threshold_level(
                &target.thresholds,
                m.rotation_magnitude_arcsec(),
                m.translation_magnitude_mm(),
            )
        }),
        consistency: e.consistency.map(|c| ConsistencyOut {
            chi2: c.chi2,
            dof: c.dof,
            threshold: c.threshold,
        }),
    }
}

/// The compensation JSON of a live result of target `ti` (for the event stream and the
/// plant's outputs).
pub(super) fn live_compensation(
    service: &crate::service::Service,
    spec: &TargetSpec,
    ti: TargetId,
    estimate: &TargetEstimate,
    reference: Option<&ReferenceVersion>,
) -> CompensationOut {
    compensation_out(
        &Described::of(service, spec),
        service.evaluate_live(ti, estimate),
        reference,
    )
}

/// The encoders the plant's outputs publish with: the event stream's compensation and the
/// alarms' JSON, so that a bus and the API cannot differ.
pub fn output_encoders(service: &crate::service::Service) -> crate::outputs::Encoders {
    let service = service.clone();
    crate::outputs::Encoders {
        compensation: std::sync::Arc::new(move |ti, estimate, reference| {
            let spec = &service.installation().model.targets[ti.0];
            serde_json::to_vec(&live_compensation(&service, spec, ti, estimate, reference))
        }),
        alarm: super::alarms::encode_alarm,
    }
}

/// Query of `compensation`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub(super) struct AtQuery {
    /// A past or future time (RFC 3339 or integer ns); the newest result without it.
    pub at: Option<String>,
}

/// `GET /api/v1/targets/{name}/compensation[?at=TIME]`.
#[utoipa::path(get, path = "/targets/{name}/compensation", tag = "targets",
    params(("name" = String, Path, description = "Target frame"), AtQuery),
    responses(
        (status = 200, description = "The current (or asked-for) pose, deformation and correction", body = CompensationOut),
        (status = 404, description = "Unknown target, or no result at that time", body = ErrorBody),
        (status = 422, description = "Invalid `at`", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_compensation(
    State(app): State<AppState>,
    Path(name): Path<String>,
    Query(q): Query<AtQuery>,
) -> Result<Json<CompensationOut>, ApiError> {
    let (ti, spec) = target_index(&app, &name)?;
    let target = Described::of(&app.service, &spec);
    let snapshot = app.service.snapshot();
    let view = &snapshot.targets[ti.0];
    let reference = view.reference.as_ref();
    let Some(at) = q.at else {
        return Ok(Json(match &view.latest {
            Some(l) => {
                let mut out =
                    compensation_out(&target, app.service.evaluate_live(ti, l), reference);
                // Live: the alarm state with its hysteresis, dwell, rate and stale tracks.
                out.alarm = view.alarms.level();
                out
            }
            None => compensation_out(
                &target,
                Evaluated::none(CompensationSource::Live),
                reference,
            ),
        }));
    };
    let at_ns = parse_query_time(&at).map_err(|m| ApiError::invalid_field("at", m))?;
    // Predict only past the newest state of every link on the paths; before that, the stored
    // results answer (the published filters keep no past states).
    let newest_ns = snapshot.bank.latest_time_ns(ti);
    if view.latest.is_some() && newest_ns.is_some_and(|l| at_ns >= l) {
        let est: TargetEstimate = snapshot
            .bank
            .evaluate(ti, at_ns)
            .map_err(|e| ApiError::invalid_field("at", e.to_string()))?;
        let source = if est.status == TargetStatus::Predicted {
            CompensationSource::Predicted
        } else {
            CompensationSource::Live
        };
        return Ok(Json(compensation_out(
            &target,
            Evaluated::estimated(&est, source),
            reference,
        )));
    }
    let e = Evaluated::from_history(app.service.store(), ti, &name, at_ns).await?;
    Ok(Json(compensation_out(&target, e, reference)))
}

/// Body of `POST .../reference`.
#[derive(Debug, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct ReferenceIn {
    /// Window start (with `to`).
    #[schema(schema_with = crate::wire::time_schema)]
    pub from: Option<serde_json::Value>,
    /// Window end (with `from`).
    #[schema(schema_with = crate::wire::time_schema)]
    pub to: Option<serde_json::Value>,
    /// An explicit `G0_from_B` (instead of a window).
    pub pose: Option<PoseIn>,
}

/// `POST /api/v1/targets/{name}/reference`.
#[utoipa::path(post, path = "/targets/{name}/reference", tag = "targets",
    params(("name" = String, Path, description = "Target frame")),
    request_body(content = ReferenceIn, description = "An explicit `G0_from_B`, or a window of filtered results to average"),
    responses(
        (status = 201, description = "The new reference version", body = ReferenceOut),
        (status = 400, description = "Malformed JSON", body = ErrorBody),
        (status = 404, description = "Unknown target", body = ErrorBody),
        (status = 422, description = "Invalid reference, or an empty window", body = ErrorBody),
    ),
    security(("bearer" = ["admin"])))]
pub(super) async fn post_reference(
    State(app): State<AppState>,
    Path(name): Path<String>,
    body: axum::body::Bytes,
) -> Result<(StatusCode, Json<ReferenceOut>), ApiError> {
    let (ti, _) = target_index(&app, &name)?;
    let r: ReferenceIn = super::parse_json_body(&body)?;
    let request = match (r.pose, r.from, r.to) {
        (Some(p), None, None) => {
            ReferenceRequest::Explicit(p.to_pose("pose").map_err(ApiError::from)?)
        }
        (None, Some(from), Some(to)) => {
            let from_ns = crate::clock::parse_json_time(&from)
                .map_err(|m| ApiError::invalid_field("from", m))?;
            let to_ns =
                crate::clock::parse_json_time(&to).map_err(|m| ApiError::invalid_field("to", m))?;
            if from_ns > to_ns {
                return Err(ApiError::invalid_field("to", "`to` is before `from`"));
            }
            ReferenceRequest::Window { from_ns, to_ns }
        }
        _ => {
            return Err(ApiError::invalid_field(
                "pose",
                "give either `pose`, or both `from` and `to` (a window of filtered results)",
            ));
        }
    };
    let current = app.service.set_reference(ti, request).await?;
    Ok((StatusCode::CREATED, Json((&current).into())))
}

/// `GET /api/v1/targets/{name}/reference`.
#[utoipa::path(get, path = "/targets/{name}/reference", tag = "targets",
    params(("name" = String, Path, description = "Target frame")),
    responses(
        (status = 200, description = "The current reference", body = ReferenceOut),
        (status = 404, description = "Unknown target, or no reference yet", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_reference(
    State(app): State<AppState>,
    Path(name): Path<String>,
) -> Result<Json<ReferenceOut>, ApiError> {
    let (ti, _) = target_index(&app, &name)?;
    let snapshot = app.service.snapshot();
    snapshot.targets[ti.0]
        .reference
        .as_ref()
        .map(|r| Json(r.into()))
        .ok_or_else(|| ApiError::not_found(format!("target `{name}` has no reference yet")))
}

/// `GET .../filter`: how the target is filtered now.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct TargetFilterOut {
    /// Target.
    pub target: String,
    /// The motion model (the most dynamic of the target's measured links').
    pub model: crate::filter::MotionModel,
    /// Whether the tuning below was fitted from the target's own results (`true`) or is the
    /// configured one (`false`: not adaptive, or too little data yet).
    pub fitted: bool,
    /// Measurement time of the fit in force, when fitted.
    pub since: Option<String>,
    /// Raw results the fit used.
    pub fit_samples: Option<usize>,
    /// The oscillation's period (s); `oscillatory` only.
    pub oscillation_period_s: Option<f64>,
    /// How long the oscillation keeps its phase (s): `1 / mu`, its damping; `oscillatory`
    /// only.
    pub oscillation_correlation_time_s: Option<f64>,
    /// The oscillation's stationary sigma per axis, rotation (arc-seconds); `oscillatory` only.
    pub oscillation_rotation_arcsec: Option<[f64; 3]>,
    /// The oscillation's stationary sigma per axis, translation (mm); `oscillatory` only.
    pub oscillation_translation_mm: Option<[f64; 3]>,
    /// The pose's (for `oscillatory`, the mean's) random walk, rotation (arc-seconds per
    /// square-root second); `static` and `oscillatory`.
    pub drift_rotation_arcsec_per_sqrt_s: Option<f64>,
    /// The random walk, translation (mm per square-root second); `static` and `oscillatory`.
    pub drift_translation_mm_per_sqrt_s: Option<f64>,
    /// White-noise acceleration, rotation (arc-seconds per second per square-root second);
    /// `constant_velocity` only.
    pub acceleration_rotation_arcsec_per_s_sqrt_s: Option<f64>,
    /// White-noise acceleration, translation (mm per second per square-root second);
    /// `constant_velocity` only.
    pub acceleration_translation_mm_per_s_sqrt_s: Option<f64>,
    /// Mean normalised innovation squared of the recent results (6 when the filter fits).
    pub mean_nis: Option<f64>,
    /// How many results that mean is over.
    pub nis_samples: usize,
    /// The band a fitting filter's mean stays in (99.9 %).
    pub nis_band: [f64; 2],
    /// False when the mean is outside its band: the model or its tuning does not fit the data.
    pub consistent: bool,
}

/// `GET /api/v1/targets/{name}/filter`.
#[utoipa::path(get, path = "/targets/{name}/filter", tag = "targets",
    params(("name" = String, Path, description = "Target frame")),
    responses(
        (status = 200, description = "The target filter's model, its tuning (fitted from the data or configured) and its consistency", body = TargetFilterOut),
        (status = 404, description = "Unknown target", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn get_filter(
    State(app): State<AppState>,
    Path(name): Path<String>,
) -> Result<Json<TargetFilterOut>, ApiError> {
    let (ti, _) = target_index(&app, &name)?;
    let snapshot = app.service.snapshot();
    let t = snapshot
        .bank
        .target_tuning(ti)
        .ok_or_else(|| ApiError::not_found(format!("unknown target `{name}`")))?;
    let o = &t.tuning.oscillation;
    let model = t.tuning.model;
    let oscillatory = model == crate::filter::MotionModel::Oscillatory;
    let cv = model == crate::filter::MotionModel::ConstantVelocity;
    Ok(Json(TargetFilterOut {
        target: name,
        model,
        fitted: t.fit.is_some(),
        since: t.fit.map(|f| format_ns(f.time_ns)),
        fit_samples: t.fit.map(|f| f.samples),
        oscillation_period_s: oscillatory.then_some(o.period_s),
        oscillation_correlation_time_s: oscillatory.then_some(o.correlation_time_s),
        oscillation_rotation_arcsec: oscillatory.then_some(o.rotation_arcsec),
        oscillation_translation_mm: oscillatory.then_some(o.translation_mm),
        drift_rotation_arcsec_per_sqrt_s: (!cv)
            .then_some(t.tuning.random_walk_rotation_arcsec_per_sqrt_s),
        drift_translation_mm_per_sqrt_s: (!cv)
            .then_some(t.tuning.random_walk_translation_mm_per_sqrt_s),
        acceleration_rotation_arcsec_per_s_sqrt_s: cv
            .then_some(t.tuning.acceleration_rotation_arcsec_per_s_sqrt_s),
        acceleration_translation_mm_per_s_sqrt_s: cv
            .then_some(t.tuning.acceleration_translation_mm_per_s_sqrt_s),
        mean_nis: t
            .consistency
            .mean_nis
            .is_finite()
            .then_some(t.consistency.mean_nis),
        nis_samples: t.consistency.samples,
        nis_band: [t.consistency.band.0, t.consistency.band.1],
        consistent: t.consistency.fits(),
    }))
}

/// `GET .../references`.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(super) struct ReferencesOut {
    /// Target.
    pub target: String,
    /// Every version, oldest first.
    pub references: Vec<ReferenceOut>,
}

/// `GET /api/v1/targets/{name}/references`.
#[utoipa::path(get, path = "/targets/{name}/references", tag = "targets",
    params(("name" = String, Path, description = "Target frame")),
    responses(
        (status = 200, description = "Every reference version, oldest first", body = ReferencesOut),
        (status = 404, description = "Unknown target", body = ErrorBody),
    ),
    security(("bearer" = ["read"])))]
pub(super) async fn list_references(
    State(app): State<AppState>,
    Path(name): Path<String>,
) -> Result<Json<ReferencesOut>, ApiError> {
    let (ti, spec) = target_index(&app, &name)?;
    Ok(Json(
        references_of(app.service.store(), ti, spec.name).await?,
    ))
}

/// Every reference version of target `ti` of `store`, named `name`, oldest first.
pub(super) async fn references_of(
    store: &crate::store::Store,
    ti: TargetId,
    name: String,
) -> Result<ReferencesOut, ApiError> {
    let stored = store.references(ti).await?;
    Ok(ReferencesOut {
        target: name,
        references: stored.iter().map(Into::into).collect(),
    })
}
