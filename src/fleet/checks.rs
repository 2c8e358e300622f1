//! What a centre checks of an upload before it applies anything, as methods of the request:
//! each problem names the field (`batch.tables[2].columns[1].int[7]`) and says why, so the
//! HTTP layer answers 422 with it and the site stops that stream instead of retrying.

use super::protocol::SyncRequest;
use crate::store::outbox::{ColumnValues, LINEAGE_KEPT, TableRows, Tier};

/// What is wrong with an upload.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UploadProblem {
    /// The field, as a path into the request.
    pub field: String,
    /// Why.
    pub message: String,
}

impl UploadProblem {
    fn new(field: impl Into<String>, message: impl Into<String>) -> Self {
        Self {
            field: field.into(),
            message: message.into(),
        }
    }
}

/// The largest report of state a site may send (its targets, their descriptions, its
/// problems), as JSON: it is shown to every reader of the fleet, so one site cannot make
/// `GET /api/v1/sites` large for all.
pub const MAX_REPORT_BYTES: usize = 256 * 1024;

impl SyncRequest {
    /// The upload's first problem, at the centre's clock `now_ns`; else its report of state as
    /// the JSON the centre keeps (`None`: no report). A batch's rows must be writable, of its
    /// tier, and within the times the centre keeps; it ends after it starts and at most at the
    /// site's newest commit, which it must state; generations are names; requested rows come
    /// without a batch; the report and the backlog are bounded.
    pub fn check(&self, now_ns: i64) -> Result<Option<String>, UploadProblem> {
        if let Some(b) = &self.batch {
            check_tables("batch.tables", &b.tables, b.tier, now_ns)?;
            if b.upto_seq <= b.after_seq.unwrap_or(i64::MIN) {
                return Err(UploadProblem::new(
                    "batch.upto_seq",
                    "must be after `after_seq`",
                ));
            }
            match self.head_seq {
                None => {
                    return Err(UploadProblem::new(
                        "head_seq",
                        "an upload with a batch says the site's newest commit",
                    ));
                }
                Some(head) if b.upto_seq > head => {
                    return Err(UploadProblem::new(
                        "batch.upto_seq",
                        format!("{} is past the site's newest commit, {head}", b.upto_seq),
                    ));
                }
                Some(_) => {}
            }
        }
        let names = std::iter::once(("generation", self.generation.as_deref()))
            .chain(self.lineage.iter().map(|g| ("lineage", Some(g.as_str()))));
        for (field, name) in names {
            if let Some(name) = name
                && (name.is_empty()
                    || name.len() > 64
                    || !name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-'))
            {
                return Err(UploadProblem::new(
                    field,
                    "a generation is 1 to 64 letters, digits or `-`",
                ));
            }
        }
        if self.lineage.len() > LINEAGE_KEPT {
            return Err(UploadProblem::new(
                "lineage",
                format!("at most {LINEAGE_KEPT} generations"),
            ));
        }
        if let Some(r) = &self.requested {
            if self.batch.is_some() {
                return Err(UploadProblem::new(
                    "requested",
                    "an upload carries a batch or requested rows, not both",
                ));
            }
            check_tables("requested.tables", &r.tables, Tier::Raw, now_ns)?;
            if r.to_ns <= r.from_ns {
                return Err(UploadProblem::new(
                    "requested.to_ns",
                    "must be after `from_ns`",
                ));
            }
        }
        let status = match &self.status {
            // A report read from JSON is written back as JSON.
            Some(s) => Some(serde_json::to_string(s).map_err(|e| {
                UploadProblem::new("status", format!("cannot be kept as JSON: {e}"))
            })?),
            None => None,
        };
        if let Some(text) = &status
            && text.len() > MAX_REPORT_BYTES
        {
            return Err(UploadProblem::new(
                "status",
                format!(
                    "the report of state is {} bytes, at most {MAX_REPORT_BYTES} are kept",
                    text.len()
                ),
            ));
        }
        if self.backlog.len() > Tier::ALL.len() {
            return Err(UploadProblem::new("backlog", "one entry a tier at most"));
        }
        Ok(status)
    }
}

/// The columns of uploaded rows that place them in time partitions: a value outside
/// [`crate::clock::EARLIEST_NS`] to a day past the centre's clock would make partitions no one
/// can keep (and an upkeep that fails for the site).
const PARTITION_TIMES: [&str; 2] = ["time_ns", "bucket_ns"];

/// The largest magnitude of an uploaded real number: a site stores translations to 1e8 mm and
/// covariances to their squares; beyond, a statistic of the copy would overflow.
const MAX_UPLOADED_REAL: f64 = 1e20;

/// How far past the centre's clock an uploaded row's time may lie.
const UPLOAD_FUTURE_NS: i64 = 86_400_000_000_000;

/// Refuses tables of an upload that cannot be written (naming `field[i]`), that are not of
/// `tier`, or whose rows lie outside the times the centre keeps (before
/// [`crate::clock::EARLIEST_NS`], or over a day past `now_ns`).
fn check_tables(
    field: &str,
    tables: &[TableRows],
    tier: Tier,
    now_ns: i64,
) -> Result<(), UploadProblem> {
    let latest = now_ns.saturating_add(UPLOAD_FUTURE_NS);
    for (i, rows) in tables.iter().enumerate() {
        if let Some(problem) = rows.problem() {
            return Err(UploadProblem::new(format!("{field}[{i}]"), problem));
        }
        if let Some(problem) = repeated_key(rows) {
            return Err(UploadProblem::new(format!("{field}[{i}]"), problem));
        }
        if rows.table.tier() != tier {
            return Err(UploadProblem::new(
                format!("{field}[{i}].table"),
                format!("not a table of the {} tier", tier.name()),
            ));
        }
        for (j, ((name, _), values)) in rows.table.columns().iter().zip(&rows.columns).enumerate() {
            if let ColumnValues::Real(reals) = values
                && let Some((k, v)) = reals.iter().enumerate().find_map(|(k, v)| {
                    v.filter(|v| !v.is_finite() || v.abs() > MAX_UPLOADED_REAL)
                        .map(|v| (k, v))
                })
            {
                return Err(UploadProblem::new(
                    format!("{field}[{i}].columns[{j}].real[{k}]"),
                    format!(
                        "{name} {v:e} is beyond anything a site stores (at most \
                         {MAX_UPLOADED_REAL:e} in magnitude)"
                    ),
                ));
            }
            if !PARTITION_TIMES.contains(name) {
                continue;
            }
            let ColumnValues::Int(times) = values else {
                continue;
            };
            if let Some((k, t)) = times.iter().enumerate().find_map(|(k, t)| {
                t.filter(|t| !(crate::clock::EARLIEST_NS..=latest).contains(t))
                    .map(|t| (k, t))
            }) {
                return Err(UploadProblem::new(
                    format!("{field}[{i}].columns[{j}].int[{k}]"),
                    format!(
                        "{name} {} lies outside the times the centre keeps ({} to a day past its \
                         clock)",
                        crate::clock::format_ns(t),
                        crate::clock::format_ns(crate::clock::EARLIEST_NS)
                    ),
                ));
            }
        }
    }
    Ok(())
}

/// Two rows of one uploaded table at the same key, if there are: the database would refuse
/// the upload every time it came (one statement cannot write a row twice).
fn repeated_key(rows: &TableRows) -> Option<String> {
    let columns = rows.table.columns();
    let key: Vec<&Vec<Option<i64>>> = rows
        .table
        .key()
        .iter()
        .filter_map(|k| columns.iter().position(|(name, _)| name == k))
        .filter_map(|at| match &rows.columns[at] {
            ColumnValues::Int(v) => Some(v),
            _ => None,
        })
        .collect();
    if key.len() != rows.table.key().len() {
        return None;
    }
    let mut seen = std::collections::HashMap::with_capacity(rows.rows());
    for row in 0..rows.rows() {
        let values: Vec<Option<i64>> = key.iter().map(|c| c[row]).collect();
        if let Some(first) = seen.insert(values, row) {
            return Some(format!(
                "rows {first} and {row} of {} have the same key ({})",
                rows.table.name(),
                rows.table.key().join(", ")
            ));
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fleet::protocol::{SiteStatus, TierBacklog, WireBatch};
    use crate::store::outbox::{RequestedRows, SyncTable};

    const NOW_NS: i64 = 1_795_000_000_000_000_000;

    fn report_only() -> SyncRequest {
        SyncRequest {
            outbox_id: "outbox-1".to_owned(),
            generation: None,
            lineage: Vec::new(),
            head_seq: None,
            registry: Default::default(),
            batch: None,
            status: None,
            backlog: Vec::new(),
            requested: None,
        }
    }

    /// `rows` rows of samples at `time_ns` (link 1), every other column a plain value.
    fn samples(times_ns: &[i64]) -> TableRows {
        let mut rows = TableRows::new(SyncTable::Samples);
        for (column, (name, _)) in rows.columns.iter_mut().zip(SyncTable::Samples.columns()) {
            for (k, &t) in times_ns.iter().enumerate() {
                match column {
                    ColumnValues::Int(v) => v.push(Some(match *name {
                        "time_ns" => t,
                        "link_id" => 1,
                        _ => k as i64,
                    })),
                    ColumnValues::Real(v) => v.push(Some(0.5)),
                    ColumnValues::Text(v) => v.push(Some("x".to_owned())),
                    ColumnValues::Blob(v) => v.push(None),
                    ColumnValues::Bool(v) => v.push(Some(false)),
                }
            }
        }
        rows
    }

    fn with_batch(after_seq: Option<i64>, upto_seq: i64, head_seq: Option<i64>) -> SyncRequest {
        SyncRequest {
            head_seq,
            batch: Some(WireBatch {
                tier: Tier::Raw,
                after_seq,
                upto_seq,
                partial: false,
                upto_stamp_ns: None,
                tables: vec![samples(&[NOW_NS - 1_000_000_000, NOW_NS])],
            }),
            ..report_only()
        }
    }

    fn field_of(request: &SyncRequest) -> String {
        request.check(NOW_NS).expect_err("refused").field
    }

    #[test]
    fn an_upload_that_can_be_applied_passes_and_keeps_its_report() {
        assert_eq!(report_only().check(NOW_NS), Ok(None));
        assert_eq!(with_batch(Some(3), 5, Some(5)).check(NOW_NS), Ok(None));
        let reported = SyncRequest {
            status: Some(SiteStatus {
                time: "2026-11-27T12:00:00Z".to_owned(),
                targets: Vec::new(),
                described: Vec::new(),
                problems: vec!["a problem".to_owned()],
            }),
            ..report_only()
        };
        let kept = reported.check(NOW_NS).expect("passes").expect("a report");
        let back: SiteStatus = serde_json::from_str(&kept).expect("JSON");
        assert_eq!(Some(back), reported.status);
    }

    #[test]
    fn a_batch_s_numbers_are_checked_against_each_other_and_the_site_s_newest() {
        assert_eq!(field_of(&with_batch(Some(5), 5, Some(9))), "batch.upto_seq");
        assert_eq!(field_of(&with_batch(Some(5), 7, None)), "head_seq");
        let past = with_batch(Some(5), 7, Some(6));
        let problem = past.check(NOW_NS).expect_err("refused");
        assert_eq!(problem.field, "batch.upto_seq");
        assert!(problem.message.contains("past the site's newest commit, 6"));
    }

    #[test]
    fn rows_outside_the_times_kept_of_another_tier_or_twice_at_a_key_are_named() {
        let mut late = with_batch(None, 1, Some(1));
        if let Some(b) = late.batch.as_mut() {
            b.tables = vec![samples(&[NOW_NS, NOW_NS + 2 * UPLOAD_FUTURE_NS])];
        }
        let at = SyncTable::Samples
            .columns()
            .iter()
            .position(|(n, _)| *n == "time_ns")
            .expect("time_ns");
        assert_eq!(
            field_of(&late),
            format!("batch.tables[0].columns[{at}].int[1]")
        );
        let mut twice = with_batch(None, 1, Some(1));
        if let Some(b) = twice.batch.as_mut() {
            b.tables = vec![samples(&[NOW_NS, NOW_NS])];
        }
        let problem = twice.check(NOW_NS).expect_err("refused");
        assert_eq!(problem.field, "batch.tables[0]");
        assert!(problem.message.contains("same key"), "{}", problem.message);
        let mut other_tier = with_batch(None, 1, Some(1));
        if let Some(b) = other_tier.batch.as_mut() {
            b.tier = Tier::Events;
        }
        assert_eq!(field_of(&other_tier), "batch.tables[0].table");
    }

    #[test]
    fn generations_requested_rows_the_report_and_the_backlog_are_bounded() {
        let named = |generation: &str| SyncRequest {
            generation: Some(generation.to_owned()),
            ..report_only()
        };
        assert!(named("gen-2").check(NOW_NS).is_ok());
        assert_eq!(field_of(&named("")), "generation");
        assert_eq!(field_of(&named("a b")), "generation");
        assert_eq!(field_of(&named(&"g".repeat(65))), "generation");
        let deep = SyncRequest {
            lineage: vec!["g".to_owned(); LINEAGE_KEPT + 1],
            ..report_only()
        };
        assert_eq!(field_of(&deep), "lineage");

        let slice = |from_ns, to_ns| RequestedRows {
            request_id: 1,
            from_ns,
            to_ns,
            replace: true,
            tables: vec![samples(&[NOW_NS])],
        };
        let both = SyncRequest {
            requested: Some(slice(0, NOW_NS)),
            ..with_batch(None, 1, Some(1))
        };
        assert_eq!(field_of(&both), "requested");
        let backwards = SyncRequest {
            requested: Some(slice(NOW_NS, NOW_NS)),
            ..report_only()
        };
        assert_eq!(field_of(&backwards), "requested.to_ns");

        let large = SyncRequest {
            status: Some(SiteStatus {
                time: "2026-11-27T12:00:00Z".to_owned(),
                targets: Vec::new(),
                described: Vec::new(),
                problems: vec!["x".repeat(MAX_REPORT_BYTES)],
            }),
            ..report_only()
        };
        assert_eq!(field_of(&large), "status");
        let backlog = TierBacklog {
            tier: Tier::Raw,
            rows: 1,
            acked_seq: None,
            requested_rows: None,
        };
        let long = SyncRequest {
            backlog: vec![backlog; Tier::ALL.len() + 1],
            ..report_only()
        };
        assert_eq!(field_of(&long), "backlog");
    }
}
