//! A service's counters for `GET /metrics`, shared by the pipeline and the server (which
//! count) and the readers (which render them). Atomics only: counting never waits. Each
//! service has its own, so two services in one process (tests) count apart.

use std::sync::atomic::{AtomicU64, Ordering};

/// Counters of the pipeline.
#[derive(Debug, Default)]
pub struct Metrics {
    /// Ingest requests committed.
    pub ingest_requests: AtomicU64,
    /// Samples newly stored.
    pub samples_stored: AtomicU64,
    /// Samples that were identical retries.
    pub samples_duplicate: AtomicU64,
    /// Samples flagged as outliers.
    pub samples_outlier: AtomicU64,
    /// Filter restarts after runs of consistent outliers.
    pub filter_restarts: AtomicU64,
    /// Transactions committed.
    pub commits: AtomicU64,
    /// Transactions that failed (their requests were refused).
    pub commits_failed: AtomicU64,
    /// Groups of ingest requests filtered while the commit before them was being written.
    pub groups_filtered_ahead: AtomicU64,
    /// Ingest requests that may repeat stored samples (a retry, a late batch), whose links'
    /// stored samples were read before filtering.
    pub ingest_read_first: AtomicU64,
    /// Of those, the ones read while a commit was being written (the committed samples
    /// through a reader, the commit's own in memory) rather than after waiting for it.
    pub ingest_read_during_commit: AtomicU64,
    /// Ingest requests filtered ahead whose samples older than the filters' memory needed
    /// other links' stored samples to complete their groups: they waited for the commit
    /// before them and went on in a transaction of the writer's own. (A late batch of whole
    /// groups completes them from its own samples and is not counted.)
    pub ingest_old_groups_from_store: AtomicU64,
    /// Sum of commit durations (microseconds).
    pub commit_micros_sum: AtomicU64,
    /// Longest commit (microseconds).
    pub commit_micros_max: AtomicU64,
    /// Alarm transitions the notification queue had no room for (never sent).
    pub alarm_feed_dropped: AtomicU64,
    /// On a centre: passes of its sites' upkeep (retention, partitions) that failed.
    pub centre_upkeep_failed: AtomicU64,
    /// On a centre: sites' rows its retention removed.
    pub centre_rows_pruned: AtomicU64,
    /// Rows the disk budget removed before their retention age.
    pub budget_rows_removed: AtomicU64,
    /// Of those, rows the centre had not acknowledged.
    pub budget_unsent_removed: AtomicU64,
    /// The SQLite file's bytes in use at the last retention pass under a disk budget.
    pub database_used_bytes: AtomicU64,
    /// Requests refused, by [`REJECTION_STATUSES`].
    pub rejected: [AtomicU64; 12],
    /// The server loop's connections.
    pub connections: ConnectionCounters,
}

/// What the server loop counts of its connections.
#[derive(Debug, Default)]
pub struct ConnectionCounters {
    /// Connections closed on arrival: the limits were reached and every connection was busy.
    pub refused: AtomicU64,
    /// Idle connections closed to make room for a newcomer.
    pub evicted: AtomicU64,
    /// Connections open now.
    pub open: AtomicU64,
}

/// The statuses refusals are counted under (500: any 5xx).
pub const REJECTION_STATUSES: [u16; 12] =
    [400, 401, 403, 404, 405, 408, 409, 413, 415, 422, 431, 500];

impl Metrics {
    /// Records one commit's duration.
    pub fn commit(&self, micros: u64) {
        self.commits.fetch_add(1, Ordering::Relaxed);
        self.commit_micros_sum.fetch_add(micros, Ordering::Relaxed);
        self.commit_micros_max.fetch_max(micros, Ordering::Relaxed);
    }

    /// Counts a refused request by its status (every 5xx as 500; others not listed are not
    /// counted).
    pub fn count_rejection(&self, status: u16) {
        let status = if status >= 500 { 500 } else { status };
        if let Some(i) = REJECTION_STATUSES.iter().position(|s| *s == status) {
            self.rejected[i].fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Reads a counter.
    pub fn get(counter: &AtomicU64) -> u64 {
        counter.load(Ordering::Relaxed)
    }
}
