//! The Prometheus text exposition of `/metrics`: the service's counters and gauges, each family
//! one group (HELP, TYPE, then its samples), label values escaped as the format wants. The HTTP
//! adapter serves what [`render`] writes; the strict parser of the tests reads it back.

use crate::archive::FrameArchive;
use crate::fleet::{TierProgress, Upstream};
use crate::model::LinkKind;
use crate::notify::Webhooks;
use crate::service::{Metrics, Service};
use std::fmt::Write as _;

/// The text being written.
#[derive(Debug, Default)]
pub struct Exposition {
    text: String,
}

/// A family of [`Exposition::labelled_families`]: name, type, help, and the row's value.
pub type Family<R> = (
    &'static str,
    &'static str,
    &'static str,
    fn(&R) -> Option<f64>,
);

/// A label value as the exposition format writes it: backslash, double quote and line feed
/// escaped.
fn escaped(value: &str) -> String {
    value
        .replace('\\', "\\\\")
        .replace('"', "\\\"")
        .replace('\n', "\\n")
}

impl Exposition {
    /// A family's HELP and TYPE lines; its samples follow.
    pub fn family(&mut self, name: &str, kind: &str, help: &str) {
        let _ = writeln!(self.text, "# HELP {name} {help}");
        let _ = writeln!(self.text, "# TYPE {name} {kind}");
    }

    /// One sample of the current family (`name` may carry a suffix such as `_sum`).
    pub fn sample(&mut self, name: &str, labels: &[(&str, String)], value: impl std::fmt::Display) {
        self.text.push_str(name);
        if !labels.is_empty() {
            self.text.push('{');
            for (i, (label, v)) in labels.iter().enumerate() {
                if i > 0 {
                    self.text.push(',');
                }
                let _ = write!(self.text, "{label}=\"{}\"", escaped(v));
            }
            self.text.push('}');
        }
        let _ = writeln!(self.text, " {value}");
    }

    /// A family of one unlabelled value.
    pub fn single(&mut self, name: &str, kind: &str, help: &str, value: impl std::fmt::Display) {
        self.family(name, kind, help);
        self.sample(name, &[], value);
    }

    /// Families of one sample per row, labelled `label` = the row's name: each family's HELP
    /// and TYPE, then its samples together; a row whose field is `None` has no sample in that
    /// family.
    pub fn labelled_families<R>(
        &mut self,
        label: &str,
        rows: &[(&str, R)],
        families: &[Family<R>],
    ) {
        for (name, kind, help, field) in families {
            self.family(name, kind, help);
            for (value, row) in rows {
                if let Some(v) = field(row) {
                    self.sample(name, &[(label, (*value).to_owned())], v);
                }
            }
        }
    }

    /// The text.
    pub fn finish(self) -> String {
        self.text
    }
}

/// What `/metrics` reports on.
pub struct Sources<'a> {
    /// The service.
    pub service: &'a Service,
    /// Its alarm notifications.
    pub webhooks: &'a Webhooks,
    /// The plant's buses it publishes on.
    pub outputs: &'a [crate::outputs::OutputStatus],
    /// The frame archive, when one is configured.
    pub archive: Option<&'a FrameArchive>,
    /// A site's uploads, when it pushes to a centre.
    pub upstream: Option<&'a Upstream>,
    /// The cameras the service takes frames from itself.
    pub cameras: &'a [std::sync::Arc<crate::acquire::SourceState>],
}

/// The whole exposition.
pub fn render(sources: &Sources<'_>) -> String {
    let service = sources.service;
    let m = service.metrics();
    let viz = service.viz_counters();
    let mut out = Exposition::default();
    for (name, help, counter) in [
        (
            "brokenray_ingest_requests_total",
            "Ingest requests committed.",
            &m.ingest_requests,
        ),
        (
            "brokenray_samples_stored_total",
            "Samples newly stored.",
            &m.samples_stored,
        ),
        (
            "brokenray_samples_duplicate_total",
            "Samples that were identical retries of stored ones.",
            &m.samples_duplicate,
        ),
        (
            "brokenray_samples_outlier_total",
            "Samples flagged as outliers by the innovation gate.",
            &m.samples_outlier,
        ),
        (
            "brokenray_filter_restarts_total",
            "Filter restarts after runs of consistent outliers.",
            &m.filter_restarts,
        ),
        (
            "brokenray_alarm_notifications_dropped_total",
            "Alarm transitions not handed to the webhooks (their queue was full).",
            &m.alarm_feed_dropped,
        ),
        (
            "brokenray_centre_upkeep_failed_total",
            "On a centre: passes of the sites' upkeep (retention, partitions) that failed.",
            &m.centre_upkeep_failed,
        ),
        (
            "brokenray_centre_rows_pruned_total",
            "On a centre: sites' rows removed by its retention.",
            &m.centre_rows_pruned,
        ),
        (
            "brokenray_budget_rows_removed_total",
            "Rows the disk budget removed before their retention age.",
            &m.budget_rows_removed,
        ),
        (
            "brokenray_budget_unsent_removed_total",
            "Rows the disk budget removed that the centre had not acknowledged.",
            &m.budget_unsent_removed,
        ),
        (
            "brokenray_commits_failed_total",
            "Transactions that failed; their requests were refused.",
            &m.commits_failed,
        ),
        (
            "brokenray_groups_filtered_ahead_total",
            "Groups of ingest requests filtered while the commit before them was being written.",
            &m.groups_filtered_ahead,
        ),
        (
            "brokenray_ingest_read_first_total",
            "Ingest requests that may repeat stored samples (a retry, a late batch), read from the store before filtering.",
            &m.ingest_read_first,
        ),
        (
            "brokenray_ingest_read_during_commit_total",
            "Of the ingest requests read first, those read while the commit before them was being written.",
            &m.ingest_read_during_commit,
        ),
        (
            "brokenray_ingest_old_groups_from_store_total",
            "Ingest requests whose samples older than the filters' memory needed other links' stored samples: they waited for the commit before them.",
            &m.ingest_old_groups_from_store,
        ),
        (
            "brokenray_connections_refused_total",
            "Connections closed on arrival: a connection limit was reached and every connection was busy with a request.",
            &m.connections.refused,
        ),
        (
            "brokenray_connections_evicted_total",
            "Idle connections (waiting for a request head) closed to make room for a newcomer.",
            &m.connections.evicted,
        ),
        (
            "brokenray_rerun_queued_total",
            "Records queued for the Rerun logger.",
            &viz.queued,
        ),
        (
            "brokenray_rerun_dropped_total",
            "Records for Rerun dropped because the logger's queue was full (a slow or absent viewer).",
            &viz.dropped,
        ),
        (
            "brokenray_rerun_decimated_total",
            "Records for Rerun left out by the configured rates.",
            &viz.decimated,
        ),
        (
            "brokenray_rerun_logged_total",
            "Records the Rerun logger wrote.",
            &viz.logged,
        ),
        (
            "brokenray_rerun_errors_total",
            "Records the Rerun SDK refused.",
            &viz.errors,
        ),
        (
            "brokenray_rerun_files_total",
            "Recording files started (one per run and rotation).",
            &viz.files,
        ),
    ] {
        out.single(name, "counter", help, Metrics::get(counter));
    }
    out.single(
        "brokenray_connections_open",
        "gauge",
        "Client connections open now.",
        Metrics::get(&m.connections.open),
    );
    out.family(
        "brokenray_requests_rejected_total",
        "counter",
        "Requests refused, by status code (500: any 5xx).",
    );
    for (code, counter) in crate::service::REJECTION_STATUSES.iter().zip(&m.rejected) {
        out.sample(
            "brokenray_requests_rejected_total",
            &[("status", code.to_string())],
            Metrics::get(counter),
        );
    }
    out.single(
        "brokenray_writer_queue_depth",
        "gauge",
        "Requests waiting for the writer.",
        service.queue_depth(),
    );
    out.family(
        "brokenray_commit_seconds",
        "summary",
        "Duration of write transactions.",
    );
    out.sample(
        "brokenray_commit_seconds_sum",
        &[],
        Metrics::get(&m.commit_micros_sum) as f64 / 1e6,
    );
    out.sample(
        "brokenray_commit_seconds_count",
        &[],
        Metrics::get(&m.commits),
    );
    out.single(
        "brokenray_commit_seconds_max",
        "gauge",
        "Longest write transaction since start.",
        Metrics::get(&m.commit_micros_max) as f64 / 1e6,
    );

    let inst = service.installation();
    let snapshot = service.snapshot();
    let bank = &snapshot.bank;
    let newest = bank.newest_sample_ns();
    let now_ns = service.now_ns();
    let tolerance_s = inst.server.clock_tolerance_s;
    if let Some(budget) = inst.retention.disk_budget_bytes {
        out.single(
            "brokenray_disk_budget_bytes",
            "gauge",
            "The SQLite file's disk budget (`[retention] disk_budget_mb`).",
            budget,
        );
        out.single(
            "brokenray_database_used_bytes",
            "gauge",
            "The SQLite file's bytes in use at the last retention pass (every ten minutes).",
            Metrics::get(&m.database_used_bytes),
        );
    }
    // Per measured link, written one family at a time.
    struct LinkRow {
        samples: u64,
        outliers: u64,
        ungrouped: u64,
        rate_hz: Option<f64>,
        behind_s: Option<f64>,
        age_s: Option<f64>,
        stale: Option<bool>,
    }
    let rows: Vec<(&str, LinkRow)> = inst
        .model
        .links
        .iter()
        .filter(|l| matches!(l.kind, LinkKind::Measured(_)))
        .map(|l| {
            let st = bank.link_status(l.id);
            let row = LinkRow {
                samples: st.n_samples,
                outliers: st.n_outliers,
                ungrouped: st.n_ungrouped,
                rate_hz: bank.observed_rate_hz(l.id),
                behind_s: newest
                    .and_then(|n| bank.link_lag(l.id, n))
                    .map(|lag| lag.behind_s),
                age_s: st.last_time_ns.map(|last| (now_ns - last) as f64 / 1e9),
                stale: st.last_time_ns.map(|_| {
                    snapshot.link_state(l.id, now_ns, tolerance_s)
                        == crate::service::LinkState::Stale
                }),
            };
            (l.name.as_str(), row)
        })
        .collect();
    let link_families: [Family<LinkRow>; 7] = [
        (
            "brokenray_link_samples_total",
            "counter",
            "Samples of a measured link.",
            |r| Some(r.samples as f64),
        ),
        (
            "brokenray_link_outliers_total",
            "counter",
            "Outliers of a measured link.",
            |r| Some(r.outliers as f64),
        ),
        (
            "brokenray_link_samples_ungrouped_total",
            "counter",
            "Samples of a measured link whose measurement group closed without a raw result (since start).",
            |r| Some(r.ungrouped as f64),
        ),
        (
            "brokenray_link_rate_hz",
            "gauge",
            "Observed sample rate of a measured link.",
            |r| r.rate_hz,
        ),
        (
            "brokenray_link_behind_seconds",
            "gauge",
            "How far a link's newest sample is behind the newest sample of any link (measurement time).",
            |r| r.behind_s,
        ),
        (
            "brokenray_link_age_seconds",
            "gauge",
            "Seconds from a link's newest sample to now on the server's clock.",
            |r| r.age_s,
        ),
        (
            "brokenray_link_stale",
            "gauge",
            "1 when a link's newest sample is older than its staleness limit on the server's clock (or behind the newest link by more than it).",
            |r| r.stale.map(|s| f64::from(u8::from(s))),
        ),
    ];
    out.labelled_families("link", &rows, &link_families);
    out.family(
        "brokenray_target_age_seconds",
        "gauge",
        "Seconds from a target's newest filtered result to now on the server's clock, labelled with its status now.",
    );
    for (i, t) in inst.model.target_ids() {
        let now = snapshot.target_now(i, now_ns, tolerance_s);
        if let Some(age_s) = now.age_s {
            out.sample(
                "brokenray_target_age_seconds",
                &[
                    ("target", t.name.clone()),
                    ("status", now.status.name().to_owned()),
                ],
                age_s,
            );
        }
    }
    webhooks(&mut out, &sources.webhooks.status());
    outputs(&mut out, sources.outputs);
    camera_sources(&mut out, sources.cameras);
    if let Some(archive) = sources.archive {
        let c = archive.counters();
        for (name, help, counter) in [
            (
                "brokenray_frames_archived_total",
                "Frames written to the frame archive.",
                &c.written,
            ),
            (
                "brokenray_frames_archive_removed_total",
                "Archived frames removed to stay under archive_max_mb.",
                &c.removed,
            ),
            (
                "brokenray_frames_archive_dropped_total",
                "Frames to archive that were not, because the archive's writer was behind.",
                &c.dropped,
            ),
            (
                "brokenray_frames_archive_failed_total",
                "Frames whose archiving failed (see the log).",
                &c.failed,
            ),
            (
                "brokenray_frames_archive_kept_first_total",
                "Frames not archived because the camera's frame at the same time is archived already (evidence is never replaced).",
                &c.kept_first,
            ),
        ] {
            out.single(name, "counter", help, Metrics::get(counter));
        }
        out.single(
            "brokenray_frames_archive_bytes",
            "gauge",
            "Size of the frame archive on disk.",
            archive.bytes(),
        );
    }
    if let Some(upstream) = sources.upstream {
        upstream_metrics(&mut out, upstream);
    }
    out.finish()
}

/// A fleet's site: its uploads per tier.
fn upstream_metrics(out: &mut Exposition, upstream: &Upstream) {
    let progress = upstream.progress();
    let families: [Family<TierProgress>; 6] = [
        (
            "brokenray_upstream_acked_seq",
            "gauge",
            "The last of this site's commits the centre acknowledged, per tier.",
            |p| p.acked_seq.map(|s| s as f64),
        ),
        (
            "brokenray_upstream_backlog_rows",
            "gauge",
            "Rows the centre has not acknowledged, per tier.",
            |p| p.backlog_rows.map(|r| r as f64),
        ),
        (
            "brokenray_upstream_sent_rows_total",
            "counter",
            "Rows the centre acknowledged since start, per tier.",
            |p| Some(p.rows_sent as f64),
        ),
        (
            "brokenray_upstream_sent_bytes_total",
            "counter",
            "Compressed bytes of acknowledged uploads since start, per tier.",
            |p| Some(p.bytes_sent as f64),
        ),
        (
            "brokenray_upstream_errors_total",
            "counter",
            "Uploads that failed since start, per tier.",
            |p| Some(p.errors as f64),
        ),
        (
            "brokenray_upstream_stopped",
            "gauge",
            "1 when the centre refused a tier's stream (it resumes after a restart).",
            |p| Some(if p.stopped.is_some() { 1.0 } else { 0.0 }),
        ),
    ];
    let rows: Vec<(&str, TierProgress)> = progress
        .into_iter()
        .map(|(tier, p)| (tier.name(), p))
        .collect();
    out.labelled_families("tier", &rows, &families);
}

/// The camera sources' counters, labelled by camera.
fn camera_sources(out: &mut Exposition, cameras: &[std::sync::Arc<crate::acquire::SourceState>]) {
    use crate::acquire::{SourceReport, SourceStatus};
    if cameras.is_empty() {
        return;
    }
    let families: [Family<SourceReport>; 9] = [
        (
            "brokenray_camera_connected",
            "gauge",
            "1 while a camera source's frames arrive.",
            |r| {
                Some(if r.detail.status == SourceStatus::Streaming {
                    1.0
                } else {
                    0.0
                })
            },
        ),
        (
            "brokenray_camera_frames_received_total",
            "counter",
            "Complete frames a camera source received.",
            |r| Some(r.received as f64),
        ),
        (
            "brokenray_camera_frames_ingested_total",
            "counter",
            "Frames of a camera source ingested.",
            |r| Some(r.ingested as f64),
        ),
        (
            "brokenray_camera_frames_dropped_total",
            "counter",
            "Frames of a camera source dropped, oldest first, from its full queue before ingest took them.",
            |r| Some(r.dropped as f64),
        ),
        (
            "brokenray_camera_incomplete_buffers_total",
            "counter",
            "Buffers of a camera source that arrived incomplete (lost packets), not used.",
            |r| Some(r.incomplete as f64),
        ),
        (
            "brokenray_camera_frames_refused_time_total",
            "counter",
            "Frames refused for their time (PTP not synchronised, a time far from the host's clock).",
            |r| Some(r.refused_time as f64),
        ),
        (
            "brokenray_camera_frames_failed_total",
            "counter",
            "Frames of a camera source that ingest refused or failed on.",
            |r| Some(r.failed as f64),
        ),
        (
            "brokenray_camera_reconnects_total",
            "counter",
            "Connections to a camera made again after a loss.",
            |r| Some(r.reconnects as f64),
        ),
        (
            "brokenray_camera_delay_p99_seconds",
            "gauge",
            "99th percentile of the newest frames' delay from the middle of the exposure to the result committed.",
            |r| r.delay_s.map(|d| d.1),
        ),
    ];
    let reports: Vec<SourceReport> = cameras.iter().map(|c| c.report()).collect();
    let rows: Vec<(&str, SourceReport)> = reports
        .iter()
        .map(|r| (r.camera.as_str(), r.clone()))
        .collect();
    out.labelled_families("camera", &rows, &families);
}

/// The webhooks' families, from the status the notifier exposes (`notify` knows nothing of the
/// exposition format).
fn webhooks(out: &mut Exposition, hooks: &[crate::notify::WebhookStatus]) {
    if hooks.is_empty() {
        return;
    }
    let labels = |h: &crate::notify::WebhookStatus| {
        vec![("webhook", h.index.to_string()), ("host", h.host.clone())]
    };
    out.family(
        "brokenray_webhook_deliveries_total",
        "counter",
        "Alarm notifications by outcome: delivered, failed (given up or refused), dropped (queue full).",
    );
    for h in hooks {
        for (outcome, n) in [
            ("delivered", h.delivered),
            ("failed", h.failed),
            ("dropped", h.dropped),
        ] {
            let mut l = labels(h);
            l.push(("outcome", outcome.to_owned()));
            out.sample("brokenray_webhook_deliveries_total", &l, n);
        }
    }
    out.family(
        "brokenray_webhook_attempts_failed_total",
        "counter",
        "Attempts that failed (each retried or given up).",
    );
    for h in hooks {
        out.sample(
            "brokenray_webhook_attempts_failed_total",
            &labels(h),
            h.attempts_failed,
        );
    }
    out.family(
        "brokenray_webhook_queued",
        "gauge",
        "Alarm notifications waiting or being retried.",
    );
    for h in hooks {
        out.sample("brokenray_webhook_queued", &labels(h), h.queued);
    }
}

/// The plant outputs' families (MQTT, Modbus, NMEA), from the status they expose.
fn outputs(out: &mut Exposition, outputs: &[crate::outputs::OutputStatus]) {
    use crate::outputs::OutputStatus;
    use crate::words::Word as _;
    if outputs.is_empty() {
        return;
    }
    /// A family: its name, type, help, and its value of an output.
    type Family = (
        &'static str,
        &'static str,
        &'static str,
        fn(&OutputStatus) -> u64,
    );
    let families: [Family; 4] = [
        (
            "brokenray_output_connected",
            "gauge",
            "1 when the output is connected (MQTT), listening (Modbus) or its last send succeeded (NMEA).",
            |o| u64::from(o.connected),
        ),
        (
            "brokenray_output_sent_total",
            "counter",
            "Messages published (MQTT), reads answered (Modbus), sentences sent (NMEA).",
            |o| o.sent,
        ),
        (
            "brokenray_output_dropped_total",
            "counter",
            "Alarm transitions dropped because the output's queue was full.",
            |o| o.dropped,
        ),
        (
            "brokenray_output_queued",
            "gauge",
            "Messages waiting to be delivered.",
            |o| o.queued,
        ),
    ];
    for (name, kind, help, value) in families {
        out.family(name, kind, help);
        for o in outputs {
            let labels = [
                ("output", o.kind.word().to_owned()),
                ("address", o.address.clone()),
            ];
            out.sample(name, &labels, value(o));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_are_written_with_their_labels_escaped() {
        let mut out = Exposition::default();
        out.family("x_total", "counter", "An x.");
        out.sample(
            "x_total",
            &[("a", "pl\"ain\\\n".to_owned()), ("b", "2".to_owned())],
            3,
        );
        out.single("y", "gauge", "A y.", 1.5);
        assert_eq!(
            out.finish(),
            "# HELP x_total An x.\n# TYPE x_total counter\nx_total{a=\"pl\\\"ain\\\\\\n\",b=\"2\"} 3\n\
             # HELP y A y.\n# TYPE y gauge\ny 1.5\n"
        );
    }
}
