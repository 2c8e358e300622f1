//! The plant's buses (`[[outputs.mqtt]]`, `[[outputs.modbus]]`, `[[outputs.nmea]]`): each
//! target's compensation and every alarm transition, published where a device that must apply
//! the correction, or a ship's alarm panel and voyage data recorder, already listens.
//!
//! One task (the dispatcher) holds the one subscription to the service's live events (the
//! results and alarm transitions the event stream carries) and hands each to every output's own
//! bounded inbox; it also reads each link's and camera's state once a second and passes on what
//! changed. An output that cannot deliver keeps the newest state per topic and a bounded queue
//! of alarm transitions (the oldest dropped, counted): the store is the history, not the
//! outputs. Nothing here is on ingest's path; a slow or absent receiver delays only its output.
//!
//! * [`mqtt`]: publishes JSON to a broker, compensations retained, with a last will.
//! * [`modbus`]: a read-only register map, computed at each read from the live state, so a read
//!   equals `GET /api/v1/targets/{name}/compensation` at that moment.
//! * [`nmea`]: `XDR` transducer sentences at a set rate and `ALR` alarm sentences, by UDP.
//!
//! Each output's state (connected, sent, dropped, its last error) is in
//! [`Outputs::status`], which `/healthz`, `/metrics`, `GET /api/v1/outputs` and the dashboard
//! show.

pub mod modbus;
pub mod mqtt;
pub mod nmea;

use crate::acquire::SourceState;
use crate::alarms::Level;
use crate::bank::{TargetEstimate, TargetStatus};
use crate::deformation::ReferenceVersion;
use crate::deformation::SmallMotion;
use crate::model::TargetId;
use crate::service::{LiveEvent, Service};
use crate::store::StoredAlarm;
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU32, AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Alarm transitions an output keeps while it cannot deliver them; older ones are dropped,
/// counted.
pub const ALARM_QUEUE: usize = 1000;

crate::words! {
    /// What kind of bus an output is.
    pub enum OutputKind("output kind") {
        /// An MQTT broker.
        Mqtt = "mqtt",
        /// A Modbus/TCP server.
        Modbus = "modbus",
        /// NMEA 0183 sentences by UDP.
        Nmea = "nmea",
    }
}

/// Why the outputs cannot start.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    /// A Modbus server cannot listen where the installation says.
    #[error("outputs.modbus[{index}].listen: cannot listen on {addr}: {source}")]
    Listen {
        /// Which `[[outputs.modbus]]`.
        index: usize,
        /// The address.
        addr: std::net::SocketAddr,
        /// Why.
        source: std::io::Error,
    },
    /// A UDP socket for NMEA cannot be opened.
    #[error("outputs.nmea[{index}].to: cannot open a UDP socket to {addr}: {source}")]
    Socket {
        /// Which `[[outputs.nmea]]`.
        index: usize,
        /// The receiver's address.
        addr: std::net::SocketAddr,
        /// Why.
        source: std::io::Error,
    },
    /// The TLS settings of a broker cannot be used.
    #[error("outputs.mqtt[{index}]: {message}")]
    Tls {
        /// Which `[[outputs.mqtt]]`.
        index: usize,
        /// What is wrong.
        message: String,
    },
}

/// The counters of one output, shared by its task and the readers of its status.
#[derive(Debug, Default)]
pub struct Counters {
    connected: AtomicBool,
    sent: AtomicU64,
    dropped: AtomicU64,
    queued: AtomicU64,
    clients: AtomicU64,
    last_sent_ns: AtomicI64,
    last_error: crate::notify::LastError,
}

impl Counters {
    fn set_connected(&self, connected: bool) {
        self.connected.store(connected, Relaxed);
    }

    fn sent(&self, n: u64, now_ns: i64) {
        self.sent.fetch_add(n, Relaxed);
        self.last_sent_ns.store(now_ns, Relaxed);
    }

    fn error(&self, now_ns: i64, message: String) {
        self.last_error.set(now_ns, message);
    }
}

/// What one output did, as `/healthz`, `/metrics` and `GET /api/v1/outputs` show it.
#[derive(Debug, Clone, PartialEq)]
pub struct OutputStatus {
    /// Its kind.
    pub kind: OutputKind,
    /// Where: the broker, the address listened on, the receiver.
    pub address: String,
    /// MQTT: connected to the broker. Modbus: listening. NMEA: the last send succeeded.
    pub connected: bool,
    /// Messages published, register reads answered, or sentences sent.
    pub sent: u64,
    /// Alarm transitions dropped because the output was away for longer than its queue holds,
    /// plus live events missed when the outputs fell behind them.
    pub dropped: u64,
    /// Messages waiting to be delivered.
    pub queued: u64,
    /// Modbus: clients connected now.
    pub clients: Option<u64>,
    /// When something was last sent (ns, server clock).
    pub last_sent_ns: Option<i64>,
    /// The last error and when (ns, server clock).
    pub last_error: Option<(i64, String)>,
}

/// A running output: its kind, address and counters.
#[derive(Debug)]
struct Running {
    kind: OutputKind,
    address: String,
    counters: Arc<Counters>,
}

/// Encodes a live result of a target with the reference in force.
pub type CompensationEncoder = dyn Fn(TargetId, &TargetEstimate, Option<&ReferenceVersion>) -> serde_json::Result<Vec<u8>>
    + Send
    + Sync;

/// How the HTTP adapter encodes what it also answers, so that an output's JSON and the API's
/// cannot differ (see [`crate::notify`] for the same rule with webhooks).
#[derive(Clone)]
pub struct Encoders {
    /// A live result as `GET /api/v1/targets/{name}/compensation` answers it.
    pub compensation: Arc<CompensationEncoder>,
    /// An alarm transition as `GET /api/v1/alarms` answers it, given its target's name.
    pub alarm: fn(&str, &StoredAlarm) -> serde_json::Result<Vec<u8>>,
}

/// A target's figures as the outputs carry them, computed from the live state the way the
/// API's live compensation is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TargetFigures {
    /// The newest result's time (ns).
    pub time_ns: i64,
    /// Its status judged now (`stale` when a link stopped).
    pub status: TargetStatus,
    /// Seconds from its time to now.
    pub age_s: f64,
    /// The alarm level in force (with its hysteresis and dwell).
    pub alarm: Level,
    /// The deformation against the reference, when one is set.
    pub deformation: Option<SmallMotion>,
    /// The correction (the deformation's inverse), when a reference is set.
    pub correction: Option<SmallMotion>,
}

impl TargetFigures {
    /// Target `ti` now; `None` before its first result.
    pub fn live(service: &Service, ti: TargetId) -> Option<TargetFigures> {
        let snapshot = service.snapshot();
        let view = snapshot.targets.get(ti.0)?;
        let latest = view.latest.as_ref()?;
        let now = snapshot.judge(
            ti,
            Some(latest),
            service.now_ns(),
            service.installation().server.clock_tolerance_s,
        );
        let d = match (&latest.target_from_base, &view.reference) {
            (Some(e), Some(r)) => Some(crate::deformation::Deformation::new(&r.reference, e)),
            _ => None,
        };
        Some(TargetFigures {
            time_ns: latest.time_ns,
            status: now.status,
            age_s: now.age_s.unwrap_or(0.0),
            alarm: view.alarms.level(),
            deformation: d.map(|d| d.deformation()),
            correction: d.map(|d| d.correction()),
        })
    }
}

/// What the dispatcher hands every output.
#[derive(Debug, Clone)]
enum Update {
    /// A target's new result with the reference in force: encoded by an output only when it
    /// sends it (an MQTT output at most `rate_hz` a second, however many results arrive).
    Compensation {
        target: TargetId,
        result: Arc<(TargetEstimate, Option<ReferenceVersion>)>,
    },
    /// An alarm transition or its acknowledgement, with its JSON (empty without an MQTT output).
    Alarm {
        alarm: Arc<StoredAlarm>,
        json: bytes::Bytes,
    },
    /// A link's or camera's state changed (topic below the prefix, JSON).
    State { topic: String, json: bytes::Bytes },
}

/// The outputs of a service: the dispatcher and one task per output.
#[derive(Debug, Default)]
pub struct Outputs {
    running: Vec<Running>,
    tasks: Mutex<Vec<tokio::task::JoinHandle<()>>>,
}

/// What the Modbus map reads besides the live state: counters the dispatcher keeps.
#[derive(Debug)]
pub struct Heartbeats {
    /// Seconds the outputs have run (incremented every second).
    pub service: AtomicU32,
    /// Per target, results published since the start.
    pub targets: Vec<AtomicU32>,
}

impl Outputs {
    /// Starts every output of the installation: binds the Modbus servers and opens the UDP
    /// sockets (what fails is refused here, naming the key), then spawns the dispatcher and
    /// the outputs' tasks, which end when the service begins to shut down.
    pub async fn start(
        service: &Service,
        sources: Arc<[Arc<SourceState>]>,
        encoders: Encoders,
    ) -> Result<Outputs, OutputError> {
        let settings = &service.installation().outputs;
        if settings.is_empty() {
            return Ok(Outputs::default());
        }
        let n_targets = service.installation().model.targets.len();
        let heartbeats = Arc::new(Heartbeats {
            service: AtomicU32::new(0),
            targets: (0..n_targets).map(|_| AtomicU32::new(0)).collect(),
        });
        let mut running = Vec::new();
        let mut tasks = Vec::new();
        let mut inboxes: Vec<Arc<dyn Inbox>> = Vec::new();
        for (index, spec) in settings.modbus.iter().enumerate() {
            let listener = tokio::net::TcpListener::bind(spec.listen)
                .await
                .map_err(|source| OutputError::Listen {
                    index,
                    addr: spec.listen,
                    source,
                })?;
            let counters = Arc::new(Counters::default());
            let address = listener
                .local_addr()
                .map_or_else(|_| spec.listen.to_string(), |a| a.to_string());
            tasks.push(modbus::spawn(
                service.clone(),
                listener,
                Arc::clone(&heartbeats),
                Arc::clone(&counters),
            ));
            running.push(Running {
                kind: OutputKind::Modbus,
                address,
                counters,
            });
        }
        for (index, spec) in settings.nmea.iter().enumerate() {
            let counters = Arc::new(Counters::default());
            let (inbox, task) = nmea::spawn(service.clone(), spec.clone(), Arc::clone(&counters))
                .map_err(|source| OutputError::Socket {
                index,
                addr: spec.to,
                source,
            })?;
            inboxes.push(inbox);
            tasks.push(task);
            running.push(Running {
                kind: OutputKind::Nmea,
                address: spec.to.to_string(),
                counters,
            });
        }
        for (index, spec) in settings.mqtt.iter().enumerate() {
            let counters = Arc::new(Counters::default());
            let (inbox, task) = mqtt::spawn(
                service,
                spec.clone(),
                Arc::clone(&encoders.compensation),
                Arc::clone(&counters),
            )
            .map_err(|message| OutputError::Tls { index, message })?;
            inboxes.push(inbox);
            tasks.push(task);
            running.push(Running {
                kind: OutputKind::Mqtt,
                address: spec.address(),
                counters,
            });
        }
        tasks.push(service.spawn_watched(
            "outputs",
            dispatch(
                service.clone(),
                sources,
                encoders,
                inboxes,
                heartbeats,
                !settings.mqtt.is_empty(),
            ),
        ));
        Ok(Outputs {
            running,
            tasks: Mutex::new(tasks),
        })
    }

    /// Every output's state: the Modbus servers, the NMEA receivers, then the MQTT brokers, each
    /// kind in file order.
    pub fn status(&self) -> Vec<OutputStatus> {
        self.running
            .iter()
            .map(|r| {
                let c = &r.counters;
                let last_sent_ns = c.last_sent_ns.load(Relaxed);
                OutputStatus {
                    kind: r.kind,
                    address: r.address.clone(),
                    connected: c.connected.load(Relaxed),
                    sent: c.sent.load(Relaxed),
                    dropped: c.dropped.load(Relaxed),
                    queued: c.queued.load(Relaxed),
                    clients: (r.kind == OutputKind::Modbus).then(|| c.clients.load(Relaxed)),
                    last_sent_ns: (last_sent_ns != 0).then_some(last_sent_ns),
                    last_error: c.last_error.get(),
                }
            })
            .collect()
    }

    /// Waits, up to `grace`, for the outputs' tasks to end once shutdown has begun (an MQTT
    /// output says `offline` on its status topic before it disconnects).
    pub async fn finish(&self, grace: Duration) {
        let tasks = match self.tasks.lock() {
            Ok(mut g) => std::mem::take(&mut *g),
            Err(p) => std::mem::take(&mut *p.into_inner()),
        };
        let all = futures::future::join_all(tasks);
        let _ = tokio::time::timeout(grace, all).await;
    }
}

/// An output's inbox: what the dispatcher hands it, never waiting.
trait Inbox: Send + Sync {
    fn put(&self, update: &Update);

    /// The counters of its output.
    fn counters(&self) -> &Counters;
}

/// The one subscriber: turns live events into updates for every inbox, and once a second
/// counts the heartbeat and, when an MQTT output takes them (`json`), passes on the links' and
/// cameras' states that changed. Alarms are encoded as JSON only for MQTT too.
async fn dispatch(
    service: Service,
    sources: Arc<[Arc<SourceState>]>,
    encoders: Encoders,
    inboxes: Vec<Arc<dyn Inbox>>,
    heartbeats: Arc<Heartbeats>,
    json: bool,
) {
    use tokio::sync::broadcast::error::RecvError;
    let mut events = service.subscribe();
    let mut stop = service.stopping();
    let mut tick = tokio::time::interval(Duration::from_secs(1));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut states: std::collections::HashMap<String, String> = Default::default();
    let send = |update: Update| {
        for inbox in &inboxes {
            inbox.put(&update);
        }
    };
    let names: Vec<String> = (service.installation().model.targets)
        .iter()
        .map(|t| t.name.clone())
        .collect();
    loop {
        tokio::select! {
            _ = stop.wait_for(|s| *s) => return,
            _ = tick.tick() => {
                heartbeats.service.fetch_add(1, Relaxed);
                if json {
                    for (topic, json) in changed_states(&service, &sources, &mut states) {
                        send(Update::State { topic, json });
                    }
                }
            }
            received = events.recv() => match received {
                Ok(LiveEvent::Result { target, estimate, reference }) => {
                    if let Some(h) = heartbeats.targets.get(target.0) {
                        h.fetch_add(1, Relaxed);
                    }
                    send(Update::Compensation { target, result: Arc::new((estimate, reference)) });
                }
                Ok(LiveEvent::Alarm(alarm) | LiveEvent::Acknowledged(alarm)) => {
                    let name = names.get(alarm.target.0).map_or("", String::as_str);
                    let encoded = if json { (encoders.alarm)(name, &alarm) } else { Ok(Vec::new()) };
                    match encoded {
                        Ok(json) => send(Update::Alarm { alarm: Arc::new(alarm), json: json.into() }),
                        Err(e) => tracing::error!(error = %e, "an alarm cannot be encoded for the outputs"),
                    }
                }
                Err(RecvError::Lagged(n)) => {
                    // Results are replaced by the next one; an alarm transition among them is
                    // lost to the outputs (the store and the webhooks have it): said and counted.
                    tracing::error!(missed = n, "the outputs fell behind the live events; alarm transitions among them were not sent");
                    let now_ns = service.now_ns();
                    for inbox in &inboxes {
                        let c = inbox.counters();
                        c.dropped.fetch_add(n, Relaxed);
                        c.error(now_ns, format!("fell {n} live events behind; alarm transitions among them were not sent"));
                    }
                }
                Err(RecvError::Closed) => return,
            },
        }
    }
}

/// The links' and cameras' states that differ from `seen` (which is updated), as topics below
/// the prefix with their JSON.
fn changed_states(
    service: &Service,
    sources: &[Arc<SourceState>],
    seen: &mut std::collections::HashMap<String, String>,
) -> Vec<(String, bytes::Bytes)> {
    use crate::words::Word as _;
    let installation = service.installation();
    let snapshot = service.snapshot();
    let now_ns = service.now_ns();
    let time = crate::clock::format_ns(now_ns);
    let mut out = Vec::new();
    let mut note = |topic: String, state: &'static str, body: serde_json::Value| {
        if seen.get(&topic).map(String::as_str) != Some(state) {
            seen.insert(topic.clone(), state.to_owned());
            out.push((topic, bytes::Bytes::from(body.to_string())));
        }
    };
    for (i, link) in installation.model.links.iter().enumerate() {
        let state = snapshot
            .link_state(
                crate::chain::LinkId(i),
                now_ns,
                installation.server.clock_tolerance_s,
            )
            .word();
        note(
            format!("links/{}/state", link.name),
            state,
            serde_json::json!({"link": link.name, "state": state, "time": time}),
        );
    }
    for source in sources {
        let report = source.report();
        let status = report.detail.status.word();
        note(
            format!("cameras/{}/state", report.camera),
            status,
            serde_json::json!({
                "camera": report.camera,
                "status": status,
                "last_error": report.detail.last_error.as_ref().map(|(m, _)| m),
                "time": time,
            }),
        );
    }
    out
}

/// A bounded queue of what must arrive in order: the oldest dropped (counted) when full.
#[derive(Debug)]
struct Ordered<T> {
    items: std::collections::VecDeque<T>,
}

impl<T> Ordered<T> {
    fn new() -> Self {
        Ordered {
            items: std::collections::VecDeque::new(),
        }
    }

    /// Adds `item`; true when the oldest had to be dropped for it.
    fn push(&mut self, item: T) -> bool {
        let full = self.items.len() >= ALARM_QUEUE;
        if full {
            self.items.pop_front();
        }
        self.items.push_back(item);
        full
    }
}

/// Locks `m`, taking the value of a poisoned lock (a panic elsewhere leaves it consistent:
/// every writer of these finishes its change before anything can panic).
fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}
