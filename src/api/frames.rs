//! `POST /api/v1/frames`: one camera frame in; its disc targets detected, each marker the
//! camera sees through a measured link identified and solved, and the found ones ingested as
//! link samples exactly as `/observations` does (atomic, durable before the answer).
//!
//! The frame itself is not stored in the database; the newest of each camera is kept in memory
//! with its answer ([`super::cameras`]). Decoding and detection are CPU work: they run on the
//! blocking pool, never on the async workers.

use super::AppState;
use super::dto::{PoseOut, SigmaOut};
use super::error::{ApiError, ErrorBody};
use super::ingest::{IngestResponse, read_body};
use super::query::Query;
use crate::api::error::ErrorCode;
use crate::archive::ArchiveReason;
use crate::clock::format_ns;
use crate::geometry::{Pose, PoseCov};
use crate::imagefile::{FrameFileError, FrameFormat, decode};
use crate::model::{FrameObservation, NotFound, ObservedLink, observe_frame_paced};
use crate::service::IngestItem;
use axum::Json;
use axum::body::Body;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode, header};
use serde::{Deserialize, Serialize};

/// Query of `POST /frames`.
#[derive(Debug, Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Query)]
#[serde(deny_unknown_fields)]
pub(super) struct FrameQuery {
    /// The camera's frame (required).
    pub camera: Option<String>,
    /// The frame's measurement time, RFC 3339 or integer nanoseconds (required).
    pub time: Option<String>,
}

crate::words! {
    /// Why a marker was not found, as a stable code.
    pub enum NotFoundCode("reason code") {
        /// The marker declares no disc target.
        NoTarget = "no_target",
        /// No filtered or nominal pose to predict its points from.
        NoPrediction = "no_prediction",
        /// Not in front of the camera at the predicted pose.
        NotInView = "not_in_view",
        /// Too few points found near their predictions.
        TooFewPoints = "too_few_points",
        /// PnP refused the matched points.
        PnpRefused = "pnp_refused",
        /// Searched with no prior, no identification used every visible point.
        NotIdentified = "not_identified",
        /// Searched with no prior, two contradicting identifications fit.
        Ambiguous = "ambiguous",
        /// A disc was found as a point of two markers.
        SharedPoints = "shared_points",
        /// Not found near its predictions; lost, it is searched for in the whole frame again
        /// once its interval has passed.
        SearchPaced = "search_paced",
    }
}

impl From<&NotFound> for NotFoundCode {
    fn from(n: &NotFound) -> Self {
        match n {
            NotFound::NoTarget => NotFoundCode::NoTarget,
            NotFound::NoPrediction => NotFoundCode::NoPrediction,
            NotFound::NotInView => NotFoundCode::NotInView,
            NotFound::TooFewPoints { .. } => NotFoundCode::TooFewPoints,
            NotFound::Pnp(_) => NotFoundCode::PnpRefused,
            NotFound::NotIdentified { .. } => NotFoundCode::NotIdentified,
            NotFound::Ambiguous { .. } => NotFoundCode::Ambiguous,
            NotFound::SharedPoints { .. } => NotFoundCode::SharedPoints,
            NotFound::SearchPaced { .. } => NotFoundCode::SearchPaced,
        }
    }
}

/// What the frame showed of one marker.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub(super) struct FrameMarkerOut {
    /// The marker's frame.
    pub marker: String,
    /// The measured link `<camera>_from_<marker>`.
    pub link: String,
    /// Whether its pose was measured (and ingested).
    pub found: bool,
    /// The images of the disc centres, eccentricity corrected (px).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub points_px: Option<Vec<[f64; 2]>>,
    /// The point id of each.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub ids: Option<Vec<u32>>,
    /// Each point's standard deviation from the detector (px).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma_px: Option<Vec<f64>>,
    /// `camera_from_marker`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pose: Option<PoseOut>,
    /// Its sigmas.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sigma: Option<SigmaOut>,
    /// Each point of `ids` projected with the solved pose (px): `points_px` minus these are
    /// the residuals.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reprojected_px: Option<Vec<[f64; 2]>>,
    /// Reprojection RMS (px).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reprojection_rms_px: Option<f64>,
    /// Indices (into `points_px`) left out by robust estimation.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rejected_points: Option<Vec<usize>>,
    /// Why it was not found (a sentence).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Why it was not found (a stable code).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason_code: Option<NotFoundCode>,
}

/// The answer to a frame.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub(super) struct FrameOut {
    /// The camera.
    pub camera: String,
    /// The frame's time (RFC 3339).
    pub time: String,
    /// Discs detected in the searched part of the frame.
    pub blobs: usize,
    /// The share of the frame searched (only where the predicted marker points' gates reach),
    /// summed over the polarities searched.
    pub searched_fraction: f64,
    /// Each marker of a measured link of the camera, in installation order.
    pub markers: Vec<FrameMarkerOut>,
    /// What ingesting the found markers' samples did.
    pub ingest: IngestResponse,
}

/// How long a frame waits for a decoding slot before it is answered 503 `busy`.
const DECODE_WAIT: std::time::Duration = std::time::Duration::from_secs(5);

/// `POST /api/v1/frames`.
#[utoipa::path(post, path = "/frames", tag = "ingest",
    params(FrameQuery),
    request_body(content = Vec<u8>, description = "The frame: PNG, JPEG, TIFF or binary PGM, 8 or 16 bit (colour taken as its luma), the camera's size",
        content_type = "image/png"),
    responses(
        (status = 200, description = "Markers found or not (each with the reason); found ones durably stored as samples", body = FrameOut),
        (status = 409, description = "A sample differs from the one stored at the same link and time", body = ErrorBody),
        (status = 413, description = "Body over `max_body_bytes`", body = ErrorBody),
        (status = 415, description = "Not PNG, JPEG, TIFF or PGM", body = ErrorBody),
        (status = 422, description = "Unknown camera, missing or unbelievable time, undecodable data or a size other than the camera's (each named); nothing was stored", body = ErrorBody),
        (status = 503, description = "The writer is not available, or every decoding slot stayed taken for 5 s (`busy`)", body = ErrorBody),
    ),
    security(("bearer" = ["ingest"])))]
pub(super) async fn post_frame(
    State(app): State<AppState>,
    Query(q): Query<FrameQuery>,
    headers: HeaderMap,
    body: Body,
) -> Result<Json<FrameOut>, ApiError> {
    let content_type = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    let format = FrameFormat::from_content_type(content_type).ok_or_else(|| {
        let accepted: Vec<&str> = FrameFormat::ALL.iter().map(|f| f.content_type()).collect();
        ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            ErrorCode::UnsupportedMediaType,
            format!(
                "a frame is sent as {}, not `{content_type}`",
                accepted.join(", ")
            ),
        )
    })?;
    let camera = q.camera.ok_or_else(|| {
        ApiError::invalid_field("camera", "the query names no camera (`?camera=C1`)")
    })?;
    let q_camera = camera.clone();
    let size = app
        .service
        .observer()
        .camera(&camera)
        .map(|c| (c.width_px, c.height_px))
        .map_err(|e| ApiError::invalid_field(e.field, e.message))?;
    let text = q.time.ok_or_else(|| {
        ApiError::invalid_field("time", "the query gives no measurement time (`&time=...`)")
    })?;
    let latest = crate::clock::latest_accepted_ns(
        app.service.now_ns(),
        app.service.installation().server.max_future_s,
    );
    let time_ns = crate::clock::parse_query_time(&text)
        .and_then(|t| crate::clock::accepted_time(t, latest))
        .map_err(|m| ApiError::invalid_field("time", m))?;
    let bytes = read_body(body, &headers, app.limits.max_body_bytes).await?;
    // At most a frame a core in decoding and search; the rest wait a little, then 503.
    let slot = super::take_slot(&app.decode_slots, DECODE_WAIT, "decoding frames").await?;
    let image = super::vision::blocking(move || {
        decode(&bytes, format, Some(size)).map_err(|e| {
            ApiError::invalid_field(
                "body",
                match e {
                    FrameFileError::WrongSize {
                        width_px,
                        height_px,
                        ..
                    } => format!(
                        "the frame is {width_px} x {height_px} px but camera {camera} is {} x {} px",
                        size.0, size.1
                    ),
                    other => other.to_string(),
                },
            )
        })
    })
    .await??;
    take_frame(&app, &q_camera, time_ns, image, slot)
        .await
        .map(Json)
}

/// A decoded frame of `camera` taken the way `POST /frames` takes it: its markers searched
/// and solved (on the blocking pool, holding `slot`), the found ones ingested, the frame
/// offered to the archive, Rerun and the newest-frame slot. A camera source's frames come
/// here too ([`super::sources`]).
pub(super) async fn take_frame(
    app: &AppState,
    camera: &str,
    time_ns: i64,
    image: crate::vision::GreyImage,
    slot: tokio::sync::OwnedSemaphorePermit,
) -> Result<FrameOut, ApiError> {
    let observer = app.service.observer();
    let snapshot = app.service.snapshot();
    let camera_name = camera.to_owned();
    // Which lost markers may be searched for in the whole frame, decided before the search
    // and recorded after it (two frames searched at once may both search: at most a core
    // each, as ever).
    let allowed: Vec<(crate::chain::LinkId, Result<(), f64>)> = {
        let pacer = app.search_pacer.lock().unwrap_or_else(|p| p.into_inner());
        observer
            .links()
            .filter(|l| l.camera_frame == camera)
            .map(|l| (l.link, pacer.whole_frame(l.link, time_ns)))
            .collect()
    };
    let pace = allowed.clone();
    let (out, items, image, found) = super::vision::blocking(move || {
        // The link's filtered pose at the frame's time (the nominal one follows by itself).
        let predictions = |link: &ObservedLink| -> Vec<Pose> {
            match snapshot.bank.link_estimate(link.link, time_ns) {
                Ok(Some(p)) => vec![p.pose],
                _ => Vec::new(),
            }
        };
        let whole_frame = |link: &ObservedLink| {
            pace.iter()
                .find(|(l, _)| *l == link.link)
                .map_or(Ok(()), |(_, allowed)| *allowed)
        };
        let seen = observe_frame_paced(&observer, &camera_name, &image, predictions, whole_frame)
            .map_err(|e| ApiError::invalid_field(e.field, e.message))?;
        let found: Vec<(crate::chain::LinkId, bool)> = seen
            .markers
            .iter()
            .map(|m| (m.link.link, m.result.is_ok()))
            .collect();
        let (out, items) = answer(&camera_name, time_ns, &seen);
        drop(slot);
        Ok::<_, ApiError>((out, items, image, found))
    })
    .await??;
    {
        let mut pacer = app.search_pacer.lock().unwrap_or_else(|p| p.into_inner());
        for (link, found) in found {
            let searched = allowed
                .iter()
                .any(|(l, allowed)| *l == link && allowed.is_ok());
            pacer.record(link, time_ns, found, searched);
        }
    }
    let ingest = if items.is_empty() {
        IngestResponse::default()
    } else {
        app.service.ingest(items).await?.into()
    };
    let out = FrameOut { ingest, ..out };
    let image = std::sync::Arc::new(image);
    if let Some(archive) = &app.archive {
        archive.offer(camera, time_ns, &image, evidence(&out));
    }
    if let Some(index) = app
        .service
        .installation()
        .model
        .cameras
        .iter()
        .position(|c| c.frame == camera)
    {
        app.service.frame_viz().offer(index, time_ns, &image, || {
            out.markers.iter().map(marks).collect()
        });
    }
    app.latest_frames.offer(camera, time_ns, image, out.clone());
    Ok(out)
}

/// What Rerun draws over a frame for one marker.
fn marks(m: &FrameMarkerOut) -> crate::viz::FrameMarks {
    crate::viz::FrameMarks {
        marker: m.marker.clone(),
        points_px: m.points_px.clone().unwrap_or_default(),
        ids: m.ids.clone().unwrap_or_default(),
        reprojected_px: m.reprojected_px.clone().unwrap_or_default(),
        not_found: (!m.found).then(|| m.reason.clone().unwrap_or_default()),
    }
}

/// Why a frame is evidence worth archiving: a marker with disc targets not found, or a sample
/// judged an outlier.
fn evidence(out: &FrameOut) -> Option<ArchiveReason> {
    if out
        .markers
        .iter()
        .any(|m| !m.found && m.reason_code != Some(NotFoundCode::NoTarget))
    {
        Some(ArchiveReason::NotFound)
    } else if out.ingest.outliers > 0 {
        Some(ArchiveReason::Outlier)
    } else {
        None
    }
}

/// The answer before ingest, and the samples to ingest.
fn answer(camera: &str, time_ns: i64, seen: &FrameObservation<'_>) -> (FrameOut, Vec<IngestItem>) {
    let mut items = Vec::new();
    let markers = seen
        .markers
        .iter()
        .map(|m| {
            let mut out = FrameMarkerOut {
                marker: m.link.marker_frame.clone(),
                link: m.link.name.clone(),
                found: false,
                points_px: None,
                ids: None,
                sigma_px: None,
                pose: None,
                sigma: None,
                reprojected_px: None,
                reprojection_rms_px: None,
                rejected_points: None,
                reason: None,
                reason_code: None,
            };
            match &m.result {
                Ok(found) => {
                    let s = &found.solution;
                    let cov = PoseCov {
                        pose: s.camera_from_marker,
                        cov: s.covariance,
                    };
                    items.push(super::vision::solved_item(
                        items.len(),
                        m.link.link,
                        time_ns,
                        s,
                    ));
                    out.found = true;
                    out.points_px = Some(found.points_px.clone());
                    out.ids = Some(found.ids.clone());
                    out.sigma_px = Some(found.sigma_px.clone());
                    out.pose = Some(PoseOut::from(&s.camera_from_marker));
                    out.sigma = Some(SigmaOut::from(&cov));
                    out.reprojected_px = Some(found.reprojected_px.clone());
                    out.reprojection_rms_px = Some(s.rms_px);
                    out.rejected_points = Some(s.rejected_points.clone());
                }
                Err(why) => {
                    out.reason = Some(why.to_string());
                    out.reason_code = Some(NotFoundCode::from(why));
                }
            }
            out
        })
        .collect();
    (
        FrameOut {
            camera: camera.to_owned(),
            time: format_ns(time_ns),
            blobs: seen.blobs,
            searched_fraction: seen.searched_fraction,
            markers,
            ingest: IngestResponse::default(),
        },
        items,
    )
}
