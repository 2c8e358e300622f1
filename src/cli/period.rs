//! `brokenray report`: a period's report fetched from a running service
//! (`GET /api/v1/report`) and written to a file that did not exist, so a filed report is never
//! overwritten.

use std::io::Write as _;

/// What period a report covers, as the command line gives it (the service defaults what is
/// left out and checks the rest).
#[derive(Debug, Clone, Default)]
pub(super) struct PeriodQuery {
    /// Start (RFC 3339 or integer ns).
    pub from: Option<String>,
    /// End.
    pub to: Option<String>,
    /// The silence counted as a gap (s).
    pub min_gap_s: Option<f64>,
}

/// How long a report may take the service: far over the 30 days a benchmark renders in a
/// few seconds, for a year's report on a slow disk.
const REPORT_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(600);

/// Fetches the report of `query` from the service at `service` and writes it to `out` (which
/// must not exist): the bytes written.
pub(super) fn write_report(
    service: &str,
    token: Option<String>,
    query: &PeriodQuery,
    out: &std::path::Path,
) -> anyhow::Result<u64> {
    let client = crate::feed::Client::new(service, token)?;
    let mut params: Vec<(&str, String)> = Vec::new();
    if let Some(from) = &query.from {
        params.push(("from", from.clone()));
    }
    if let Some(to) = &query.to {
        params.push(("to", to.clone()));
    }
    if let Some(gap) = query.min_gap_s {
        params.push(("min_gap_s", gap.to_string()));
    }
    // Refuse an existing file before asking the service for a long report.
    anyhow::ensure!(
        !out.exists(),
        "{} exists: a report is written to a new file",
        out.display()
    );
    let page = super::runtime(false)?.block_on(client.get_text(
        "/api/v1/report",
        &params,
        REPORT_TIMEOUT,
    ))?;
    let mut file = super::create_new(out)?;
    file.write_all(page.as_bytes())?;
    file.sync_all()?;
    Ok(page.len() as u64)
}
