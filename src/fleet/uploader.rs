//! The site's uploader: one task that pushes the outbox to the centre, tier by tier.
//!
//! Each round it looks at the tiers in order (events, results, raw) and sends the first batch
//! waiting, so a burst of alarms never waits behind a day of results. Raw batches go only when
//! `raw_kbit_s` allows: after one of `n` bytes, the next waits `8 n / raw_kbit_s` ms. A batch
//! the centre acknowledges is recorded in the site's database (through the writer, like every
//! write) before the next of its tier is read; until then a restart sends it again, which the
//! centre answers as a duplicate. Failures of the link or the centre (no answer, 5xx, 408, 429)
//! are retried with back-off from 1 s to 60 s; a refusal (401, 403, 404, 409, 422) stops
//! that tier's stream, says so in `GET /api/v1/upstream`, the health check and the log, and
//! never skips data: after the operator fixes the cause, a restart resumes where it stopped.
//! So does an acknowledgement past the site's newest commit, or of a commit the site made at
//! another time than the centre was told (either way the centre has commits of this outbox
//! generation that the file does not: it was replaced by an older copy of itself), which is
//! never recorded.
//!
//! A batch is bounded by rows (`batch_rows`) and by bytes: `batch_mb` of JSON, and what the
//! centre says it reads of one upload, both in bytes and in values. The rows a batch may take
//! follow the bytes a row took in the tier's last batch; a batch encoded over the bound is read
//! again smaller before it is sent, and a 413 is answered by a batch half as large. A commit
//! larger than a batch goes in parts, which the centre applies without acknowledging the
//! commit until its last part (a restart sends the commit again from its first part).

use super::protocol::{
    Outcome, RawRequest, RequestedRows, SiteStatus, SyncRequest, SyncResponse, TargetStatus,
    TierBacklog, UploadLimits, ZSTD_LEVEL,
};
use crate::config::{SiteName, UpstreamSettings};
use crate::service::Service;
use crate::store::outbox::{PartCursor, Tier};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// The longest wait between retries.
const MAX_BACKOFF: Duration = Duration::from_secs(60);

/// Measurement time a slice of a requested period covers (ns): a minute, about 6000 rows of
/// one target and three links at 25 Hz.
const REQUEST_SLICE_NS: i64 = 60_000_000_000;

/// Bytes a row is counted for in the backlog's estimate before any of its tier was sent.
const DEFAULT_BYTES_PER_ROW: f64 = 100.0;

/// One tier's progress.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TierProgress {
    /// The last commit the centre acknowledged (`None`: nothing yet).
    pub acked_seq: Option<i64>,
    /// Rows still to send (counted at start, then again at most every heartbeat and no more
    /// often than a hundred times as long as a count takes; in between, less what was
    /// acknowledged; `None` until first counted).
    pub backlog_rows: Option<u64>,
    /// Batches, rows, compressed and uncompressed bytes sent and acknowledged since start.
    pub batches_sent: u64,
    /// Rows acknowledged since start.
    pub rows_sent: u64,
    /// Compressed bytes of acknowledged batches since start (the events tier also counts the
    /// reports of state sent alone).
    pub bytes_sent: u64,
    /// The same batches' bytes before compression.
    pub json_bytes_sent: u64,
    /// When the centre last acknowledged a batch (server clock, ns).
    pub last_success_ns: Option<i64>,
    /// The last failure: when (ns) and what.
    pub last_error: Option<(i64, String)>,
    /// Failures since start.
    pub errors: u64,
    /// Why the stream stopped (a refusal), if it did.
    pub stopped: Option<String>,
    /// Raw tier only: rows sent for periods the centre asked for.
    pub requested_rows_sent: u64,
    /// Raw tier only: rows of the periods the centre asked for still to send (counted with
    /// the backlog).
    pub requested_rows: Option<u64>,
}

impl TierProgress {
    /// The backlog's size on the wire, estimated from the compressed bytes per row sent so far.
    pub fn backlog_bytes(&self) -> Option<u64> {
        let per_row = if self.rows_sent > 0 {
            self.bytes_sent as f64 / self.rows_sent as f64
        } else {
            DEFAULT_BYTES_PER_ROW
        };
        self.backlog_rows
            .map(|rows| (rows as f64 * per_row).round() as u64)
    }
}

/// The uploader's shared state: its settings and each tier's progress.
#[derive(Debug)]
pub struct Upstream {
    /// The site.
    pub site: SiteName,
    /// Where and how it pushes.
    pub settings: UpstreamSettings,
    tiers: Mutex<[TierProgress; 3]>,
    /// When the centre last answered anything (server clock, ns).
    last_contact_ns: Mutex<Option<i64>>,
    /// The periods of raw rows the centre asked for and has not all of, as it last said.
    raw_requests: Mutex<Vec<RawRequest>>,
}

fn index(tier: Tier) -> usize {
    match tier {
        Tier::Events => 0,
        Tier::Results => 1,
        Tier::Raw => 2,
    }
}

impl Upstream {
    /// The state of a site that pushes with `settings`.
    pub fn new(site: SiteName, settings: UpstreamSettings) -> Upstream {
        Upstream {
            site,
            settings,
            tiers: Mutex::new(Default::default()),
            last_contact_ns: Mutex::new(None),
            raw_requests: Mutex::new(Vec::new()),
        }
    }

    /// The periods of raw rows the centre asked for and has not all of yet, the oldest first.
    pub fn raw_requests(&self) -> Vec<RawRequest> {
        self.raw_requests
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// Each tier's progress, most urgent first.
    pub fn progress(&self) -> Vec<(Tier, TierProgress)> {
        let tiers = self.tiers.lock().unwrap_or_else(|p| p.into_inner());
        Tier::ALL
            .iter()
            .map(|&t| (t, tiers[index(t)].clone()))
            .collect()
    }

    /// When the centre last answered.
    pub fn last_contact_ns(&self) -> Option<i64> {
        *self
            .last_contact_ns
            .lock()
            .unwrap_or_else(|p| p.into_inner())
    }

    /// What is wrong with the uploads, for the health check: a stopped stream.
    pub fn problem(&self) -> Option<String> {
        self.progress().into_iter().find_map(|(t, p)| {
            p.stopped
                .map(|why| format!("the upload of the {} tier stopped: {why}", t.name()))
        })
    }

    fn update(&self, tier: Tier, f: impl FnOnce(&mut TierProgress)) {
        let mut tiers = self.tiers.lock().unwrap_or_else(|p| p.into_inner());
        f(&mut tiers[index(tier)]);
    }

    fn contact(&self, now_ns: i64) {
        *self
            .last_contact_ns
            .lock()
            .unwrap_or_else(|p| p.into_inner()) = Some(now_ns);
    }
}

/// Why an upload failed.
enum Failure {
    /// Worth retrying: the link or the centre is down or busy.
    Transient(String),
    /// Larger than the centre reads (413): worth sending again smaller.
    TooLarge(String),
    /// The centre refused it: retrying the same would fail the same way.
    Refused(String),
}

/// An upload encoded for the wire.
struct Encoded {
    /// The zstd-compressed JSON.
    body: Vec<u8>,
    /// The JSON's bytes.
    json_bytes: u64,
    /// Its values, counted as the centre counts them.
    values: u64,
}

/// Encodes and compresses an upload on a blocking thread (a batch is megabytes: never on the
/// async workers).
async fn encode(request: SyncRequest) -> Result<Encoded, String> {
    tokio::task::spawn_blocking(move || {
        let json =
            serde_json::to_vec(&request).map_err(|e| format!("cannot encode the upload: {e}"))?;
        let body = zstd::bulk::compress(&json, ZSTD_LEVEL)
            .map_err(|e| format!("cannot compress the upload: {e}"))?;
        Ok(Encoded {
            body,
            json_bytes: json.len() as u64,
            values: super::protocol::json_values(&json),
        })
    })
    .await
    .map_err(|e| format!("the upload's encoder failed: {e}"))?
}

/// Rows a batch of a tier starts with, before its own rows were measured: a filtered result
/// with its reference is about 1.6 KB of JSON, a sample about 300 bytes.
fn first_bytes_per_row(tier: Tier) -> f64 {
    match tier {
        Tier::Events => 1000.0,
        Tier::Results => 2000.0,
        Tier::Raw => 400.0,
    }
}

/// What bounds a tier's batches: the JSON bytes and values its rows took in its last batch,
/// and the bytes it may take (halved after a 413).
#[derive(Debug, Clone, Copy)]
struct Sizing {
    bytes_per_row: f64,
    values_per_row: f64,
    /// Bytes of JSON a batch may take (`None`: the settings' and the centre's bounds alone).
    shrunk_to: Option<u64>,
}

impl Sizing {
    fn new(tier: Tier) -> Sizing {
        Sizing {
            bytes_per_row: first_bytes_per_row(tier),
            values_per_row: 40.0,
            shrunk_to: None,
        }
    }

    /// The JSON bytes and values one upload may take: the settings' bytes, nine tenths of what
    /// the centre reads (room for the report of state beside the rows), a bound after a 413.
    fn bounds(&self, settings_bytes: usize, limits: Option<UploadLimits>) -> (u64, u64) {
        let mut bytes = settings_bytes as u64;
        let mut values = u64::MAX;
        if let Some(l) = limits {
            bytes = bytes.min(l.json_bytes / 10 * 9);
            values = l.values / 10 * 9;
        }
        if let Some(shrunk) = self.shrunk_to {
            bytes = bytes.min(shrunk);
        }
        (bytes, values)
    }

    /// Rows the next batch may take.
    fn rows(
        &self,
        batch_rows: usize,
        settings_bytes: usize,
        limits: Option<UploadLimits>,
    ) -> usize {
        let (bytes, values) = self.bounds(settings_bytes, limits);
        let by_bytes = bytes as f64 / self.bytes_per_row;
        let by_values = values as f64 / self.values_per_row;
        (by_bytes.min(by_values).floor() as usize).clamp(1, batch_rows.max(1))
    }

    /// Learns from an encoded batch of `rows` rows (with a tenth to spare).
    fn learn(&mut self, rows: usize, encoded: &Encoded) {
        if rows == 0 {
            return;
        }
        self.bytes_per_row = (encoded.json_bytes as f64 / rows as f64 * 1.1).max(50.0);
        self.values_per_row = (encoded.values as f64 / rows as f64 * 1.1).max(2.0);
    }
}

/// The site's current state, from the service's snapshot.
/// `described` is the installation's description of its targets, made once per run (the
/// installation does not change while the service runs).
fn site_status(service: &Service, described: &[super::protocol::TargetDescription]) -> SiteStatus {
    let snapshot = service.snapshot();
    let now_ns = service.now_ns();
    let inst = service.installation();
    SiteStatus {
        time: crate::clock::format_ns(now_ns),
        targets: inst
            .model
            .targets
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let now = snapshot.target_now(
                    crate::model::TargetId(i),
                    now_ns,
                    inst.server.clock_tolerance_s,
                );
                let view = &snapshot.targets[i];
                TargetStatus {
                    name: t.name.clone(),
                    status: now.status.into(),
                    alarm: view.alarms.level().into(),
                    time: view
                        .latest
                        .as_ref()
                        .map(|l| crate::clock::format_ns(l.time_ns)),
                }
            })
            .collect(),
        described: described.to_vec(),
        problems: service.storage_problem().into_iter().collect(),
    }
}

/// The uploader's connection to the centre.
struct Link {
    client: reqwest::Client,
    url: url::Url,
    token: Option<String>,
}

impl Link {
    fn new(upstream: &Upstream) -> Result<Link, String> {
        let mut base = upstream.settings.url.clone();
        if !base.path().ends_with('/') {
            base.set_path(&format!("{}/", base.path()));
        }
        let url = base
            .join(&format!("api/v1/sites/{}/sync", upstream.site))
            .map_err(|e| format!("the centre's URL does not take a path: {e}"))?;
        let client = reqwest::Client::builder()
            .connect_timeout(Duration::from_secs(10))
            .timeout(Duration::from_secs(300))
            .build()
            .map_err(|e| format!("cannot make an HTTP client: {e}"))?;
        Ok(Link {
            client,
            url,
            token: upstream.settings.token.clone(),
        })
    }

    /// Posts one encoded upload; returns the answer.
    async fn send(&self, body: Vec<u8>) -> Result<SyncResponse, Failure> {
        let mut post = self
            .client
            .post(self.url.clone())
            .header(reqwest::header::CONTENT_TYPE, "application/json")
            .header(reqwest::header::CONTENT_ENCODING, "zstd")
            .body(body);
        if let Some(token) = &self.token {
            post = post.bearer_auth(token);
        }
        let response = post.send().await.map_err(|e| {
            Failure::Transient(format!("the centre cannot be reached: {}", e.without_url()))
        })?;
        let status = response.status();
        let text = response
            .text()
            .await
            .map_err(|e| Failure::Transient(format!("the answer was cut: {e}")))?;
        if status.is_success() {
            return serde_json::from_str(&text).map_err(|e| {
                Failure::Transient(format!("the centre's answer does not parse: {e}"))
            });
        }
        let message = serde_json::from_str::<serde_json::Value>(&text)
            .ok()
            .and_then(|v| v["error"]["message"].as_str().map(str::to_owned))
            .unwrap_or_else(|| text.chars().take(300).collect());
        let what = format!("the centre answered {status}: {message}");
        if status.is_server_error() || matches!(status.as_u16(), 408 | 429) {
            Err(Failure::Transient(what))
        } else if status == reqwest::StatusCode::PAYLOAD_TOO_LARGE {
            Err(Failure::TooLarge(what))
        } else {
            Err(Failure::Refused(what))
        }
    }
}

/// Sleeps for `d`, or less when the service begins to stop; true when it does.
async fn pause(stopping: &mut tokio::sync::watch::Receiver<bool>, d: Duration) -> bool {
    if *stopping.borrow() {
        return true;
    }
    tokio::select! {
        () = tokio::time::sleep(d) => *stopping.borrow(),
        _ = stopping.changed() => true,
    }
}

/// Counts each tier's backlog and the acknowledged numbers from the database, and the rows of
/// the periods the centre asked for still to send.
async fn refresh_backlog(service: &Service, upstream: &Upstream) -> Option<Vec<TierBacklog>> {
    let mut requested = 0u64;
    for r in upstream.raw_requests() {
        match service
            .store()
            .count_raw_in(r.delivered_to_ns, r.to_ns)
            .await
        {
            Ok(n) => requested += n,
            Err(e) => tracing::warn!(error = %e, "cannot count the rows the centre asked for"),
        }
    }
    upstream.update(Tier::Raw, |p| p.requested_rows = Some(requested));
    match service.store().backlog().await {
        Ok(backlog) => Some(
            backlog
                .into_iter()
                .map(|(tier, b)| {
                    upstream.update(tier, |p| {
                        p.backlog_rows = Some(b.rows);
                        p.acked_seq = p.acked_seq.max(b.acked_seq);
                    });
                    TierBacklog {
                        tier,
                        rows: b.rows,
                        acked_seq: b.acked_seq,
                        requested_rows: (tier == Tier::Raw).then_some(requested),
                    }
                })
                .collect(),
        ),
        Err(e) => {
            tracing::warn!(error = %e, "cannot count the upload backlog");
            None
        }
    }
}

/// Each tier's backlog as the uploader now knows it: the last count, less what the centre has
/// acknowledged since (zero once nothing waits).
fn backlog_now(upstream: &Upstream) -> Vec<TierBacklog> {
    upstream
        .progress()
        .into_iter()
        .filter_map(|(tier, p)| {
            Some(TierBacklog {
                tier,
                rows: p.backlog_rows?,
                acked_seq: p.acked_seq,
                requested_rows: p.requested_rows,
            })
        })
        .collect()
}

/// Whether to count the backlog again: at most every heartbeat, and no more often than a
/// hundred times as long as the last count took, so that counting a backlog of days (every
/// row above the acknowledged number) takes at most about 1 % of a core. In between, the
/// figures follow the acknowledgements.
fn count_due(last: Option<(Instant, Duration)>, heartbeat: Duration) -> bool {
    last.is_none_or(|(at, took)| at.elapsed() >= heartbeat.max(took * 100))
}

/// A tier's place in its stream: the last commit the centre acknowledged, where the next
/// part of a commit larger than a batch starts, and what bounds its batches.
struct Stream {
    after: Option<i64>,
    part: Option<PartCursor>,
    sizing: Sizing,
}

/// The next batch of a tier's stream (a part of a commit where one is under way) and where
/// the part after it starts, if one waits; an empty tier's backlog is zero now, and a failure
/// to read is counted and logged.
async fn read_batch(
    service: &Service,
    upstream: &Upstream,
    tier: Tier,
    stream: &Stream,
    limit: usize,
) -> Option<(crate::store::outbox::OutboxBatch, Option<PartCursor>)> {
    match service
        .store()
        .outbox_batch(tier, stream.after, limit, stream.part.as_ref())
        .await
    {
        Ok(Some(batch)) => Some(batch),
        // Nothing waits: the tier's backlog is empty now, whatever the last count.
        Ok(None) => {
            upstream.update(tier, |p| p.backlog_rows = Some(0));
            None
        }
        Err(e) => {
            tracing::warn!(error = %e, tier = tier.name(), "cannot read the outbox");
            upstream.update(tier, |p| {
                p.last_error = Some((service.now_ns(), e.to_string()));
                p.errors += 1;
            });
            None
        }
    }
}

/// The next slice of a period the centre asked for: `slice_ns` of rows from where it was
/// delivered to; a stretch without any is passed in the same slice (a period of months with
/// an hour of rows is a few uploads). Its end and its rows.
async fn requested_slice(
    store: &crate::store::Store,
    r: &RawRequest,
    slice_ns: i64,
) -> crate::store::StoreResult<(i64, Vec<crate::store::outbox::TableRows>)> {
    let to_ns = match store.next_raw_time(r.delivered_to_ns, r.to_ns).await? {
        None => r.to_ns,
        Some(t) => r
            .to_ns
            .min(t.max(r.delivered_to_ns).saturating_add(slice_ns)),
    };
    Ok((to_ns, store.raw_rows_in(r.delivered_to_ns, to_ns).await?))
}

/// Stops a tier's stream (or every stream, for a report of state alone) and says why; true
/// when that is news (a stream that was not stopped for this reason already), so that a site
/// whose reports keep being refused logs it once, not every heartbeat.
fn stop(upstream: &Upstream, tier: Option<Tier>, now_ns: i64, why: &str) -> bool {
    let stopped: Vec<Tier> = match tier {
        Some(t) => vec![t],
        None => Tier::ALL.to_vec(),
    };
    let mut news = false;
    for t in stopped {
        upstream.update(t, |p| {
            news |= p.stopped.as_deref() != Some(why);
            p.last_error = Some((now_ns, why.to_owned()));
            p.errors += 1;
            p.stopped = Some(why.to_owned());
        });
    }
    news
}

/// What was sent: the batch's bounds, or a slice of a period asked for.
#[derive(Debug, Clone)]
struct Sent {
    upto_seq: i64,
    partial: bool,
    rest: Option<PartCursor>,
}

/// Runs the uploader until the service begins to stop.
pub async fn run(service: Service, upstream: Arc<Upstream>) {
    let mut stopping = service.stopping();
    let link = match Link::new(&upstream) {
        Ok(link) => link,
        Err(e) => {
            for &tier in Tier::ALL {
                upstream.update(tier, |p| p.stopped = Some(e.clone()));
            }
            tracing::error!(error = %e, "the uploader cannot start");
            return;
        }
    };
    let store = service.store().clone();
    let identity = loop {
        match store.outbox_identity().await {
            Ok(id) => break id,
            Err(e) => {
                tracing::warn!(error = %e, "the uploader cannot read the outbox; retrying");
                if pause(&mut stopping, Duration::from_secs(5)).await {
                    return;
                }
            }
        }
    };
    let settings = upstream.settings.clone();
    let described = super::protocol::describe_targets(&service.installation().model);
    let heartbeat = Duration::from_secs_f64(settings.heartbeat_s);
    let counted_at = Instant::now();
    let backlog = refresh_backlog(&service, &upstream)
        .await
        .unwrap_or_default();
    let mut last_count = Some((counted_at, counted_at.elapsed()));
    let mut streams = [Tier::Events, Tier::Results, Tier::Raw].map(|tier| Stream {
        after: None,
        part: None,
        sizing: Sizing::new(tier),
    });
    for b in &backlog {
        streams[index(b.tier)].after = b.acked_seq;
    }
    // What the centre reads of one upload, once it has said.
    let mut limits: Option<UploadLimits> = None;
    // The span of a slice of a period asked for (halved while one is too large).
    let mut slice_ns = REQUEST_SLICE_NS;
    let mut backoff = Duration::from_secs(1);
    let mut raw_allowed_at = Instant::now();
    // Whether the raw stream goes before the next slice of a period asked for.
    let mut stream_turn = false;
    let mut last_report: Option<Instant> = None;
    tracing::info!(site = %upstream.site, centre = %crate::config::redacted_url(&link.url), "uploading to the centre");
    while !*stopping.borrow() {
        let report_due = last_report.is_none_or(|t| t.elapsed() >= heartbeat);
        if report_due && count_due(last_count, heartbeat) {
            let at = Instant::now();
            refresh_backlog(&service, &upstream).await;
            last_count = Some((at, at.elapsed()));
        }
        // The first tier with a batch waiting and a stream that runs; before the raw stream,
        // a slice of a period the centre asked for.
        let mut next = None;
        let mut requested = None;
        let progress = upstream.progress();
        for &tier in Tier::ALL {
            let i = index(tier);
            if progress[i].1.stopped.is_some() {
                continue;
            }
            let limit = streams[i]
                .sizing
                .rows(settings.batch_rows, settings.batch_bytes, limits);
            if tier != Tier::Raw {
                next = read_batch(&service, &upstream, tier, &streams[i], limit).await;
                if next.is_some() {
                    break;
                }
                continue;
            }
            let stream_allowed = settings.raw_kbit_s > 0.0 && Instant::now() >= raw_allowed_at;
            let mut stream_read = false;
            // The raw stream and the periods asked for take turns, so neither starves.
            if stream_turn && stream_allowed {
                stream_turn = false;
                stream_read = true;
                next = read_batch(&service, &upstream, tier, &streams[i], limit).await;
                if next.is_some() {
                    break;
                }
            }
            if let Some(r) = upstream.raw_requests().first().copied() {
                match requested_slice(&store, &r, slice_ns).await {
                    Ok((to_ns, tables)) => {
                        stream_turn = true;
                        requested = Some(RequestedRows {
                            request_id: r.id,
                            from_ns: r.delivered_to_ns,
                            to_ns,
                            // Without a raw stream these are the only copies the centre gets:
                            // the newest versions replace what it has.
                            replace: settings.raw_kbit_s <= 0.0,
                            tables,
                        });
                        break;
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "cannot read the raw rows the centre asked for");
                        upstream.update(tier, |p| {
                            p.last_error = Some((service.now_ns(), e.to_string()));
                            p.errors += 1;
                        });
                    }
                }
            }
            if stream_allowed && !stream_read {
                next = read_batch(&service, &upstream, tier, &streams[i], limit).await;
            }
        }
        if next.is_none() && requested.is_none() && !report_due {
            if pause(&mut stopping, Duration::from_millis(500)).await {
                break;
            }
            continue;
        }
        let registry = match store.registry().await {
            Ok(r) => r,
            Err(e) => {
                tracing::warn!(error = %e, "cannot read the outbox's registry");
                if pause(&mut stopping, backoff).await {
                    break;
                }
                continue;
            }
        };
        let slice = requested.as_ref().map(|r| {
            (
                r.tables.iter().map(|t| t.rows() as u64).sum::<u64>(),
                r.to_ns - r.from_ns,
            )
        });
        // A requested slice's failures are the raw tier's.
        let tier = next
            .as_ref()
            .map(|(b, _)| b.tier)
            .or(requested.as_ref().map(|_| Tier::Raw));
        let rows = next.as_ref().map_or(0, |(b, _)| b.rows() as u64);
        let sent = next.as_ref().map(|(b, rest)| Sent {
            upto_seq: b.upto_seq,
            partial: b.partial,
            rest: rest.clone(),
        });
        // Read after the batch: at or past its last commit.
        let head_seq = match store.outbox_head().await {
            Ok(head) => head,
            Err(e) => {
                tracing::warn!(error = %e, "cannot read the outbox's newest commit");
                if pause(&mut stopping, backoff).await {
                    break;
                }
                continue;
            }
        };
        let request = SyncRequest {
            outbox_id: identity.outbox_id.clone(),
            generation: Some(identity.generation.clone()),
            lineage: identity.lineage.clone(),
            head_seq: Some(head_seq),
            registry,
            batch: next.map(|(b, _)| b.into()),
            status: Some(site_status(&service, &described)),
            backlog: backlog_now(&upstream),
            requested,
        };
        let encoded = match encode(request).await {
            Ok(encoded) => encoded,
            Err(why) => {
                tracing::error!(error = %why, "an upload cannot be encoded; its stream stops");
                let _ = stop(&upstream, tier, service.now_ns(), &why);
                continue;
            }
        };
        // Over what may be sent: read again smaller, before anything is sent.
        if let Some(t) = tier {
            let sizing = &mut streams[index(t)].sizing;
            let (max_bytes, max_values) = sizing.bounds(settings.batch_bytes, limits);
            let over = encoded.json_bytes > max_bytes || encoded.values > max_values;
            if let Some((slice_rows, span_ns)) = slice {
                if over && slice_rows > 1 && span_ns > 1 {
                    slice_ns = (span_ns / 2).max(1);
                    continue;
                }
            } else if over && rows > 1 {
                let before = sizing.rows(settings.batch_rows, settings.batch_bytes, limits);
                sizing.learn(rows as usize, &encoded);
                if sizing.rows(settings.batch_rows, settings.batch_bytes, limits) >= before {
                    sizing.bytes_per_row *= 2.0;
                }
                continue;
            }
            if over {
                let why = format!(
                    "one row of the {} tier takes {} bytes of JSON ({} values), more than \
                     an upload may take ({max_bytes} bytes, {max_values} values: `[upstream] \
                     batch_mb` and the centre's `[central] max_sync_mb`)",
                    t.name(),
                    encoded.json_bytes,
                    encoded.values
                );
                tracing::error!(tier = t.name(), "{why}");
                let _ = stop(&upstream, tier, service.now_ns(), &why);
                continue;
            }
            if slice.is_none() {
                sizing.learn(rows as usize, &encoded);
            }
        }
        let (bytes, json_bytes) = (encoded.body.len() as u64, encoded.json_bytes);
        match link.send(encoded.body).await {
            Ok(answer) => {
                let now = service.now_ns();
                upstream.contact(now);
                backoff = Duration::from_secs(1);
                last_report = Some(Instant::now());
                limits = answer.limits.or(limits);
                *upstream
                    .raw_requests
                    .lock()
                    .unwrap_or_else(|p| p.into_inner()) = answer.raw_requests.clone();
                if let Some((slice_rows, span_ns)) = slice {
                    // The centre's list says how far each request now is.
                    upstream.update(Tier::Raw, |p| {
                        p.bytes_sent += bytes;
                        p.json_bytes_sent += json_bytes;
                        p.requested_rows_sent += slice_rows;
                    });
                    if span_ns >= slice_ns {
                        slice_ns = (slice_ns * 2).min(REQUEST_SLICE_NS);
                    }
                    continue;
                }
                let (Some(tier), Some(sent)) = (tier, sent) else {
                    // A report of state alone: counted with the events tier's bytes.
                    upstream.update(Tier::Events, |p| {
                        p.bytes_sent += bytes;
                        p.json_bytes_sent += json_bytes;
                    });
                    continue;
                };
                let i = index(tier);
                // A bound a 413 set loosens again with every batch taken.
                let sizing = &mut streams[i].sizing;
                sizing.shrunk_to = sizing
                    .shrunk_to
                    .map(|b| b.saturating_mul(5) / 4)
                    .filter(|&b| b < settings.batch_bytes as u64);
                if let Some(acked) = answer.acked_seq
                    && acked > head_seq
                {
                    // Recording it would mark commits this file has not made yet as received:
                    // the rows they will hold would never be sent.
                    let why = format!(
                        "the centre acknowledges commit {acked} of this tier, but this site's \
                         newest commit is {head_seq}: its database is older than what the centre \
                         received (restored from a copy that did not start an outbox generation \
                         of its own?); stop the service, run `brokenray new-generation` on the \
                         database, and start it again"
                    );
                    tracing::error!(tier = tier.name(), acked, head_seq, "{why}");
                    let _ = stop(&upstream, Some(tier), now, &why);
                    continue;
                }
                match answer.outcome {
                    Outcome::Applied | Outcome::Duplicate => {
                        // An acknowledgement of another commit than the one sent: the centre
                        // must have had it from this database, made when this database made it.
                        if let (Some(acked), Some(stamp)) =
                            (answer.acked_seq, answer.acked_stamp_ns)
                            && acked != sent.upto_seq
                        {
                            match store.commit_stamp(acked).await {
                                Ok(Some(own)) if own != stamp => {
                                    let why = format!(
                                        "the centre acknowledges commit {acked} of this tier as \
                                         made at {}, but this site made its commit {acked} at {}: \
                                         its database was replaced by an older copy that did not \
                                         start an outbox generation of its own, and the centre \
                                         holds another life's commits under these numbers; stop \
                                         the service, run `brokenray new-generation` on the \
                                         database, and start it again",
                                        crate::clock::format_ns(stamp),
                                        crate::clock::format_ns(own)
                                    );
                                    tracing::error!(tier = tier.name(), acked, "{why}");
                                    let _ = stop(&upstream, Some(tier), now, &why);
                                    continue;
                                }
                                // Its record is gone (pruned with old rows): nothing to tell.
                                Ok(_) => {}
                                Err(e) => {
                                    tracing::warn!(error = %e, "cannot read a commit's stamp; retrying");
                                    if pause(&mut stopping, backoff).await {
                                        break;
                                    }
                                    continue;
                                }
                            }
                        }
                        let stream = &mut streams[i];
                        stream.part = if answer.outcome == Outcome::Applied && sent.partial {
                            sent.rest.clone()
                        } else {
                            None
                        };
                        if let Some(acked) = answer.acked_seq {
                            if let Err(e) = service.record_upstream_ack(tier, acked).await {
                                // The centre has it: a restart sends it again as a duplicate.
                                tracing::warn!(error = %e, "cannot record the centre's acknowledgement");
                            }
                            stream.after = Some(acked);
                        }
                        upstream.update(tier, |p| {
                            p.acked_seq = answer.acked_seq.or(p.acked_seq);
                            p.batches_sent += 1;
                            p.rows_sent += rows;
                            p.bytes_sent += bytes;
                            p.json_bytes_sent += json_bytes;
                            p.backlog_rows = p.backlog_rows.map(|b| b.saturating_sub(rows));
                            p.last_success_ns = Some(now);
                        });
                        if tier == Tier::Raw && settings.raw_kbit_s > 0.0 {
                            raw_allowed_at = Instant::now()
                                + Duration::from_secs_f64(
                                    bytes as f64 * 8.0 / (settings.raw_kbit_s * 1000.0),
                                );
                        }
                    }
                    Outcome::Gap => {
                        tracing::warn!(
                            tier = tier.name(),
                            resume_after = ?answer.acked_seq,
                            "the centre has less than this site recorded; resuming from its number"
                        );
                        streams[i].after = answer.acked_seq;
                        streams[i].part = None;
                    }
                }
            }
            Err(Failure::Transient(why)) => {
                if let Some(tier) = tier {
                    upstream.update(tier, |p| {
                        p.last_error = Some((service.now_ns(), why.clone()));
                        p.errors += 1;
                    });
                }
                tracing::warn!(error = %why, retry_in_s = backoff.as_secs(), "an upload failed; retrying");
                if pause(&mut stopping, backoff).await {
                    break;
                }
                backoff = (backoff * 2).min(MAX_BACKOFF);
            }
            Err(Failure::TooLarge(why))
                if tier.is_some() && (rows > 1 || slice.is_some_and(|(n, s)| n > 1 && s > 1)) =>
            {
                // Smaller, at once: the centre reads less than it said, or than was guessed.
                let t = tier.unwrap_or(Tier::Raw);
                tracing::warn!(error = %why, tier = t.name(), json_bytes, "an upload was too large for the centre; sending it in smaller batches");
                upstream.update(t, |p| {
                    p.last_error = Some((service.now_ns(), why.clone()));
                    p.errors += 1;
                });
                if let Some((_, span_ns)) = slice {
                    slice_ns = (span_ns / 2).max(1);
                } else {
                    let sizing = &mut streams[index(t)].sizing;
                    sizing.shrunk_to = Some((json_bytes / 2).max(1));
                }
            }
            Err(Failure::Refused(why) | Failure::TooLarge(why)) => {
                // A report of state alone refused: the refusal is about the site (its token,
                // its outbox), so every stream stops.
                if stop(&upstream, tier, service.now_ns(), &why) {
                    tracing::error!(error = %why, tier = ?tier.map(Tier::name), "the centre refused an upload; its stream stops until the service restarts");
                } else {
                    tracing::debug!(error = %why, "the centre refused a report of state again");
                }
                last_report = Some(Instant::now());
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn encoded(json_bytes: u64, values: u64) -> Encoded {
        Encoded {
            body: Vec::new(),
            json_bytes,
            values,
        }
    }

    #[test]
    fn a_batch_takes_the_rows_its_bytes_and_values_allow() {
        let mut sizing = Sizing::new(Tier::Results);
        // 4 MB at 2000 bytes a row before anything was measured.
        assert_eq!(sizing.rows(20_000, 4_000_000, None), 2000);
        // The rows' limit is the smaller.
        assert_eq!(sizing.rows(500, 4_000_000, None), 500);
        // A batch of 1000 rows took 1.6 MB and 40 000 values: 1760 bytes and 44 values a row.
        sizing.learn(1000, &encoded(1_600_000, 40_000));
        assert_eq!(sizing.rows(20_000, 4_000_000, None), 2272);
        // A centre that reads 4 MB and 10 000 values: nine tenths of its values bound it.
        let by_values = UploadLimits {
            json_bytes: 4_000_000,
            values: 10_000,
        };
        assert_eq!(sizing.rows(20_000, 4_000_000, Some(by_values)), 9000 / 44);
        // One that reads 250 kB: nine tenths of its bytes.
        let limits = UploadLimits {
            json_bytes: 250_000,
            values: 10_000,
        };
        assert_eq!(sizing.rows(20_000, 4_000_000, Some(limits)), 225_000 / 1760);
        // After a 413 at 100 kB: half of it.
        sizing.shrunk_to = Some(50_000);
        assert_eq!(sizing.rows(20_000, 4_000_000, Some(limits)), 28);
        // Never less than one row.
        sizing.learn(1, &encoded(10_000_000, 10));
        assert_eq!(sizing.rows(20_000, 4_000_000, Some(limits)), 1);
    }

    #[test]
    fn the_backlog_is_counted_no_more_often_than_a_hundred_times_a_count() {
        let heartbeat = Duration::from_secs(10);
        let ago = |s: u64| Instant::now() - Duration::from_secs(s);
        assert!(count_due(None, heartbeat), "counted at start");
        // A quick count: every heartbeat.
        let quick = Duration::from_millis(5);
        assert!(!count_due(Some((ago(5), quick)), heartbeat));
        assert!(count_due(Some((ago(11), quick)), heartbeat));
        // A count that took 2 s (a backlog of days): not again before 200 s.
        let slow = Duration::from_secs(2);
        assert!(!count_due(Some((ago(11), slow)), heartbeat));
        assert!(!count_due(Some((ago(150), slow)), heartbeat));
        assert!(count_due(Some((ago(201), slow)), heartbeat));
    }
}
