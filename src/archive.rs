//! The archive of camera frames (`[frames] archive_dir`): evidence of what each camera saw.
//!
//! Kept: one frame per camera every `archive_every_s` of measurement time, and every frame in
//! which a marker was not found or a link's sample was judged an outlier. Each is a lossless
//! PNG named by its camera and measurement time, `DIR/<camera>/<time>_<reason>.png` with the
//! time at full width (`2026-11-21T10:00:00.040000000Z`, so names sort in time order) and the
//! reason `periodic`, `not_found` or `outlier`.
//!
//! The size cap holds: before a frame is written the oldest frames (of any camera) are removed
//! until it fits, so the archive never exceeds `archive_max_mb` (unless one frame alone does).
//! Files are written under a temporary name and linked into place, so a crash leaves no half
//! frame and an archived frame is never replaced (a second frame of the camera at the same time
//! is not archived, and counted); the
//! archive is read back at start (the cap counts what earlier runs kept), and temporary files
//! left by a crash are removed then.
//!
//! Writing never slows `POST /frames`: frames are handed to one writer thread through a short
//! queue; when the queue is full the frame is not archived, and that is counted
//! ([`ArchiveCounters`], in `/metrics`) and logged, as are write failures (a full disk, a
//! directory that went away).

use crate::clock::{format_ns_fixed, parse_rfc3339_ns};
use crate::config::FrameSettings;
use crate::imagefile::encode_png_fast;
use crate::vision::GreyImage;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError, sync_channel};
use std::sync::{Arc, Mutex};

/// Frames waiting for the writer; more are not archived (and counted).
const QUEUE: usize = 16;

crate::words! {
    /// Why a frame was kept.
    #[derive(PartialOrd, Ord)]
    pub enum ArchiveReason("archive reason") {
        /// The camera's frame of its period.
        Periodic = "periodic",
        /// A marker of the camera was not found.
        NotFound = "not_found",
        /// A sample from the frame was judged an outlier.
        Outlier = "outlier",
    }
}

/// One archived frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ArchivedFrame {
    /// The camera.
    pub camera: String,
    /// Measurement time (ns).
    pub time_ns: i64,
    /// Why it was kept.
    pub reason: ArchiveReason,
    /// Its size on disk (bytes).
    pub bytes: u64,
    /// Its path.
    pub path: PathBuf,
}

/// What the archive did since the service started.
#[derive(Debug, Default)]
pub struct ArchiveCounters {
    /// Frames written.
    pub written: AtomicU64,
    /// Frames removed to stay under the cap.
    pub removed: AtomicU64,
    /// Frames not archived because the writer was behind.
    pub dropped: AtomicU64,
    /// Frames whose writing failed.
    pub failed: AtomicU64,
    /// Frames not archived because one of the camera at the same time is archived already
    /// (the first stays: evidence is never replaced).
    pub kept_first: AtomicU64,
}

/// What is on disk: every archived frame by (time, camera), and their total size.
#[derive(Debug, Default)]
struct Index {
    files: BTreeMap<(i64, String), ArchivedFrame>,
    bytes: u64,
    /// Per camera, the measurement time of the last periodic frame handed to the writer.
    last_periodic_ns: HashMap<String, i64>,
}

struct Job {
    camera: String,
    time_ns: i64,
    reason: ArchiveReason,
    image: Arc<GreyImage>,
}

/// The archive; cheap to clone (one writer thread behind every clone).
#[derive(Clone)]
pub struct FrameArchive {
    dir: PathBuf,
    every_ns: i64,
    max_bytes: u64,
    index: Arc<Mutex<Index>>,
    counters: Arc<ArchiveCounters>,
    queue: SyncSender<Job>,
}

/// Errors of opening the archive.
#[derive(Debug, thiserror::Error)]
#[error("the frame archive at {dir} cannot be used: {source}")]
pub struct ArchiveError {
    dir: PathBuf,
    source: std::io::Error,
}

impl FrameArchive {
    /// Opens (creating it if needed) the archive `settings` names, reads back what is in it
    /// and starts its writer; `None` when no archive is configured.
    pub fn open(settings: &FrameSettings) -> Result<Option<Self>, ArchiveError> {
        let Some(dir) = settings.archive_dir.clone() else {
            return Ok(None);
        };
        let err = |source| ArchiveError {
            dir: dir.clone(),
            source,
        };
        std::fs::create_dir_all(&dir).map_err(err)?;
        let index = Arc::new(Mutex::new(read_back(&dir).map_err(err)?));
        let (queue, jobs) = sync_channel(QUEUE);
        let archive = Self {
            every_ns: (settings.archive_every_s * 1e9).round() as i64,
            max_bytes: (settings.archive_max_mb * 1e6) as u64,
            dir: dir.clone(),
            index,
            counters: Arc::new(ArchiveCounters::default()),
            queue,
        };
        let writer = archive.clone_for_writer();
        std::thread::Builder::new()
            .name("frame-archive".into())
            .spawn(move || writer.run(jobs))
            .map_err(err)?;
        Ok(Some(archive))
    }

    /// The writer's view: the same index and counters, without a sender (so the thread ends
    /// when the last clone of the archive is dropped).
    fn clone_for_writer(&self) -> Writer {
        Writer {
            dir: self.dir.clone(),
            max_bytes: self.max_bytes,
            index: Arc::clone(&self.index),
            counters: Arc::clone(&self.counters),
        }
    }

    /// What the archive did.
    pub fn counters(&self) -> &ArchiveCounters {
        &self.counters
    }

    /// The archive's size on disk now (bytes).
    pub fn bytes(&self) -> u64 {
        self.lock().bytes
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Index> {
        self.index.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Hands a frame over when it is to be kept: as evidence (`evidence` given), or as its
    /// camera's periodic frame. Never waits: when the writer is behind, the frame is counted
    /// as dropped. Returns why it was kept, if it was handed over.
    pub fn offer(
        &self,
        camera: &str,
        time_ns: i64,
        image: &Arc<GreyImage>,
        evidence: Option<ArchiveReason>,
    ) -> Option<ArchiveReason> {
        let mut index = self.lock();
        let periodic_due = index
            .last_periodic_ns
            .get(camera)
            // Due a period after the last one, or when time went back by more than a period.
            .is_none_or(|last| time_ns >= last + self.every_ns || time_ns < last - self.every_ns);
        let reason = evidence.or(periodic_due.then_some(ArchiveReason::Periodic))?;
        let job = Job {
            camera: camera.to_owned(),
            time_ns,
            reason,
            image: Arc::clone(image),
        };
        match self.queue.try_send(job) {
            Ok(()) => {
                if periodic_due {
                    // Evidence counts as the period's frame too.
                    index.last_periodic_ns.insert(camera.to_owned(), time_ns);
                }
                Some(reason)
            }
            Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => {
                let dropped = self.counters.dropped.fetch_add(1, Relaxed) + 1;
                if dropped.is_power_of_two() {
                    tracing::warn!(
                        camera,
                        dropped,
                        "the frame archive's writer is behind: frames are not being archived"
                    );
                }
                None
            }
        }
    }

    /// The archived frames of `camera` with measurement times in `[from_ns, to_ns]`, oldest
    /// first, at most `limit`.
    pub fn list(&self, camera: &str, from_ns: i64, to_ns: i64, limit: usize) -> Vec<ArchivedFrame> {
        self.lock()
            .files
            .range((from_ns, String::new())..)
            .take_while(|((t, _), _)| *t <= to_ns)
            .filter(|((_, c), _)| c == camera)
            .take(limit)
            .map(|(_, f)| f.clone())
            .collect()
    }

    /// The archived frame of `camera` at exactly `time_ns`.
    pub fn get(&self, camera: &str, time_ns: i64) -> Option<ArchivedFrame> {
        self.lock()
            .files
            .get(&(time_ns, camera.to_owned()))
            .cloned()
    }
}

/// The writer thread's side.
struct Writer {
    dir: PathBuf,
    max_bytes: u64,
    index: Arc<Mutex<Index>>,
    counters: Arc<ArchiveCounters>,
}

impl Writer {
    fn run(self, jobs: Receiver<Job>) {
        while let Ok(job) = jobs.recv() {
            if let Err(e) = self.write(&job) {
                self.counters.failed.fetch_add(1, Relaxed);
                tracing::error!(
                    camera = %job.camera,
                    time = %crate::clock::format_ns(job.time_ns),
                    error = %e,
                    "a frame could not be archived"
                );
            }
        }
    }

    fn write(&self, job: &Job) -> std::io::Result<()> {
        let png = encode_png_fast(&job.image).map_err(std::io::Error::other)?;
        let size = png.len() as u64;
        let camera_dir = self.dir.join(&job.camera);
        std::fs::create_dir_all(&camera_dir)?;
        let name = file_name(job.time_ns, job.reason);
        let path = camera_dir.join(&name);
        let key = (job.time_ns, job.camera.clone());
        // Room first: the oldest frames go until this one fits under the cap. The index is
        // only locked to choose them (offers from requests take the same lock), not while
        // files are removed or written.
        let mut doomed = Vec::new();
        {
            let mut index = self.index.lock().unwrap_or_else(|p| p.into_inner());
            if index.files.contains_key(&key) {
                // The same camera and time again: the archived frame is evidence and stays.
                self.counters.kept_first.fetch_add(1, Relaxed);
                return Ok(());
            }
            while index.bytes + size > self.max_bytes {
                let Some((_, oldest)) = index.files.pop_first() else {
                    break;
                };
                index.bytes -= oldest.bytes;
                doomed.push(oldest.path);
                self.counters.removed.fetch_add(1, Relaxed);
            }
        }
        for old in doomed {
            match std::fs::remove_file(&old) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => {
                    tracing::warn!(path = %old.display(), error = %e, "an archived frame could not be removed");
                }
            }
        }
        let temporary = camera_dir.join(format!(".{name}.tmp"));
        std::fs::write(&temporary, &png)?;
        // A link, not a rename: it fails rather than replace a frame already there (one of an
        // earlier run, not in the index).
        let linked = std::fs::hard_link(&temporary, &path);
        let _ = std::fs::remove_file(&temporary);
        match linked {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                self.counters.kept_first.fetch_add(1, Relaxed);
                return Ok(());
            }
            Err(e) => return Err(e),
        }
        let mut index = self.index.lock().unwrap_or_else(|p| p.into_inner());
        index.bytes += size;
        index.files.insert(
            key,
            ArchivedFrame {
                camera: job.camera.clone(),
                time_ns: job.time_ns,
                reason: job.reason,
                bytes: size,
                path,
            },
        );
        self.counters.written.fetch_add(1, Relaxed);
        Ok(())
    }
}

/// The archived frames under `dir` with measurement times in `[from_ns, to_ns]`, in time order
/// (for readers such as `replay`; nothing is removed or written).
pub fn archived_in(dir: &Path, from_ns: i64, to_ns: i64) -> std::io::Result<Vec<ArchivedFrame>> {
    let mut files: Vec<ArchivedFrame> = walk(dir, false)?
        .into_iter()
        .filter(|f| (from_ns..=to_ns).contains(&f.time_ns))
        .collect();
    files.sort_by(|a, b| (a.time_ns, &a.camera).cmp(&(b.time_ns, &b.camera)));
    Ok(files)
}

/// `<time>_<reason>.png`.
fn file_name(time_ns: i64, reason: ArchiveReason) -> String {
    format!("{}_{}.png", format_ns_fixed(time_ns), reason.name())
}

/// The time and reason of an archive file's name.
fn parse_name(name: &str) -> Option<(i64, ArchiveReason)> {
    let stem = name.strip_suffix(".png")?;
    let (time, reason) = stem.split_once('_')?;
    let reason = ArchiveReason::parse(reason)?;
    Some((parse_rfc3339_ns(time).ok()?, reason))
}

/// Every archived frame under `dir` (other files are left alone and not counted); temporary
/// files of interrupted writes are removed.
fn read_back(dir: &Path) -> std::io::Result<Index> {
    let mut index = Index::default();
    for frame in walk(dir, true)? {
        index.bytes += frame.bytes;
        index
            .files
            .insert((frame.time_ns, frame.camera.clone()), frame);
    }
    Ok(index)
}

/// The frames named as the archive names them under `dir/<camera>/`; with `clean`, temporary
/// files of interrupted writes are removed on the way.
fn walk(dir: &Path, clean: bool) -> std::io::Result<Vec<ArchivedFrame>> {
    let mut out = Vec::new();
    for camera in std::fs::read_dir(dir)? {
        let camera = camera?;
        if !camera.file_type()?.is_dir() {
            continue;
        }
        let Some(camera_name) = camera.file_name().to_str().map(str::to_owned) else {
            continue;
        };
        for file in std::fs::read_dir(camera.path())? {
            let file = file?;
            let name = file.file_name();
            let Some(name) = name.to_str() else {
                continue;
            };
            if clean && name.starts_with('.') && name.ends_with(".tmp") {
                let _ = std::fs::remove_file(file.path());
                continue;
            }
            let Some((time_ns, reason)) = parse_name(name) else {
                continue;
            };
            out.push(ArchivedFrame {
                camera: camera_name.clone(),
                time_ns,
                reason,
                bytes: file.metadata()?.len(),
                path: file.path(),
            });
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_carry_the_time_and_reason_and_parse_back() {
        let t = 1_795_255_200_040_000_000;
        for &reason in ArchiveReason::ALL {
            let name = file_name(t, reason);
            assert_eq!(parse_name(&name), Some((t, reason)), "{name}");
        }
        assert_eq!(
            file_name(t, ArchiveReason::NotFound),
            "2026-11-21T10:00:00.040000000Z_not_found.png"
        );
        assert_eq!(parse_name("notes.txt"), None);
        assert_eq!(parse_name("2026-11-21T10:00:00Z_other.png"), None);
    }
}
