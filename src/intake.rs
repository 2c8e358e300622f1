//! A camera frame's way in, whoever brings it (`POST /frames`, or a camera the service takes
//! frames from itself, [`crate::acquire`]): the markers the camera sees searched and solved off
//! the async workers, the found ones ingested as link samples (durable before the answer), the
//! frame offered to the archive, to Rerun and to the newest-frame slot of its camera. The
//! answer is a domain value, [`TakenFrame`]; the HTTP layer shapes it, the rest is fed from it.
//!
//! Memory is bounded by the installation and the host: frames are searched in one slot a core
//! ([`Intake::decode_slot`]), and one newest frame is kept per configured camera, with its PNG
//! encoded once, on the first request for it.

use crate::acquire::SourceState;
use crate::archive::{ArchiveError, ArchiveReason, FrameArchive};
use crate::chain::LinkId;
use crate::geometry::Pose;
use crate::model::{Found, NotFound, ObservedLink, SearchPacer, observe_frame_paced};
use crate::service::{IngestItem, IngestReport, Service, ServiceError};
use crate::vision::GreyImage;
use std::sync::{Arc, Mutex, OnceLock};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// Why a frame was not taken.
#[derive(Debug, thiserror::Error)]
pub enum IntakeError {
    /// The frame does not fit its camera (unknown camera, wrong size), naming the field.
    #[error("{message}")]
    Refused {
        /// The request's field at fault (`camera`, `body`).
        field: &'static str,
        /// What is wrong.
        message: String,
    },
    /// Every slot for searching frames stayed taken.
    #[error("every slot for decoding frames is taken; retry shortly")]
    Busy,
    /// The search stopped on a defect (a panic), reported, never hidden.
    #[error("the frame's search failed: {0}")]
    Failed(String),
    /// Ingesting the found markers' samples failed.
    #[error(transparent)]
    Ingest(#[from] ServiceError),
}

/// What a frame showed of one marker a camera sees through a measured link.
#[derive(Debug, Clone)]
pub struct MarkerTaken {
    /// The measured link's id.
    pub link_id: LinkId,
    /// The marker's frame.
    pub marker: String,
    /// The measured link `<camera>_from_<marker>`.
    pub link: String,
    /// Its points and pose, or why it was not found.
    pub result: Result<Found, NotFound>,
}

/// A frame taken: what was found in it and what ingesting the found markers did.
#[derive(Debug, Clone)]
pub struct TakenFrame {
    /// The camera's frame.
    pub camera: String,
    /// The frame's measurement time (ns).
    pub time_ns: i64,
    /// Discs detected in the searched part of the frame.
    pub blobs: usize,
    /// The share of the frame searched, summed over the polarities searched.
    pub searched_fraction: f64,
    /// Each marker of a measured link of the camera, in installation order.
    pub markers: Vec<MarkerTaken>,
    /// What ingesting the found markers' samples did.
    pub ingest: IngestReport,
}

impl TakenFrame {
    /// Why the frame is evidence worth archiving: a marker with disc targets not found, or a
    /// sample judged an outlier.
    pub fn evidence(&self) -> Option<ArchiveReason> {
        if self
            .markers
            .iter()
            .any(|m| matches!(&m.result, Err(why) if *why != NotFound::NoTarget))
        {
            Some(ArchiveReason::NotFound)
        } else if self.ingest.outliers > 0 {
            Some(ArchiveReason::Outlier)
        } else {
            None
        }
    }

    /// What Rerun draws over the frame, a marker each.
    fn marks(&self) -> Vec<crate::viz::FrameMarks> {
        self.markers
            .iter()
            .map(|m| {
                let found = m.result.as_ref().ok();
                crate::viz::FrameMarks {
                    marker: m.marker.clone(),
                    points_px: found.map(|f| f.points_px.clone()).unwrap_or_default(),
                    ids: found.map(|f| f.ids.clone()).unwrap_or_default(),
                    reprojected_px: found.map(|f| f.reprojected_px.clone()).unwrap_or_default(),
                    not_found: m.result.as_ref().err().map(ToString::to_string),
                }
            })
            .collect()
    }
}

/// The sample a solved observation gives its link, with the fit's quality: what a frame's
/// found markers and `POST /observations` ingest.
pub fn solved_item(
    index: usize,
    link: LinkId,
    time_ns: i64,
    solution: &crate::vision::PnpSolution,
) -> IngestItem {
    IngestItem {
        index,
        sample: crate::bank::Sample {
            link,
            time_ns,
            parent_from_child: solution.camera_from_marker,
            uncertainty: crate::bank::MeasurementUncertainty::Covariance(solution.covariance),
        },
        quality: crate::store::Quality {
            reprojection_rms_px: Some(solution.rms_px),
            points: u32::try_from(solution.points).ok(),
        },
    }
}

/// A camera's newest frame, with what was found in it.
#[derive(Debug)]
pub struct LatestFrame {
    /// What was found and ingested.
    pub frame: Arc<TakenFrame>,
    /// The decoded frame.
    pub image: Arc<GreyImage>,
    /// The frame as PNG, encoded on the first request for it.
    png: OnceLock<Result<bytes::Bytes, String>>,
}

impl LatestFrame {
    /// The frame as PNG (8 or 16 bit grey, as it came), encoded once: CPU work, to be called
    /// off the async workers.
    pub fn png(&self) -> Result<bytes::Bytes, String> {
        self.png
            .get_or_init(|| {
                crate::imagefile::encode_png_fast(&self.image)
                    .map(bytes::Bytes::from)
                    .map_err(|e| e.to_string())
            })
            .clone()
    }
}

/// Takes frames: the search's slots and pace, the archive, the newest frame of every camera.
pub struct Intake {
    service: Service,
    archive: Option<FrameArchive>,
    /// One slot per configured camera, by its frame's name.
    latest: Vec<(String, Mutex<Option<Arc<LatestFrame>>>)>,
    /// The pace of whole-frame searches for lost markers (`[pnp] lost_search_interval_s`).
    pacer: Mutex<SearchPacer>,
    /// Frames decoded and searched at once: one a core (each takes memory up to its camera's
    /// decode budget).
    decode_slots: Arc<Semaphore>,
}

impl std::fmt::Debug for Intake {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Intake")
            .field("cameras", &self.latest.len())
            .field("archive", &self.archive.is_some())
            .finish_non_exhaustive()
    }
}

impl Intake {
    /// The intake of `service`'s installation; opens the frame archive when one is configured.
    pub fn new(service: Service) -> Result<Self, ArchiveError> {
        let inst = service.installation();
        let archive = FrameArchive::open(&inst.frames)?;
        let latest = (inst.model.cameras.iter())
            .map(|c| (c.frame.clone(), Mutex::new(None)))
            .collect();
        let pacer = SearchPacer::new(
            inst.model.links.len(),
            (inst.model.pnp.lost_search_interval_s * 1e9).round() as i64,
        );
        let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
        Ok(Self {
            archive,
            latest,
            pacer: Mutex::new(pacer),
            decode_slots: Arc::new(Semaphore::new(cores)),
            service,
        })
    }

    /// The frame archive, when one is configured.
    pub fn archive(&self) -> Option<&FrameArchive> {
        self.archive.as_ref()
    }

    /// The newest frame of `camera`, if it sent one.
    pub fn latest(&self, camera: &str) -> Option<Arc<LatestFrame>> {
        self.slot(camera)
            .and_then(|s| s.lock().unwrap_or_else(|p| p.into_inner()).clone())
    }

    fn slot(&self, camera: &str) -> Option<&Mutex<Option<Arc<LatestFrame>>>> {
        self.latest
            .iter()
            .find(|(c, _)| c == camera)
            .map(|(_, s)| s)
    }

    /// Waits up to `wait` for a slot to decode and search a frame in ([`IntakeError::Busy`]
    /// otherwise): at most a frame a core.
    pub async fn decode_slot(
        &self,
        wait: std::time::Duration,
    ) -> Result<OwnedSemaphorePermit, IntakeError> {
        match tokio::time::timeout(wait, Arc::clone(&self.decode_slots).acquire_owned()).await {
            Ok(Ok(permit)) => Ok(permit),
            _ => Err(IntakeError::Busy),
        }
    }

    /// Takes a decoded frame of `camera`: its markers searched and solved on the blocking
    /// pool (holding `slot` meanwhile), the found ones ingested, the frame offered to the
    /// archive, Rerun and the newest-frame slot.
    pub async fn take(
        &self,
        camera: &str,
        time_ns: i64,
        image: GreyImage,
        slot: OwnedSemaphorePermit,
    ) -> Result<Arc<TakenFrame>, IntakeError> {
        let observer = self.service.observer();
        let snapshot = self.service.snapshot();
        // Which lost markers may be searched for in the whole frame, decided before the search
        // and recorded after it (two frames searched at once may both search: at most a core
        // each, as ever).
        let allowed: Vec<(LinkId, Result<(), f64>)> = {
            let pacer = self.pacer.lock().unwrap_or_else(|p| p.into_inner());
            observer
                .links()
                .filter(|l| l.camera_frame == camera)
                .map(|l| (l.link, pacer.whole_frame(l.link, time_ns)))
                .collect()
        };
        let pace = allowed.clone();
        let camera_name = camera.to_owned();
        let searched = tokio::task::spawn_blocking(move || {
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
            let seen =
                observe_frame_paced(&observer, &camera_name, &image, predictions, whole_frame)
                    .map_err(|e| IntakeError::Refused {
                        field: e.field,
                        message: e.message,
                    })?;
            drop(slot);
            let mut items = Vec::new();
            for m in &seen.markers {
                if let Ok(found) = &m.result {
                    items.push(solved_item(
                        items.len(),
                        m.link.link,
                        time_ns,
                        &found.solution,
                    ));
                }
            }
            let frame = TakenFrame {
                camera: camera_name,
                time_ns,
                blobs: seen.blobs,
                searched_fraction: seen.searched_fraction,
                markers: (seen.markers.into_iter())
                    .map(|m| MarkerTaken {
                        link_id: m.link.link,
                        marker: m.link.marker_frame.clone(),
                        link: m.link.name.clone(),
                        result: m.result,
                    })
                    .collect(),
                ingest: IngestReport::default(),
            };
            Ok::<_, IntakeError>((frame, items, image))
        })
        .await
        .map_err(|e| IntakeError::Failed(e.to_string()))??;
        let (mut frame, items, image) = searched;
        {
            let mut pacer = self.pacer.lock().unwrap_or_else(|p| p.into_inner());
            for m in &frame.markers {
                let searched = allowed
                    .iter()
                    .any(|(l, allowed)| *l == m.link_id && allowed.is_ok());
                pacer.record(m.link_id, time_ns, m.result.is_ok(), searched);
            }
        }
        if !items.is_empty() {
            frame.ingest = self.service.ingest(items).await?;
        }
        let frame = Arc::new(frame);
        let image = Arc::new(image);
        if let Some(archive) = &self.archive {
            archive.offer(camera, time_ns, &image, frame.evidence());
        }
        let cameras = &self.service.installation().model.cameras;
        if let Some(index) = cameras.iter().position(|c| c.frame == camera) {
            self.service
                .frame_viz()
                .offer(index, time_ns, &image, || frame.marks());
        }
        self.offer_latest(Arc::clone(&frame), image);
        Ok(frame)
    }

    /// Keeps a frame when it is its camera's newest by measurement time (a late frame does not
    /// hide a newer one).
    fn offer_latest(&self, frame: Arc<TakenFrame>, image: Arc<GreyImage>) {
        let Some(slot) = self.slot(&frame.camera) else {
            return;
        };
        let mut held = slot.lock().unwrap_or_else(|p| p.into_inner());
        if held
            .as_ref()
            .is_some_and(|l| l.frame.time_ns > frame.time_ns)
        {
            return;
        }
        *held = Some(Arc::new(LatestFrame {
            frame,
            image,
            png: OnceLock::new(),
        }));
    }

    /// Starts a task per camera source taking its frames in turn; each ends when its source is
    /// closed. A frame whose time is not accepted, that finds no slot within five seconds, or
    /// that ingest refuses is counted failed in its source's state, with why.
    pub fn spawn_sources(
        self: &Arc<Self>,
        sources: &[Arc<SourceState>],
    ) -> Vec<tokio::task::JoinHandle<()>> {
        sources
            .iter()
            .map(|state| {
                let intake = Arc::clone(self);
                let state = Arc::clone(state);
                tokio::spawn(async move { intake.take_source(&state).await })
            })
            .collect()
    }

    async fn take_source(&self, state: &SourceState) {
        /// How long a source's frame waits for a slot before it is dropped (counted failed).
        const SLOT_WAIT: std::time::Duration = std::time::Duration::from_secs(5);
        let camera = state.source.camera.clone();
        let max_future_s = self.service.installation().server.max_future_s;
        while let Some(frame) = state.next().await {
            let now = self.service.now_ns();
            let latest = crate::clock::latest_accepted_ns(now, max_future_s);
            if let Err(m) = crate::clock::accepted_time(frame.time_ns, latest) {
                state.failed(format!("its time is not accepted: {m}"), now);
                continue;
            }
            let taken = match self.decode_slot(SLOT_WAIT).await {
                Ok(slot) => self.take(&camera, frame.time_ns, frame.image, slot).await,
                Err(e) => Err(e),
            };
            match taken {
                Ok(_) => state.ingested((crate::clock::wall_now_ns() - frame.time_ns) as f64 / 1e9),
                Err(e) => state.failed(e.to_string(), self.service.now_ns()),
            }
        }
    }
}
