//! The frame archive on a real directory: the periodic and evidence frames kept under names a
//! person can read, the size cap never exceeded with the oldest frames removed first, and what
//! an earlier run kept counted again after a restart (its interrupted writes removed).

use brokenray::archive::{ArchiveReason, FrameArchive};
use brokenray::config::FrameSettings;
use brokenray::imagefile::{FrameFormat, decode};
use brokenray::vision::GreyImage;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

const T0: i64 = 1_795_255_200_000_000_000;

/// A 64 x 64 frame of noise (it compresses little, so each file has about the same size).
fn noise(seed: u64) -> Arc<GreyImage> {
    let mut state = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
    let bytes: Vec<u8> = (0..64 * 64)
        .map(|_| {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 56) as u8
        })
        .collect();
    Arc::new(GreyImage::from_u8(64, 64, &bytes).expect("frame"))
}

/// Waits until the writer has written (or failed) `n` frames in all.
fn settled(archive: &FrameArchive, n: u64) {
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let c = archive.counters();
        if c.written.load(Relaxed) + c.failed.load(Relaxed) >= n {
            assert_eq!(c.failed.load(Relaxed), 0, "no write failed");
            return;
        }
        assert!(Instant::now() < deadline, "the writer did not finish");
        std::thread::sleep(Duration::from_millis(5));
    }
}

fn disk_bytes(dir: &std::path::Path) -> (u64, usize) {
    let mut total = (0, 0);
    for camera in std::fs::read_dir(dir).expect("dir") {
        for f in std::fs::read_dir(camera.expect("entry").path()).expect("camera dir") {
            let f = f.expect("file");
            total.0 += f.metadata().expect("metadata").len();
            total.1 += 1;
        }
    }
    total
}

#[test]
fn periodic_and_evidence_frames_are_kept_under_readable_names() {
    let dir = tempfile::tempdir().expect("temp dir");
    let settings = FrameSettings {
        archive_dir: Some(dir.path().join("frames")),
        archive_every_s: 1.0,
        archive_max_mb: 100.0,
    };
    let archive = FrameArchive::open(&settings)
        .expect("opens")
        .expect("configured");
    let ms = 1_000_000;
    let offers = [
        ("C1", T0, None, Some(ArchiveReason::Periodic)),
        ("C1", T0 + 40 * ms, None, None), // within the period
        ("C2", T0 + 40 * ms, None, Some(ArchiveReason::Periodic)), // its own period
        (
            "C1",
            T0 + 80 * ms,
            Some(ArchiveReason::NotFound),
            Some(ArchiveReason::NotFound),
        ),
        ("C1", T0 + 999 * ms, None, None),
        ("C1", T0 + 1000 * ms, None, Some(ArchiveReason::Periodic)),
        (
            "C1",
            T0 + 1040 * ms,
            Some(ArchiveReason::Outlier),
            Some(ArchiveReason::Outlier),
        ),
    ];
    let mut kept = 0;
    for (i, (camera, t, evidence, expected)) in offers.iter().enumerate() {
        let reason = archive.offer(camera, *t, &noise(i as u64), *evidence);
        assert_eq!(reason, *expected, "offer {i}");
        if reason.is_some() {
            kept += 1;
            settled(&archive, kept);
        }
    }
    let c1 = archive.list("C1", i64::MIN, i64::MAX, 100);
    let listed: Vec<(i64, ArchiveReason)> = c1.iter().map(|f| (f.time_ns, f.reason)).collect();
    assert_eq!(
        listed,
        [
            (T0, ArchiveReason::Periodic),
            (T0 + 80 * ms, ArchiveReason::NotFound),
            (T0 + 1000 * ms, ArchiveReason::Periodic),
            (T0 + 1040 * ms, ArchiveReason::Outlier),
        ]
    );
    assert_eq!(
        c1[1].path,
        dir.path()
            .join("frames/C1/2026-11-21T10:00:00.080000000Z_not_found.png")
    );
    // A period of the list, and a frame read back as it was offered.
    let middle = archive.list("C1", T0 + 1, T0 + 1000 * ms, 100);
    assert_eq!(middle.len(), 2);
    let bytes = std::fs::read(&c1[1].path).expect("the file");
    assert_eq!(
        decode(&bytes, FrameFormat::Png, None).expect("a PNG"),
        *noise(3),
        "lossless"
    );
    assert_eq!(archive.list("C2", i64::MIN, i64::MAX, 100).len(), 1);
    assert_eq!(archive.bytes(), disk_bytes(&dir.path().join("frames")).0);
}

#[test]
fn the_cap_is_never_exceeded_the_oldest_go_first_and_a_restart_counts_what_is_there() {
    let dir = tempfile::tempdir().expect("temp dir");
    let root = dir.path().join("frames");
    let one = brokenray::imagefile::encode_png_fast(&noise(0))
        .expect("png")
        .len() as f64;
    // Room for about five frames.
    let settings = FrameSettings {
        archive_dir: Some(root.clone()),
        archive_every_s: 60.0,
        archive_max_mb: 5.5 * one / 1e6,
    };
    let cap = (settings.archive_max_mb * 1e6) as u64;
    let archive = FrameArchive::open(&settings)
        .expect("opens")
        .expect("configured");
    for i in 0..20u64 {
        let camera = if i % 2 == 0 { "C1" } else { "C2" };
        let t = T0 + i as i64 * 40_000_000;
        assert!(
            archive
                .offer(camera, t, &noise(i), Some(ArchiveReason::NotFound))
                .is_some()
        );
        settled(&archive, i + 1);
        let (bytes, files) = disk_bytes(&root);
        assert!(
            bytes <= cap,
            "frame {i}: {bytes} bytes on disk over the cap {cap}"
        );
        assert_eq!(bytes, archive.bytes());
        assert!(files <= 5, "{files} files");
    }
    // The newest frames are the ones kept.
    let mut kept: Vec<i64> = ["C1", "C2"]
        .iter()
        .flat_map(|c| archive.list(c, i64::MIN, i64::MAX, 100))
        .map(|f| f.time_ns)
        .collect();
    kept.sort_unstable();
    let newest: Vec<i64> = (20 - kept.len() as i64..20)
        .map(|i| T0 + i * 40_000_000)
        .collect();
    assert_eq!(kept, newest);
    assert!(archive.counters().removed.load(Relaxed) >= 15);
    drop(archive);

    // A crash left a temporary file and someone put a note beside the frames: after a
    // restart the temporary file is gone, the note stays and is not counted.
    std::fs::write(
        root.join("C1/.2026-11-21T10:00:05.000000000Z_periodic.png.tmp"),
        b"half",
    )
    .expect("temp");
    std::fs::write(root.join("C1/README.txt"), b"camera C1, bow").expect("note");
    let reopened = FrameArchive::open(&settings)
        .expect("reopens")
        .expect("configured");
    assert!(
        !root
            .join("C1/.2026-11-21T10:00:05.000000000Z_periodic.png.tmp")
            .exists()
    );
    assert!(root.join("C1/README.txt").exists());
    let listed = reopened.list("C1", i64::MIN, i64::MAX, 100).len()
        + reopened.list("C2", i64::MIN, i64::MAX, 100).len();
    assert_eq!(listed, kept.len());
    let (bytes, _) = disk_bytes(&root);
    assert_eq!(reopened.bytes(), bytes - "camera C1, bow".len() as u64);
}

/// A second frame of a camera at the time of an archived one (another frame posted for the same
/// time) is not archived: the evidence on disk stays the first frame, bit for bit, and the
/// refusal is counted.
#[test]
fn an_archived_frame_is_never_replaced() {
    let dir = tempfile::tempdir().expect("temp dir");
    let settings = FrameSettings {
        archive_dir: Some(dir.path().join("frames")),
        archive_every_s: 1.0,
        archive_max_mb: 100.0,
    };
    let archive = FrameArchive::open(&settings)
        .expect("opens")
        .expect("configured");
    let first = noise(1);
    archive.offer("C1", T0, &first, Some(ArchiveReason::NotFound));
    settled(&archive, 1);
    archive.offer("C1", T0, &noise(2), Some(ArchiveReason::Outlier));
    let deadline = Instant::now() + Duration::from_secs(20);
    while archive.counters().kept_first.load(Relaxed) < 1 {
        assert!(
            Instant::now() < deadline,
            "the second frame was not handled"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_eq!(archive.counters().written.load(Relaxed), 1);
    let kept = archive.get("C1", T0).expect("archived");
    assert_eq!(kept.reason, ArchiveReason::NotFound);
    let on_disk = decode(
        &std::fs::read(&kept.path).expect("file"),
        FrameFormat::Png,
        None,
    )
    .expect("decodes");
    assert_eq!(on_disk.pixels(), first.pixels(), "the first frame stays");
    assert_eq!(disk_bytes(&dir.path().join("frames")).1, 1, "one file");
}
