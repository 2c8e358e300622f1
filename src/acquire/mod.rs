//! Frames taken from the cameras themselves: GigE Vision and USB3 Vision through libaravis
//! (the `genicam` feature), one thread a camera, each opening its camera by address (never
//! finding it by a broadcast), configuring it from `[cameras.source]`, settling each frame's
//! time ([`timing`]) and handing it on through a short queue that drops its oldest frame when
//! full ([`state`]). A camera that goes away is opened again with back-off; what each source is
//! doing is in its [`SourceState`].
//!
//! `serve` takes the frames into the same path as `POST /frames` (detection, identification,
//! ingest, the newest frame, the archive, Rerun); `brokenray acquire --to URL` posts them to a
//! service elsewhere.

pub mod state;
pub mod timing;

#[cfg(feature = "genicam")]
mod genicam;

pub use state::{AcquiredFrame, SourceReport, SourceState, SourceStatus};

use crate::config::Installation;
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

/// Whether this build takes frames from cameras (the `genicam` feature).
pub const SUPPORTED: bool = cfg!(feature = "genicam");

/// The trigger groups' recent instants, shared by their cameras' threads.
pub type TriggerGroups = Arc<Mutex<HashMap<String, timing::TriggerInstants>>>;

/// The running sources of an installation.
#[derive(Debug)]
pub struct Acquisition {
    sources: Vec<Arc<SourceState>>,
    stop: Arc<AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl Acquisition {
    /// Starts a thread for every camera that has a source. Without the `genicam` feature no
    /// thread starts and every source says `unsupported`.
    pub fn start(installation: &Installation) -> Acquisition {
        let stop = Arc::new(AtomicBool::new(false));
        let groups = TriggerGroups::default();
        let mut sources = Vec::new();
        #[cfg_attr(not(feature = "genicam"), allow(unused_mut))]
        let mut threads = Vec::new();
        for source in &installation.sources {
            let state = Arc::new(SourceState::new(source.clone()));
            let size = installation
                .model
                .camera(&source.camera)
                .map(|c| (c.intrinsics.width_px, c.intrinsics.height_px));
            #[cfg(feature = "genicam")]
            if let Some(size) = size {
                match genicam::spawn(
                    Arc::clone(&state),
                    size,
                    Arc::clone(&groups),
                    Arc::clone(&stop),
                ) {
                    Ok(thread) => threads.push(thread),
                    Err(e) => state.error(
                        SourceStatus::Stopped,
                        format!("cannot start the acquisition thread: {e}"),
                        crate::clock::wall_now_ns(),
                    ),
                }
            }
            #[cfg(not(feature = "genicam"))]
            {
                let _ = (size, &groups);
                state.error(
                    SourceStatus::Unsupported,
                    "this build takes no frames from cameras: build with `--features genicam` (libaravis 0.8)".into(),
                    crate::clock::wall_now_ns(),
                );
            }
            sources.push(state);
        }
        Acquisition {
            sources,
            stop,
            threads,
        }
    }

    /// Every source, in installation order.
    pub fn sources(&self) -> &[Arc<SourceState>] {
        &self.sources
    }

    /// The source of a camera.
    pub fn source(&self, camera: &str) -> Option<&Arc<SourceState>> {
        self.sources.iter().find(|s| s.source.camera == camera)
    }

    /// Stops every thread (each stops its camera's acquisition) and closes the queues.
    pub fn stop(&mut self) {
        self.stop.store(true, Ordering::Release);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
        for s in &self.sources {
            s.close();
        }
    }
}

impl Drop for Acquisition {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Opens each source's camera and applies its settings, without acquiring: what
/// `check-config --cameras` reports. One line per camera: its device, or the error naming the
/// key. Without the `genicam` feature, says so.
pub fn probe(installation: &Installation) -> Vec<(String, Result<String, String>)> {
    installation
        .sources
        .iter()
        .map(|source| {
            let size = installation
                .model
                .camera(&source.camera)
                .map_or((0, 0), |c| (c.intrinsics.width_px, c.intrinsics.height_px));
            #[cfg(feature = "genicam")]
            let result = genicam::probe(source, size);
            #[cfg(not(feature = "genicam"))]
            let result = {
                let _ = size;
                Err(
                    "this build takes no frames from cameras: build with `--features genicam`"
                        .to_owned(),
                )
            };
            (source.camera.clone(), result)
        })
        .collect()
}
