//! Alarm notifications by webhook (`[[notify.webhooks]]`): the service's outward side.
//!
//! Every stored alarm transition whose higher level (before or after) reaches a webhook's
//! `min_level` is POSTed to its URL as JSON, exactly the alarm as `GET /api/v1/alarms` shows it
//! (the HTTP adapter hands its encoder to [`Webhooks::start`], so the two cannot differ),
//! with the header `X-Brokenray-Signature: sha256=<hex HMAC-SHA256 of the body with the
//! secret>` (and `X-Brokenray-Alarm-Id`). Each webhook has its own queue and task, so a slow or
//! dead receiver delays only itself, in order; ingest never waits (the service hands
//! transitions over without blocking, see [`crate::service::Service::take_alarm_feed`]).
//!
//! A delivery is retried with exponential back-off (1 s, 2 s, 4 s, ... at most 60 s) on a
//! network error, a timeout, a 5xx, a 408 or a 429, up to `max_attempts`; other 4xx answers
//! say the receiver refuses it, and are not retried. What fails is logged, counted in
//! `/metrics` (`brokenray_webhook_*`) and shown by `GET /api/v1/webhooks`.

use crate::config::{NotifyLevel, WebhookSpec};
use crate::service::Service;
use crate::store::StoredAlarm;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::mpsc;

/// Deliveries waiting per webhook before new ones are dropped (counted).
const QUEUE_CAPACITY: usize = 1000;

/// The longest wait between two attempts.
const MAX_BACKOFF: Duration = Duration::from_secs(60);

/// The signature header's value for `body`: `sha256=` and the lowercase hex HMAC-SHA256.
pub fn signature(secret: &str, body: &[u8]) -> String {
    use hmac::Mac as _;
    // HMAC takes a key of any length: this cannot fail.
    let Ok(mut mac) = hmac::Hmac::<sha2::Sha256>::new_from_slice(secret.as_bytes()) else {
        return String::new();
    };
    mac.update(body);
    format!("sha256={}", hex::encode(mac.finalize().into_bytes()))
}

/// True when a transition concerns a webhook of `min_level`.
fn concerns(min_level: NotifyLevel, alarm: &StoredAlarm) -> bool {
    use crate::alarms::Level;
    let top = alarm.transition.from.max(alarm.transition.to);
    match min_level {
        NotifyLevel::Warn => top >= Level::Warn,
        NotifyLevel::Alarm => top >= Level::Alarm,
    }
}

/// What happened to one webhook's deliveries.
#[derive(Debug, Default)]
struct Counters {
    delivered: AtomicU64,
    failed: AtomicU64,
    dropped: AtomicU64,
    attempts_failed: AtomicU64,
    queued: AtomicU64,
    /// The newest attempt failed.
    failing: std::sync::atomic::AtomicBool,
    last_delivered_ns: AtomicI64,
    last_error: LastError,
}

impl Counters {
    fn error(&self, now_ns: i64, message: String) {
        self.last_error.set(now_ns, message);
    }

    fn last_error(&self) -> Option<(i64, String)> {
        self.last_error.get()
    }
}

/// The last error of something that delivers (a webhook, an output) and when it happened (ns,
/// server clock), shared by its task and the readers of its status.
#[derive(Debug, Default)]
pub struct LastError(Mutex<Option<(i64, String)>>);

impl LastError {
    /// Records `message` at `now_ns`.
    pub fn set(&self, now_ns: i64, message: String) {
        // A panic elsewhere cannot leave the value half written: take it from a poisoned lock.
        *self
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = Some((now_ns, message));
    }

    /// The last error and when, if any.
    pub fn get(&self) -> Option<(i64, String)> {
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }
}

struct Hook {
    spec: WebhookSpec,
    counters: Counters,
}

/// Makes a notification's body from the target's name and the transition.
pub type Encoder = fn(&str, &StoredAlarm) -> serde_json::Result<Vec<u8>>;

/// The configured webhooks and their delivery tasks.
#[derive(Clone, Default)]
pub struct Webhooks {
    hooks: Arc<Vec<Hook>>,
    tasks: Arc<Mutex<Vec<tokio::task::JoinHandle<()>>>>,
}

impl Webhooks {
    /// Starts delivering the service's alarm transitions to the configured webhooks (none
    /// configured: nothing runs), each transition's body made by `encode` from the target's name
    /// and the transition. The tasks end when the service's pipeline has stopped and every
    /// queued delivery is done or given up.
    pub fn start(service: &Service, encode: Encoder) -> Self {
        let specs = &service.installation().notify.webhooks;
        let Some(mut feed) = service.take_alarm_feed() else {
            return Self::default();
        };
        let hooks: Arc<Vec<Hook>> = Arc::new(
            specs
                .iter()
                .map(|spec| Hook {
                    spec: spec.clone(),
                    counters: Counters::default(),
                })
                .collect(),
        );
        // Redirects are never followed: one could send an alarm (signed) to any host, this
        // service's own admin API among them, and be counted as delivered.
        let client = match reqwest::Client::builder()
            .user_agent(concat!("brokenray/", env!("CARGO_PKG_VERSION")))
            .redirect(reqwest::redirect::Policy::none())
            .build()
        {
            Ok(c) => c,
            Err(e) => {
                tracing::error!(error = %e, "cannot build the webhook client; no alarm will be sent");
                return Self::default();
            }
        };
        let mut queues = Vec::new();
        let mut tasks = Vec::new();
        for i in 0..hooks.len() {
            let (tx, rx) = mpsc::channel::<Arc<Delivery>>(QUEUE_CAPACITY);
            queues.push(tx);
            tasks.push(service.spawn_watched(
                "webhook delivery",
                deliver_all(Arc::clone(&hooks), i, rx, client.clone(), service.clock()),
            ));
        }
        let names: Vec<String> = service.installation().model.target_names();
        let dispatch_hooks = Arc::clone(&hooks);
        let clock = service.clock();
        tasks.push(service.spawn_watched("webhook dispatch", async move {
            while let Some(alarm) = feed.recv().await {
                let Some(name) = names.get(alarm.target.0) else {
                    continue;
                };
                let body = match encode(name, &alarm) {
                    Ok(b) => b,
                    Err(e) => {
                        tracing::error!(alarm = alarm.id, error = %e, "an alarm cannot be encoded for the webhooks");
                        continue;
                    }
                };
                let delivery = Arc::new(Delivery { id: alarm.id, body });
                for (hook, queue) in dispatch_hooks.iter().zip(&queues) {
                    if !concerns(hook.spec.min_level, &alarm) {
                        continue;
                    }
                    if queue.try_send(Arc::clone(&delivery)).is_ok() {
                        hook.counters.queued.fetch_add(1, Relaxed);
                    } else {
                        hook.counters.dropped.fetch_add(1, Relaxed);
                        hook.counters.error(
                            clock.now_ns(),
                            format!("queue full: alarm {} not sent", alarm.id),
                        );
                        tracing::error!(webhook = hook.spec.host(), alarm = alarm.id, "the webhook's queue is full; the alarm will not be sent to it");
                    }
                }
            }
            // The queues close here: each webhook finishes what it holds.
        }));
        Self {
            hooks,
            tasks: Arc::new(Mutex::new(tasks)),
        }
    }

    /// Waits, at most `limit`, for every queued delivery to be made or given up (call after
    /// the pipeline has stopped); says how many were left undelivered.
    pub async fn finish(&self, limit: Duration) {
        let tasks: Vec<_> = match self.tasks.lock() {
            Ok(mut g) => g.drain(..).collect(),
            Err(p) => p.into_inner().drain(..).collect(),
        };
        if tasks.is_empty() {
            return;
        }
        let all = futures::future::join_all(tasks);
        if tokio::time::timeout(limit, all).await.is_err() {
            for h in self.hooks.iter() {
                let left = h.counters.queued.load(Relaxed);
                if left > 0 {
                    tracing::error!(
                        webhook = h.spec.host(),
                        undelivered = left,
                        "stopping with alarm notifications not delivered"
                    );
                }
            }
        }
    }

    /// Each webhook's deliveries and failures, in file order.
    pub fn status(&self) -> Vec<WebhookStatus> {
        self.hooks
            .iter()
            .enumerate()
            .map(|(i, h)| {
                let c = &h.counters;
                let last_delivered = c.last_delivered_ns.load(Relaxed);
                let last_error = c.last_error();
                WebhookStatus {
                    index: i,
                    host: h.spec.host().to_owned(),
                    min_level: h.spec.min_level,
                    delivered: c.delivered.load(Relaxed),
                    failed: c.failed.load(Relaxed),
                    dropped: c.dropped.load(Relaxed),
                    attempts_failed: c.attempts_failed.load(Relaxed),
                    queued: c.queued.load(Relaxed),
                    last_delivered_ns: (last_delivered > 0).then_some(last_delivered),
                    failing: c.failing.load(Relaxed),
                    last_error,
                }
            })
            .collect()
    }
}

/// One alarm's notification: the body is the same for every webhook.
struct Delivery {
    id: i64,
    body: Vec<u8>,
}

/// Why an attempt failed, and whether another may succeed.
struct Failure {
    message: String,
    retry: bool,
}

async fn attempt(
    client: &reqwest::Client,
    spec: &WebhookSpec,
    d: &Delivery,
) -> Result<(), Failure> {
    let response = client
        .post(&spec.url)
        .timeout(Duration::from_secs_f64(spec.timeout_s))
        .header(reqwest::header::CONTENT_TYPE, "application/json")
        .header("X-Brokenray-Signature", signature(&spec.secret, &d.body))
        .header("X-Brokenray-Alarm-Id", d.id.to_string())
        .body(d.body.clone())
        .send()
        .await
        .map_err(|e| Failure {
            // Without the URL, which may carry a token.
            message: e.without_url().to_string(),
            retry: true,
        })?;
    let status = response.status();
    if status.is_success() {
        return Ok(());
    }
    if status.is_redirection() {
        let to = response
            .headers()
            .get(reqwest::header::LOCATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| url::Url::parse(v).ok())
            .and_then(|u| u.host_str().map(str::to_owned))
            .unwrap_or_else(|| "elsewhere".to_owned());
        return Err(Failure {
            message: format!(
                "answered {status}, a redirect to {to}: redirects are not followed (configure the \
                 final URL)"
            ),
            retry: false,
        });
    }
    Err(Failure {
        message: format!("answered {status}"),
        retry: status.is_server_error()
            || status == reqwest::StatusCode::REQUEST_TIMEOUT
            || status == reqwest::StatusCode::TOO_MANY_REQUESTS,
    })
}

/// Delivers webhook `i`'s queue in order, each with its retries.
async fn deliver_all(
    hooks: Arc<Vec<Hook>>,
    i: usize,
    mut rx: mpsc::Receiver<Arc<Delivery>>,
    client: reqwest::Client,
    clock: crate::clock::SharedClock,
) {
    let hook = &hooks[i];
    let spec = &hook.spec;
    let c = &hook.counters;
    while let Some(d) = rx.recv().await {
        let mut wait = Duration::from_secs(1);
        for n in 1..=spec.max_attempts {
            match attempt(&client, spec, &d).await {
                Ok(()) => {
                    c.failing.store(false, Relaxed);
                    c.delivered.fetch_add(1, Relaxed);
                    c.last_delivered_ns.store(clock.now_ns(), Relaxed);
                    break;
                }
                Err(f) => {
                    c.failing.store(true, Relaxed);
                    c.attempts_failed.fetch_add(1, Relaxed);
                    c.error(clock.now_ns(), f.message.clone());
                    if !f.retry || n == spec.max_attempts {
                        c.failed.fetch_add(1, Relaxed);
                        tracing::error!(webhook = spec.host(), alarm = d.id, attempts = n, error = %f.message, "an alarm notification was not delivered");
                        break;
                    }
                    tracing::warn!(webhook = spec.host(), alarm = d.id, attempt = n, error = %f.message, retry_in_s = wait.as_secs(), "an alarm notification failed; retrying");
                    tokio::time::sleep(wait).await;
                    wait = (wait * 2).min(MAX_BACKOFF);
                }
            }
        }
        c.queued.fetch_sub(1, Relaxed);
    }
}

/// One webhook's deliveries and failures.
#[derive(Debug, Clone, PartialEq)]
pub struct WebhookStatus {
    /// Its position in `[[notify.webhooks]]`.
    pub index: usize,
    /// The URL's host and port (the rest may carry credentials).
    pub host: String,
    /// The lowest level it is told about.
    pub min_level: NotifyLevel,
    /// Notifications delivered.
    pub delivered: u64,
    /// Notifications given up after `max_attempts`, or refused by the receiver (4xx).
    pub failed: u64,
    /// Notifications dropped because the queue was full.
    pub dropped: u64,
    /// Attempts that failed (retried or given up).
    pub attempts_failed: u64,
    /// Notifications waiting or being retried.
    pub queued: u64,
    /// The last delivery (server clock, ns).
    pub last_delivered_ns: Option<i64>,
    /// The newest attempt failed.
    pub failing: bool,
    /// The last failed attempt: when (server clock, ns) and its error.
    pub last_error: Option<(i64, String)>,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// RFC 4231, test case 2: key "Jefe".
    #[test]
    fn the_signature_is_the_hmac_sha256_of_the_body() {
        assert_eq!(
            signature("Jefe", b"what do ya want for nothing?"),
            "sha256=5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
    }
}
