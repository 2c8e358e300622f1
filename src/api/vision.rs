//! The measurement pipeline over HTTP: `POST /api/v1/observations` (raw marker observations,
//! solved by PnP and ingested as link samples) and `POST /api/v1/calibration/hand-eye`
//! (`A_i X = X B_i` for a rigid station; computes, stores nothing).

use super::AppState;
use super::dto::{PoseIn, PoseOut, SigmaOut, invalid, time_schema};
use super::error::{ApiError, ErrorBody};
use super::ingest::{IngestResponse, Problems, check_batch_size, read_body};
use super::parse_json_body;
use crate::clock::format_ns;
use crate::geometry::{Pose, PoseCov};
use crate::service::IngestItem;
use crate::vision::{HandEyeOptions, HandEyeSolution, solve_hand_eye};
use axum::Json;
use axum::body::Body;
use axum::extract::State;
use axum::http::HeaderMap;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::collections::HashSet;

/// One camera image of one marker: the measured pixel of each marker point.
#[derive(Debug, Clone, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(crate) struct ObservationIn {
    /// The camera's frame.
    pub camera: String,
    /// The marker's frame.
    pub marker: String,
    /// RFC 3339 text or integer nanoseconds.
    #[schema(schema_with = time_schema)]
    pub time: Value,
    /// Pixels `[u, v]`, in the marker's point order (or paired with `ids`).
    pub points_px: Vec<[f64; 2]>,
    /// The marker point id of each pixel, when not all points are seen or the order differs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ids: Option<Vec<u32>>,
    /// Each pixel's standard deviation (px), when a detector measured it: the point is
    /// weighted by it, the camera's `pixel_sigma` added in quadrature.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma_px: Option<Vec<f64>>,
}

/// A batch of observations, each solved and stored, or none.
#[derive(Debug, Clone, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(crate) struct ObservationsBatch {
    /// The observations.
    pub observations: Vec<ObservationIn>,
}

/// The pose PnP computed for one observation.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub(crate) struct ObservedPoseOut {
    /// The measured link `<camera>_from_<marker>`.
    pub link: String,
    /// The observation's time (RFC 3339).
    pub time: String,
    /// `camera_from_marker`.
    pub pose: PoseOut,
    /// Its sigmas, from `(J^T J)^-1 pixel_sigma^2`.
    pub sigma: SigmaOut,
    /// Reprojection RMS (px).
    pub reprojection_rms_px: f64,
    /// Points used.
    pub points: usize,
    /// RMS of the best solution over the runner-up's (0 when there is none; near 1 ambiguous).
    pub ambiguity_ratio: f64,
    /// Indices (into `points_px`) left out by robust estimation.
    pub rejected_points: Vec<usize>,
}

/// The answer to an accepted batch of observations.
#[derive(Debug, Serialize, utoipa::ToSchema)]
pub(crate) struct ObservationsResponse {
    /// What ingesting the computed samples did.
    #[serde(flatten)]
    pub ingest: IngestResponse,
    /// The computed poses, in the order of the observations.
    pub poses: Vec<ObservedPoseOut>,
}

/// `POST /api/v1/observations`.
#[utoipa::path(post, path = "/observations", tag = "ingest",
    request_body(content = ObservationsBatch, description = "Marker observations `{\"observations\": [...]}`"),
    responses(
        (status = 200, description = "Every observation solved and its sample durably stored", body = ObservationsResponse),
        (status = 400, description = "Malformed JSON", body = ErrorBody),
        (status = 409, description = "A sample differs from the one stored at the same link and time", body = ErrorBody),
        (status = 413, description = "Body or batch over the limit", body = ErrorBody),
        (status = 422, description = "An observation is invalid or cannot be solved (each named); nothing was stored", body = ErrorBody),
        (status = 503, description = "The writer is not available", body = ErrorBody),
    ),
    security(("bearer" = ["ingest"])))]
pub(crate) async fn post_observations(
    State(app): State<AppState>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<ObservationsResponse>, ApiError> {
    let bytes = read_body(body, &headers, app.limits.max_body_bytes).await?;
    let batch: ObservationsBatch = parse_json_body(&bytes)?;
    check_batch_size(
        "observations",
        batch.observations.len(),
        app.limits.max_batch_samples,
    )?;
    let observer = app.service.observer();
    // PnP is CPU work (tens of microseconds per observation): off the async workers.
    let latest = crate::clock::latest_accepted_ns(
        app.service.now_ns(),
        app.service.installation().server.max_future_s,
    );
    let solved = blocking(move || solve_batch(&observer, &batch.observations, latest)).await?;
    let (items, poses) = solved.map_err(|problems| {
        invalid(
            format!(
                "{} observation problem(s); nothing was stored",
                problems.len()
            ),
            problems,
        )
    })?;
    let report = app.service.ingest(items).await?;
    Ok(Json(ObservationsResponse {
        ingest: report.into(),
        poses,
    }))
}

/// Runs CPU work on the blocking pool; a panic in it is a 500.
pub(super) async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> T + Send + 'static,
) -> Result<T, ApiError> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| ApiError::internal(e.to_string()))
}

/// Solves every observation, or lists every problem.
fn solve_batch(
    observer: &crate::model::Observer,
    observations: &[ObservationIn],
    latest_ns: i64,
) -> Result<(Vec<IngestItem>, Vec<ObservedPoseOut>), Problems> {
    let mut problems: Problems = Vec::new();
    let mut items = Vec::with_capacity(observations.len());
    let mut poses = Vec::with_capacity(observations.len());
    let mut seen = HashSet::new();
    for (index, o) in observations.iter().enumerate() {
        let time_ns = match crate::clock::parse_measurement_time(&o.time, latest_ns) {
            Ok(t) => t,
            Err(m) => {
                problems.push((Some(index), ("time".to_owned(), m)));
                continue;
            }
        };
        let (link, solution) = match observer.solve(
            &o.camera,
            &o.marker,
            &o.points_px,
            o.ids.as_deref(),
            o.sigma_px.as_deref(),
        ) {
            Ok(v) => v,
            Err(e) => {
                problems.push((Some(index), (e.field.to_owned(), e.message)));
                continue;
            }
        };
        if !seen.insert((link.link.0, time_ns)) {
            problems.push((
                Some(index),
                (
                    "time".to_owned(),
                    format!(
                        "a second observation of `{}` at the same time in this batch",
                        link.name
                    ),
                ),
            ));
            continue;
        }
        let cov = PoseCov {
            pose: solution.camera_from_marker,
            cov: solution.covariance,
        };
        poses.push(ObservedPoseOut {
            link: link.name.clone(),
            time: format_ns(time_ns),
            pose: PoseOut::from(&solution.camera_from_marker),
            sigma: SigmaOut::from(&cov),
            reprojection_rms_px: solution.rms_px,
            points: solution.points,
            ambiguity_ratio: solution.ambiguity_ratio,
            rejected_points: solution.rejected_points.clone(),
        });
        items.push(crate::intake::solved_item(
            index, link.link, time_ns, &solution,
        ));
    }
    if problems.is_empty() {
        Ok((items, poses))
    } else {
        Err(problems)
    }
}

/// One motion of the station: `a` seen by the first sensor, `b` by the second.
#[derive(Debug, Clone, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(crate) struct HandEyePairIn {
    /// Motion `A_i`.
    pub a: PoseIn,
    /// Motion `B_i`.
    pub b: PoseIn,
}

/// The noise of the measured motions, for weighting the refinement.
#[derive(Debug, Clone, Copy, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(crate) struct HandEyeSigmaIn {
    /// Rotation (arc-seconds).
    pub rotation_arcsec: f64,
    /// Translation (mm).
    pub translation_mm: f64,
}

/// `A_i X = X B_i`: the motions, at least three about non-parallel axes.
#[derive(Debug, Clone, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub(crate) struct HandEyeIn {
    /// The motions.
    pub pairs: Vec<HandEyePairIn>,
    /// Their noise (default 10 arc-seconds, 0.1 mm).
    pub sigma: Option<HandEyeSigmaIn>,
}

/// How one pair agrees with X.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub(crate) struct PairResidualOut {
    /// Rotation of `A_i X (X B_i)^-1` (arc-seconds).
    pub rotation_arcsec: f64,
    /// Translation of `A_i X (X B_i)^-1` (mm).
    pub translation_mm: f64,
}

/// The fit's residuals.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub(crate) struct HandEyeResidualsOut {
    /// Per pair, in input order.
    pub pairs: Vec<PairResidualOut>,
    /// RMS of the rotation residuals (arc-seconds).
    pub rms_rotation_arcsec: f64,
    /// RMS of the translation residuals (mm).
    pub rms_translation_mm: f64,
}

/// The rotation spread of the input motions.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub(crate) struct SpreadOut {
    /// Smallest rotation of a motion (degrees).
    pub min_rotation_deg: f64,
    /// Largest rotation of a motion (degrees).
    pub max_rotation_deg: f64,
    /// Largest angle between two motion axes (degrees, up to 90).
    pub max_axis_angle_deg: f64,
}

/// The solved station link.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub(crate) struct HandEyeOut {
    /// X.
    pub x: PoseOut,
    /// X's sigmas (from the weighted fit, scaled by its variance factor).
    pub sigma: SigmaOut,
    /// X's covariance, 36 numbers row-major, `[rho_mm; phi_rad]`: ready for
    /// `PUT /links/{name}/calibration`.
    pub covariance: Vec<f64>,
    /// How the pairs agree with X.
    pub residuals: HandEyeResidualsOut,
    /// The input motions' spread.
    pub spread: SpreadOut,
    /// Park and Martin's closed form, before refinement.
    pub closed_form: PoseOut,
    /// Refinement iterations.
    pub iterations: usize,
}

impl From<&HandEyeSolution> for HandEyeOut {
    fn from(s: &HandEyeSolution) -> Self {
        let cov = PoseCov {
            pose: s.x,
            cov: s.covariance,
        };
        Self {
            x: PoseOut::from(&s.x),
            sigma: SigmaOut::from(&cov),
            covariance: s.covariance.transpose().iter().copied().collect(),
            residuals: HandEyeResidualsOut {
                pairs: s
                    .residuals
                    .iter()
                    .map(|r| PairResidualOut {
                        rotation_arcsec: r.rotation_arcsec,
                        translation_mm: r.translation_mm,
                    })
                    .collect(),
                rms_rotation_arcsec: s.rms_rotation_arcsec,
                rms_translation_mm: s.rms_translation_mm,
            },
            spread: SpreadOut {
                min_rotation_deg: s.spread.min_rotation_deg,
                max_rotation_deg: s.spread.max_rotation_deg,
                max_axis_angle_deg: s.spread.max_axis_angle_deg,
            },
            closed_form: PoseOut::from(&s.closed_form),
            iterations: s.iterations,
        }
    }
}

impl HandEyeIn {
    /// Validates the poses and solves; every invalid pose is named, a refusal says why.
    pub(crate) fn solve(&self) -> Result<HandEyeOut, ApiError> {
        let mut problems = Vec::new();
        let mut pairs: Vec<(Pose, Pose)> = Vec::with_capacity(self.pairs.len());
        for (i, p) in self.pairs.iter().enumerate() {
            match (p.a.to_pose("a"), p.b.to_pose("b")) {
                (Ok(a), Ok(b)) => pairs.push((a, b)),
                (a, b) => {
                    problems.extend(a.err().into_iter().chain(b.err()).map(|e| (Some(i), e)));
                }
            }
        }
        let mut options = HandEyeOptions::default();
        if let Some(s) = self.sigma {
            // A measurement's noise, from a thousandth of an arc-second (or a nanometre) to
            // a hundred degrees (or a hundred metres): beyond, the weights overflow.
            for (field, v, lo, hi) in [
                ("sigma.rotation_arcsec", s.rotation_arcsec, 1e-3, 3.6e5),
                ("sigma.translation_mm", s.translation_mm, 1e-6, 1e5),
            ] {
                if !(v.is_finite() && (lo..=hi).contains(&v)) {
                    problems.push((
                        None,
                        (
                            field.to_owned(),
                            format!("must lie in [{lo}, {hi}], not {v}"),
                        ),
                    ));
                }
            }
            options.sigma_rotation_arcsec = s.rotation_arcsec;
            options.sigma_translation_mm = s.translation_mm;
        }
        if !problems.is_empty() {
            return Err(invalid(
                format!("{} invalid pose(s) or setting(s)", problems.len()),
                problems,
            ));
        }
        let solution = solve_hand_eye(&pairs, &options).map_err(super::calibration::refused)?;
        Ok(HandEyeOut::from(&solution))
    }
}

/// `POST /api/v1/calibration/hand-eye`.
#[utoipa::path(post, path = "/calibration/hand-eye", tag = "calibration",
    request_body(content = HandEyeIn, description = "The motions of the station: `A_i X = X B_i`"),
    responses(
        (status = 200, description = "X with its residuals and the motions' spread", body = HandEyeOut),
        (status = 400, description = "Malformed JSON", body = ErrorBody),
        (status = 422, description = "An invalid pose, or motions that cannot determine X (too few, too small, inconsistent, parallel axes)", body = ErrorBody),
    ),
    security(("bearer" = ["admin"])))]
pub(crate) async fn post_hand_eye(
    State(app): State<AppState>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<HandEyeOut>, ApiError> {
    let bytes = read_body(body, &headers, app.limits.max_body_bytes).await?;
    let input: HandEyeIn = parse_json_body(&bytes)?;
    let out = blocking(move || input.solve()).await??;
    Ok(Json(out))
}
