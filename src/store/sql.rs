//! The statements both backends run, each written once.
//!
//! Placeholders are `$1, $2, ...`, which PostgreSQL takes and SQLite takes as numbered
//! parameters (a number used twice is one parameter, bound once). Column lists come from the
//! table descriptions of [`super::schema`]. What differs between the engines (PostgreSQL's
//! `COPY` and partition upkeep, SQLite's outbox column and multi-row inserts) stays in the
//! backends' modules.

use super::schema::{ALARMS, CALIBRATIONS, REFERENCES, RESULTS, SAMPLES};
use std::sync::LazyLock;

/// Samples of a link in a time window, oldest first: `$1` link id, `$2`..`$3` the window
/// (ns, inclusive), `$4` the most rows.
pub(super) static SAMPLES_IN: LazyLock<String> = LazyLock::new(|| {
    format!(
        "select {} from samples where link_id = $1 and time_ns >= $2 and time_ns <= $3 \
         order by time_ns limit $4",
        SAMPLES.list()
    )
});

/// Results of a target and source in a time window, oldest first: `$1` target id, `$2`
/// source, `$3`..`$4` the window (ns, inclusive), `$5` the most rows.
pub(super) static RESULTS_IN: LazyLock<String> = LazyLock::new(|| {
    format!(
        "select {} from results where target_id = $1 and source = $2 \
         and time_ns >= $3 and time_ns <= $4 order by time_ns limit $5",
        RESULTS.list()
    )
});

/// The time, pose and covariances of results, as [`RESULTS_IN`] without a limit: what the
/// statistics of a window fold.
pub(super) const RESULT_POSES_IN: &str = "select time_ns, tx_mm, ty_mm, tz_mm, qw, qx, qy, qz, \
     cov, cov_systematic from results where target_id = $1 and source = $2 and time_ns >= $3 \
     and time_ns <= $4 order by time_ns";

/// How many results of a target and source lie in a window.
pub(super) const COUNT_RESULTS: &str = "select count(*) from results where target_id = $1 \
     and source = $2 and time_ns >= $3 and time_ns <= $4";

/// The newest stored sample's time of a link (`null` when it has none).
pub(super) const NEWEST_SAMPLE: &str = "select max(time_ns) from samples where link_id = $1";

/// How many samples of a link lie in a window.
pub(super) const COUNT_SAMPLES: &str =
    "select count(*) from samples where link_id = $1 and time_ns >= $2 and time_ns <= $3";

/// The silences between consecutive results of a target and source in a window: the times
/// of the result before and the result after each silence longer than `$5` ns, oldest first,
/// at most `$6`.
pub(super) const RESULT_GAPS: &str = "select prev_ns, time_ns from (select time_ns, \
     lag(time_ns) over (order by time_ns) as prev_ns from results where target_id = $1 \
     and source = $2 and time_ns >= $3 and time_ns <= $4) as runs \
     where time_ns - prev_ns > $5 order by time_ns limit $6";

/// How many samples of a link lie in a window, and how many of them were rejected as
/// outliers.
pub(super) const COUNT_SAMPLES_AND_OUTLIERS: &str = "select count(*), \
     coalesce(sum(case when outlier then 1 else 0 end), 0) from samples where link_id = $1 \
     and time_ns >= $2 and time_ns <= $3";

/// The newest result of a target and source at or before `$3`.
pub(super) static RESULT_AT_OR_BEFORE: LazyLock<String> = LazyLock::new(|| {
    format!(
        "select {} from results where target_id = $1 and source = $2 and time_ns <= $3 \
         order by time_ns desc limit 1",
        RESULTS.list()
    )
});

/// The oldest result of a target and source after `$3`.
pub(super) static RESULT_AFTER: LazyLock<String> = LazyLock::new(|| {
    format!(
        "select {} from results where target_id = $1 and source = $2 and time_ns > $3 \
         order by time_ns asc limit 1",
        RESULTS.list()
    )
});

/// The systematic part of a reference's covariance and its calibration stamp: `$1` the
/// covariance, `$2` the stamp, `$3` target id, `$4` version (written after the reference row,
/// in its transaction).
pub(super) const SET_REFERENCE_SYSTEMATIC: &str = "update target_references \
     set cov_systematic = $1, calibration_stamp = $2 where target_id = $3 and version = $4";

/// Every reference version of a target, oldest first.
pub(super) static REFERENCES_OF: LazyLock<String> = LazyLock::new(|| {
    format!(
        "select {} from target_references where target_id = $1 order by version",
        REFERENCES.list()
    )
});

/// Every calibration version of a link, oldest first.
pub(super) static CALIBRATIONS_OF: LazyLock<String> = LazyLock::new(|| {
    format!(
        "select {} from calibrations where link_id = $1 order by version",
        CALIBRATIONS.list()
    )
});

/// The newest manual restart of each link's filter.
pub(super) const LAST_LINK_RESETS: &str = "select r.link_id, r.created_ns, r.by_name, r.note \
     from link_resets r \
     where r.created_ns = (select max(created_ns) from link_resets where link_id = r.link_id)";

/// The columns an acceptance is read with.
const ACCEPTANCE_COLUMNS: &str = "acceptance_id, created_ns, by_name, note, passed, record";

/// Records an acceptance: `$1` now (ns), `$2` who, `$3` a note, `$4` passed, `$5` the record
/// (JSON); answers its id.
pub(super) const INSERT_ACCEPTANCE: &str = "insert into acceptances \
     (created_ns, by_name, note, passed, record) values ($1, $2, $3, $4, $5) \
     returning acceptance_id";

/// The newest acceptances first: `$1` the most rows.
pub(super) static ACCEPTANCES: LazyLock<String> = LazyLock::new(|| {
    format!(
        "select {ACCEPTANCE_COLUMNS} from acceptances \
         order by created_ns desc, acceptance_id desc limit $1"
    )
});

/// The newest acceptance recorded at or before `$1` (ns).
pub(super) static ACCEPTANCE_AT: LazyLock<String> = LazyLock::new(|| {
    format!(
        "select {ACCEPTANCE_COLUMNS} from acceptances where created_ns <= $1 \
         order by created_ns desc, acceptance_id desc limit 1"
    )
});

/// One acceptance: `$1` its id.
pub(super) static ACCEPTANCE: LazyLock<String> = LazyLock::new(|| {
    format!("select {ACCEPTANCE_COLUMNS} from acceptances where acceptance_id = $1")
});

/// The persisted filter state.
pub(super) const FILTER_STATE: &str =
    "select installation_digest, state from filter_state where id = 1";

/// Saves the filter state: `$1` the installation's digest, `$2` the state, `$3` now (ns).
pub(super) const SAVE_FILTER_STATE: &str = "insert into filter_state \
     (id, installation_digest, state, updated_ns) values (1, $1, $2, $3) \
     on conflict (id) do update set installation_digest = excluded.installation_digest, \
     state = excluded.state, updated_ns = excluded.updated_ns";

/// One alarm transition by id.
pub(super) static ALARM_BY_ID: LazyLock<String> =
    LazyLock::new(|| format!("select {} from alarms where alarm_id = $1", ALARMS.list()));

/// Alarm transitions of one target (`$1`, or all when null) in a window, oldest first.
pub(super) static ALARMS_OLDEST_FIRST: LazyLock<String> =
    LazyLock::new(|| alarms_in("time_ns, target_id, kind"));

/// As [`ALARMS_OLDEST_FIRST`], newest first.
pub(super) static ALARMS_NEWEST_FIRST: LazyLock<String> =
    LazyLock::new(|| alarms_in("time_ns desc, target_id desc, kind desc"));

fn alarms_in(order: &str) -> String {
    format!(
        "select {} from alarms where ($1 is null or target_id = $1) \
         and time_ns >= $2 and time_ns <= $3 order by {order} limit $4",
        ALARMS.list()
    )
}

/// The level an alarm kind (`$2`) of a target (`$1`) was last left at.
pub(super) const LAST_ALARM_LEVEL: &str = "select to_level from alarms \
     where target_id = $1 and kind = $2 order by time_ns desc limit 1";

/// The level and acknowledgement of an alarm transition.
pub(super) const ALARM_ACK_STATE: &str =
    "select to_level, acknowledged_by, ack_note from alarms where alarm_id = $1";

/// The first bucket start of a rollup level (`$1` target, `$2` source, `$3` width). Each end
/// is its own indexed lookup (SQLite optimises a lone `min` or `max`, not both in one query).
pub(super) const ROLLUP_FIRST: &str = "select bucket_ns from rollups \
     where target_id = $1 and source = $2 and width_s = $3 order by bucket_ns asc limit 1";

/// The last bucket start of a rollup level.
pub(super) const ROLLUP_LAST: &str = "select bucket_ns from rollups \
     where target_id = $1 and source = $2 and width_s = $3 order by bucket_ns desc limit 1";

/// Rollup rows `(start, n, n_def, stats)` of one level with starts in `[$4, $5]`.
pub(super) const ROLLUP_ROWS: &str = "select bucket_ns, n, n_def, stats from rollups \
     where target_id = $1 and source = $2 and width_s = $3 \
     and bucket_ns >= $4 and bucket_ns <= $5 order by bucket_ns";

/// A write whose rows carry, on SQLite, the outbox's commit number (`commit_seq`,
/// [`super::outbox`]) and on PostgreSQL do not: one statement in the two texts the engines
/// take. The commit number is bound last, on SQLite only.
pub(super) struct Outboxed {
    with_seq: String,
    without: String,
}

impl Outboxed {
    /// From `text`, where `{seq_col}` stands for the column in a column list, `{seq_val}` for
    /// its value (parameter `$seq`) in a value list, and `{seq_set}` for its assignment in a
    /// `set`.
    fn new(text: &str, seq: usize) -> Self {
        let fill = |col: &str, val: &str, set: &str| {
            text.replace("{seq_col}", col)
                .replace("{seq_val}", val)
                .replace("{seq_set}", set)
        };
        Outboxed {
            with_seq: fill(
                ", commit_seq",
                &format!(", ${seq}"),
                &format!(", commit_seq = ${seq}"),
            ),
            without: fill("", "", ""),
        }
    }

    /// The text for a backend whose rows carry the commit number (`outbox`) or not.
    pub(super) fn text(&self, outbox: bool) -> &str {
        if outbox {
            &self.with_seq
        } else {
            &self.without
        }
    }
}

/// Stores an alarm transition, or updates the one at the same key (a transition recomputed
/// after a rolled-back commit): `$1` target id, `$2` time, `$3` kind, `$4`..`$5` the levels,
/// `$6` value, `$7` unit, `$8` message, `$9` created; answers its id.
pub(super) static INSERT_ALARM: LazyLock<Outboxed> = LazyLock::new(|| {
    Outboxed::new(
        "insert into alarms (target_id, time_ns, kind, from_level, to_level, value, unit, \
         message, created_ns{seq_col}) values ($1, $2, $3, $4, $5, $6, $7, $8, $9{seq_val}) \
         on conflict (target_id, time_ns, kind) do update set from_level = excluded.from_level, \
         to_level = excluded.to_level, value = excluded.value, unit = excluded.unit, \
         message = excluded.message, created_ns = excluded.created_ns{seq_set} \
         returning alarm_id",
        10,
    )
});

/// Records an acknowledgement: `$1` by, `$2` when, `$3` note, `$4` the alarm's id.
pub(super) static ACKNOWLEDGE_ALARM: LazyLock<Outboxed> = LazyLock::new(|| {
    Outboxed::new(
        "update alarms set acknowledged_by = $1, acknowledged_ns = $2, ack_note = $3{seq_set} \
         where alarm_id = $4",
        5,
    )
});

/// Stores a target's next reference version: `$1` target id, `$2`..`$8` the pose, `$9` its
/// covariance, `$10` origin, `$11`..`$13` the window, `$14` created; answers the version.
pub(super) static INSERT_REFERENCE: LazyLock<Outboxed> = LazyLock::new(|| {
    Outboxed::new(
        "insert into target_references (target_id, version, tx_mm, ty_mm, tz_mm, qw, qx, qy, \
         qz, cov, origin, window_from_ns, window_to_ns, window_count, created_ns{seq_col}) \
         select $1, coalesce(max(version), 0) + 1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, \
         $12, $13, $14{seq_val} from target_references where target_id = $1 returning version",
        15,
    )
});

/// Stores a link's next calibration version: `$1` link id, `$2` valid from, `$3`..`$9` the
/// pose, `$10` its covariance, `$11` created; answers the version.
pub(super) static INSERT_CALIBRATION: LazyLock<Outboxed> = LazyLock::new(|| {
    Outboxed::new(
        "insert into calibrations (link_id, version, valid_from_ns, tx_mm, ty_mm, tz_mm, qw, \
         qx, qy, qz, cov, created_ns{seq_col}) select $1, coalesce(max(version), 0) + 1, $2, \
         $3, $4, $5, $6, $7, $8, $9, $10, $11{seq_val} from calibrations where link_id = $1 \
         returning version",
        12,
    )
});

/// Records a manual restart of a link's filter (again at the same instant: the newer words
/// replace the older): `$1` link id, `$2` when, `$3` by, `$4` note.
pub(super) static INSERT_LINK_RESET: LazyLock<Outboxed> = LazyLock::new(|| {
    Outboxed::new(
        "insert into link_resets (link_id, created_ns, by_name, note{seq_col}) \
         values ($1, $2, $3, $4{seq_val}) on conflict (link_id, created_ns) do update set \
         by_name = excluded.by_name, note = excluded.note{seq_set}",
        5,
    )
});
