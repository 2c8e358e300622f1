//! A look at an SQLite write-ahead log before the database is opened, so that a damaged one is
//! said, not silently cut short.
//!
//! Opening a database whose WAL holds frames replays the frames up to the last commit whose
//! checksums chain correctly; a damaged frame in the middle ends the replay there and the
//! commits after it (acknowledged writes among them) are gone, without a word from SQLite to
//! the program. This reads the WAL file as its format defines it (a 32-byte header, then frames
//! of a 24-byte header and a page, each checksummed cumulatively, salted per generation) and
//! counts what will be replayed and what lies past a break in this generation.

use std::path::Path;

/// What a WAL file holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(crate) struct WalReport {
    /// Frames that will be replayed (up to the last good commit).
    pub replayed_frames: u64,
    /// Commits among them.
    pub replayed_commits: u64,
    /// Frames of this generation of the WAL past a break in the checksum chain: lost.
    pub lost_frames: u64,
    /// Commits among those.
    pub lost_commits: u64,
}

fn be32(b: &[u8], at: usize) -> u32 {
    u32::from_be_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

/// The WAL checksum over `data` (a multiple of 8 bytes), continuing from `s`.
fn checksum(s: (u32, u32), data: &[u8], big_endian: bool) -> (u32, u32) {
    let (mut s0, mut s1) = s;
    for pair in data.chunks_exact(8) {
        let word = |i: usize| {
            let w = [pair[i], pair[i + 1], pair[i + 2], pair[i + 3]];
            if big_endian {
                u32::from_be_bytes(w)
            } else {
                u32::from_le_bytes(w)
            }
        };
        s0 = s0.wrapping_add(word(0)).wrapping_add(s1);
        s1 = s1.wrapping_add(word(4)).wrapping_add(s0);
    }
    (s0, s1)
}

/// What the WAL beside the database at `database` holds; `None` when there is none, or it is
/// empty or not a WAL (SQLite then ignores it).
pub(crate) fn inspect(database: &Path) -> Option<WalReport> {
    let mut name = database.as_os_str().to_owned();
    name.push("-wal");
    let bytes = std::fs::read(std::path::PathBuf::from(name)).ok()?;
    read(&bytes)
}

/// The same, of a WAL's bytes.
pub(crate) fn read(bytes: &[u8]) -> Option<WalReport> {
    if bytes.len() < 32 {
        return None;
    }
    let magic = be32(bytes, 0);
    if magic & !1 != 0x377f_0682 {
        return None;
    }
    let big_endian = magic & 1 == 1;
    let page_size = match be32(bytes, 8) {
        1 => 65_536,
        n if n.is_power_of_two() && (512..=32_768).contains(&n) => n as usize,
        _ => return None,
    };
    let salts = (be32(bytes, 16), be32(bytes, 20));
    let header_sum = checksum((0, 0), &bytes[..24], big_endian);
    if header_sum != (be32(bytes, 24), be32(bytes, 28)) {
        return None;
    }
    let mut report = WalReport::default();
    let mut sum = header_sum;
    let (mut frames_since_commit, mut broken) = (0u64, false);
    let frame_size = 24 + page_size;
    for frame in bytes[32..].chunks_exact(frame_size) {
        let (page_number, commit_size) = (be32(frame, 0), be32(frame, 4));
        let same_generation = (be32(frame, 8), be32(frame, 12)) == salts;
        if !broken {
            let next = checksum(
                checksum(sum, &frame[..8], big_endian),
                &frame[24..],
                big_endian,
            );
            if same_generation && page_number != 0 && next == (be32(frame, 16), be32(frame, 20)) {
                sum = next;
                frames_since_commit += 1;
                if commit_size != 0 {
                    report.replayed_frames += frames_since_commit;
                    report.replayed_commits += 1;
                    frames_since_commit = 0;
                }
                continue;
            }
            broken = true;
            // Frames after the last commit, before the break, are an unfinished transaction:
            // never acknowledged, not lost.
        }
        if same_generation {
            report.lost_frames += 1;
            report.lost_commits += u64::from(commit_size != 0);
        }
    }
    Some(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A WAL of `commits` one-frame commits with 512-byte pages, checksummed as SQLite does.
    fn wal(commits: u32, big_endian: bool) -> Vec<u8> {
        let mut out = vec![0u8; 32];
        out[..4].copy_from_slice(&(0x377f_0682u32 | u32::from(big_endian)).to_be_bytes());
        out[4..8].copy_from_slice(&3_007_000u32.to_be_bytes());
        out[8..12].copy_from_slice(&512u32.to_be_bytes());
        out[16..20].copy_from_slice(&7u32.to_be_bytes());
        out[20..24].copy_from_slice(&9u32.to_be_bytes());
        let mut sum = checksum((0, 0), &out[..24], big_endian);
        out[24..28].copy_from_slice(&sum.0.to_be_bytes());
        out[28..32].copy_from_slice(&sum.1.to_be_bytes());
        for k in 0..commits {
            let mut frame = vec![0u8; 24 + 512];
            frame[..4].copy_from_slice(&(k + 1).to_be_bytes());
            frame[4..8].copy_from_slice(&(k + 1).to_be_bytes());
            frame[8..12].copy_from_slice(&7u32.to_be_bytes());
            frame[12..16].copy_from_slice(&9u32.to_be_bytes());
            for (i, b) in frame[24..].iter_mut().enumerate() {
                *b = (i as u32 * 31 + k) as u8;
            }
            sum = checksum(
                checksum(sum, &frame[..8], big_endian),
                &frame[24..],
                big_endian,
            );
            frame[16..20].copy_from_slice(&sum.0.to_be_bytes());
            frame[20..24].copy_from_slice(&sum.1.to_be_bytes());
            out.extend_from_slice(&frame);
        }
        out
    }

    #[test]
    fn a_whole_wal_is_replayed_and_a_damaged_one_says_what_is_lost() {
        for big_endian in [false, true] {
            let good = wal(5, big_endian);
            assert_eq!(
                read(&good),
                Some(WalReport {
                    replayed_frames: 5,
                    replayed_commits: 5,
                    lost_frames: 0,
                    lost_commits: 0,
                })
            );
            // A byte of the third frame's page flipped: frames 3 to 5 are lost.
            let mut damaged = good.clone();
            damaged[32 + 2 * (24 + 512) + 100] ^= 0x40;
            assert_eq!(
                read(&damaged),
                Some(WalReport {
                    replayed_frames: 2,
                    replayed_commits: 2,
                    lost_frames: 3,
                    lost_commits: 3,
                })
            );
        }
        assert_eq!(read(b"not a wal at all, not even close to 32 bytes"), None);
    }

    /// Against SQLite itself: a WAL it wrote reads as whole, and the same damage makes SQLite
    /// replay exactly the commits counted as replayed.
    #[test]
    fn the_count_agrees_with_sqlites_own_replay() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.db");
        let db = rusqlite::Connection::open(&path).unwrap();
        db.execute_batch(
            "pragma journal_mode = wal; pragma wal_autocheckpoint = 0; \
             create table t (k integer primary key, v blob);",
        )
        .unwrap();
        for k in 0..20 {
            db.execute("insert into t (k, v) values (?1, randomblob(3000))", [k])
                .unwrap();
        }
        let wal_path = dir.path().join("w.db-wal");
        let mut bytes = std::fs::read(&wal_path).unwrap();
        let whole = read(&bytes).unwrap();
        assert_eq!(whole.lost_frames, 0);
        assert!(whole.replayed_commits >= 21, "{whole:?}");
        // A copy of the files, its WAL damaged in the middle.
        let copy = dir.path().join("copy.db");
        std::fs::copy(&path, &copy).unwrap();
        let page = be32(&bytes, 8) as usize;
        let middle = 32 + (bytes.len() - 32) / (24 + page) / 2 * (24 + page) + 24 + 10;
        bytes[middle] ^= 0xff;
        std::fs::write(dir.path().join("copy.db-wal"), &bytes).unwrap();
        drop(db);
        let report = read(&bytes).unwrap();
        assert!(report.lost_commits > 0, "{report:?}");
        let copy_db = rusqlite::Connection::open(&copy).unwrap();
        let rows: i64 = copy_db
            .query_row("select count(*) from t", [], |r| r.get(0))
            .unwrap_or(0);
        // The table's creation is one commit; each insert one more.
        assert_eq!(
            rows as u64,
            report
                .replayed_commits
                .saturating_sub(whole.replayed_commits - 20),
            "{report:?}"
        );
    }
}
