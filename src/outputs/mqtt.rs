//! MQTT (`[[outputs.mqtt]]`): the service publishes to a broker, with topics below
//! `topic_prefix`:
//!
//! * `{prefix}/targets/{target}/compensation`: each new result's compensation, the JSON of
//!   `GET /api/v1/targets/{name}/compensation`, retained (a subscriber that connects later gets
//!   the newest at once), at most `rate_hz` a second per target (the newest wins, encoded,
//!   its status and age judged, when it is sent: results that a newer one replaces before
//!   their turn cost nothing);
//! * `{prefix}/targets/{target}/alarm`: each alarm transition and each acknowledgement, the
//!   JSON of `GET /api/v1/alarms`, in order, retained;
//! * `{prefix}/links/{link}/state` and `{prefix}/cameras/{camera}/state`: a link's or camera's
//!   state when it changes, retained;
//! * `{prefix}/status`: `{"state":"online",...}` on every connection (retained), and the last
//!   will `{"state":"offline"}` the broker publishes when the service goes away; a clean stop
//!   publishes `offline` itself.
//!
//! A broker that goes away is connected to again with back-off (1 s doubling to 4 s, so that one that returns is served within about 5 s). While it
//! is away the newest message per topic is kept, and alarm transitions in a queue of
//! [`super::ALARM_QUEUE`]; on its return everything kept is published again. Publishing never
//! waits on ingest and ingest never waits on it.

use super::{Counters, Inbox, Ordered, Update, lock};
use crate::bank::TargetEstimate;
use crate::config::MqttSpec;
use crate::deformation::ReferenceVersion;
use crate::model::TargetId;
use crate::service::Service;
use bytes::Bytes;
use rumqttc::{AsyncClient, Event, LastWill, MqttOptions, Packet, QoS, Transport};
use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::Duration;
use tokio::sync::Notify;
use tokio::time::Instant;

/// The longest wait between two connection attempts: a broker that returns is published to
/// within about this.
const MAX_BACKOFF: Duration = Duration::from_secs(4);

/// The system's certificate authorities (Debian's bundle), used for `mqtts://` without
/// `ca_file`.
const SYSTEM_CA_BUNDLE: &str = "/etc/ssl/certs/ca-certificates.crt";

/// What a retained topic publishes.
enum Payload {
    /// Ready to send.
    Encoded(Bytes),
    /// A target's result with its reference, encoded when it is sent.
    Result(TargetId, Arc<(TargetEstimate, Option<ReferenceVersion>)>),
}

/// The newest message of a retained topic.
struct Latest {
    payload: Payload,
    /// Not yet published (or to publish again on a new connection).
    dirty: bool,
    /// When it was last published, for the rate per target.
    last_sent: Option<Instant>,
    /// The least time between two publications.
    interval: Duration,
}

/// What waits to be published.
struct Pending {
    /// Topic (below the prefix) to its newest message.
    latest: BTreeMap<String, Latest>,
    /// Alarm transitions, in order: topic below the prefix, payload.
    alarms: Ordered<(String, Bytes)>,
}

/// The inbox of one broker.
struct MqttInbox {
    pending: std::sync::Mutex<Pending>,
    wake: Notify,
    counters: Arc<Counters>,
    /// The least time between two compensations of a target.
    interval: Duration,
    /// Target names, by index.
    targets: Vec<String>,
    /// The compensation's JSON, as the API answers it.
    encode: Arc<super::CompensationEncoder>,
}

impl MqttInbox {
    fn queued(&self, p: &Pending) {
        let n = p.latest.values().filter(|l| l.dirty).count() + p.alarms.items.len();
        self.counters.queued.store(n as u64, Relaxed);
    }

    fn set_latest(&self, topic: String, payload: Payload, interval: Duration) {
        let mut p = lock(&self.pending);
        let entry = p.latest.entry(topic).or_insert(Latest {
            payload: Payload::Encoded(Bytes::new()),
            dirty: false,
            last_sent: None,
            interval,
        });
        entry.payload = payload;
        entry.dirty = true;
        self.queued(&p);
        drop(p);
        self.wake.notify_one();
    }
}

impl Inbox for MqttInbox {
    fn counters(&self) -> &Counters {
        &self.counters
    }

    fn put(&self, update: &Update) {
        match update {
            Update::Compensation { target, result } => {
                let Some(name) = self.targets.get(target.0) else {
                    return;
                };
                self.set_latest(
                    format!("targets/{name}/compensation"),
                    Payload::Result(*target, Arc::clone(result)),
                    self.interval,
                );
            }
            Update::State { topic, json } => {
                self.set_latest(
                    topic.clone(),
                    Payload::Encoded(json.clone()),
                    Duration::ZERO,
                );
            }
            Update::Alarm { alarm, json } => {
                let Some(name) = self.targets.get(alarm.target.0) else {
                    return;
                };
                let mut p = lock(&self.pending);
                if p.alarms
                    .push((format!("targets/{name}/alarm"), json.clone()))
                {
                    self.counters.dropped.fetch_add(1, Relaxed);
                }
                self.queued(&p);
                drop(p);
                self.wake.notify_one();
            }
        }
    }
}

/// The TLS transport of `spec`: its `ca_file`, or the system's authorities.
fn transport(spec: &MqttSpec) -> Result<Transport, String> {
    let path = spec
        .ca_file
        .clone()
        .unwrap_or_else(|| SYSTEM_CA_BUNDLE.into());
    let ca = std::fs::read(&path).map_err(|e| {
        format!(
            "the certificate authorities for mqtts:// cannot be read from {}: {e}",
            path.display()
        )
    })?;
    Ok(Transport::tls_with_config(
        rumqttc::TlsConfiguration::Simple {
            ca,
            alpn: None,
            client_auth: None,
        },
    ))
}

/// The JSON of the service's own state on the status topic.
fn status_payload(state: &str, now_ns: i64) -> Bytes {
    Bytes::from(
        serde_json::json!({
            "state": state,
            "version": env!("CARGO_PKG_VERSION"),
            "time": crate::clock::format_ns(now_ns),
        })
        .to_string(),
    )
}

/// Starts the output of one broker: its inbox and its task.
pub(super) fn spawn(
    service: &Service,
    spec: MqttSpec,
    encode: Arc<super::CompensationEncoder>,
    counters: Arc<Counters>,
) -> Result<(Arc<dyn Inbox>, tokio::task::JoinHandle<()>), String> {
    let mut options = MqttOptions::new(spec.client_id.clone(), spec.host.clone(), spec.port);
    options.set_keep_alive(Duration::from_secs(10));
    options.set_clean_session(true);
    let qos = if spec.qos == 0 {
        QoS::AtMostOnce
    } else {
        QoS::AtLeastOnce
    };
    options.set_last_will(LastWill::new(
        format!("{}/status", spec.topic_prefix),
        status_payload("offline", service.now_ns()).to_vec(),
        qos,
        true,
    ));
    if let Some((user, password)) = &spec.credentials {
        options.set_credentials(user.clone(), password.clone());
    }
    if spec.tls {
        options.set_transport(transport(&spec)?);
    }
    let inbox = Arc::new(MqttInbox {
        pending: std::sync::Mutex::new(Pending {
            latest: BTreeMap::new(),
            alarms: Ordered::new(),
        }),
        wake: Notify::new(),
        counters: Arc::clone(&counters),
        interval: Duration::from_secs_f64(1.0 / spec.rate_hz),
        targets: (service.installation().model.targets)
            .iter()
            .map(|t| t.name.clone())
            .collect(),
        encode,
    });
    let task = service.spawn_watched(
        "mqtt output",
        run(
            service.clone(),
            spec,
            options,
            qos,
            Arc::clone(&inbox),
            counters,
        ),
    );
    Ok((inbox, task))
}

/// Keeps the connection to the broker and publishes what waits, until shutdown.
async fn run(
    service: Service,
    spec: MqttSpec,
    options: MqttOptions,
    qos: QoS,
    inbox: Arc<MqttInbox>,
    counters: Arc<Counters>,
) {
    let (client, mut events) = AsyncClient::new(options, 256);
    let mut stop = service.stopping();
    let mut connected = false;
    let mut backoff = Duration::from_secs(1);
    let address = spec.address();
    let prefix = spec.topic_prefix.clone();
    let mut retry_at: Option<Instant> = None;
    loop {
        if let Some(at) = retry_at.take() {
            tokio::select! {
                _ = stop.wait_for(|s| *s) => break,
                _ = tokio::time::sleep_until(at) => {}
            }
        }
        let due = if connected { next_due(&inbox) } else { None };
        tokio::select! {
            _ = stop.wait_for(|s| *s) => break,
            polled = events.poll() => match polled {
                Ok(Event::Incoming(Packet::ConnAck(_))) => {
                    connected = true;
                    counters.set_connected(true);
                    backoff = Duration::from_secs(1);
                    tracing::info!(broker = %address, "MQTT output connected");
                    // Everything kept goes again: the broker may have lost its retained messages.
                    let mut p = lock(&inbox.pending);
                    for l in p.latest.values_mut() {
                        l.dirty = true;
                        l.last_sent = None;
                    }
                    drop(p);
                    let _ = client.try_publish(
                        format!("{prefix}/status"),
                        qos,
                        true,
                        status_payload("online", service.now_ns()).to_vec(),
                    );
                }
                Ok(_) => {}
                Err(e) => {
                    if connected {
                        tracing::warn!(broker = %address, error = %e, "MQTT output disconnected; connecting again");
                    }
                    connected = false;
                    counters.set_connected(false);
                    counters.error(service.now_ns(), format!("broker {address}: {e}"));
                    retry_at = Some(Instant::now() + backoff);
                    backoff = (backoff * 2).min(MAX_BACKOFF);
                }
            },
            _ = inbox.wake.notified(), if connected => {}
            _ = tokio::time::sleep_until(due.unwrap_or_else(Instant::now)), if due.is_some() => {}
        }
        if connected {
            publish_due(&client, &prefix, qos, &inbox, &counters, service.now_ns());
        }
    }
    // A clean stop says so itself, rather than leaving it to the will.
    if connected {
        let _ = client.try_publish(
            format!("{prefix}/status"),
            qos,
            true,
            status_payload("offline", service.now_ns()).to_vec(),
        );
        let _ = client.try_disconnect();
        let _ = tokio::time::timeout(Duration::from_secs(2), async {
            while events.poll().await.is_ok() {}
        })
        .await;
    }
    counters.set_connected(false);
}

/// When the next kept message held back by its rate may go.
fn next_due(inbox: &MqttInbox) -> Option<Instant> {
    let p = lock(&inbox.pending);
    p.latest
        .values()
        .filter(|l| l.dirty)
        .filter_map(|l| l.last_sent.map(|t| t + l.interval))
        .min()
}

/// Hands the client what may go now: alarm transitions first, in order, then the newest
/// message of each topic whose rate allows it. What the client's queue cannot take stays.
fn publish_due(
    client: &AsyncClient,
    prefix: &str,
    qos: QoS,
    inbox: &MqttInbox,
    counters: &Counters,
    now_ns: i64,
) {
    let now = Instant::now();
    let mut p = lock(&inbox.pending);
    let mut sent = 0;
    while let Some((topic, payload)) = p.alarms.items.front() {
        if client
            .try_publish(format!("{prefix}/{topic}"), qos, true, payload.to_vec())
            .is_err()
        {
            break;
        }
        p.alarms.items.pop_front();
        sent += 1;
    }
    for (topic, l) in &mut p.latest {
        if !l.dirty || l.last_sent.is_some_and(|t| now < t + l.interval) {
            continue;
        }
        let payload = match &l.payload {
            Payload::Encoded(bytes) => bytes.to_vec(),
            Payload::Result(target, result) => {
                match (inbox.encode)(*target, &result.0, result.1.as_ref()) {
                    Ok(json) => json,
                    Err(e) => {
                        tracing::error!(error = %e, "a compensation cannot be encoded for MQTT");
                        l.dirty = false;
                        continue;
                    }
                }
            }
        };
        if client
            .try_publish(format!("{prefix}/{topic}"), qos, true, payload)
            .is_err()
        {
            break;
        }
        l.dirty = false;
        l.last_sent = Some(now);
        sent += 1;
    }
    inbox.queued(&p);
    drop(p);
    if sent > 0 {
        counters.sent(sent, now_ns);
    }
}
