//! NMEA 0183 / IEC 61162-1 by UDP (`[[outputs.nmea]]`): one datagram per sentence to a
//! receiver (a serial gateway, a voyage data recorder's network input, an alarm panel).
//!
//! * **`XDR`** (transducer measurements), `rate_hz` times a second per target, two sentences:
//!   the deformation's rotation vector (type `A`, angular displacement, in degrees `D`, names
//!   `{target}_RX`, `_RY`, `_RZ`) and its translation (type `D`, linear displacement, in metres
//!   `M`, names `{target}_TX`, `_TY`, `_TZ`), each to 7 decimals (0.00036 arc-second, 0.1 µm).
//!   Without a reference, or while the target's status is not `ok`, the values are empty (the
//!   standard's null field: not available), so a receiver never takes an old value for a
//!   current one.
//! * **`ALR`** (set alarm state), for every alarm transition and acknowledgement, in order, and
//!   again every 30 s while a target's alarm is active: `$--ALR,hhmmss.ss,nnn,c,a,text*hh`
//!   with the transition's UTC time, the alarm number (the target's index in the installation
//!   plus 1, three digits), the condition (`A` above a threshold, `V` back to normal), the
//!   acknowledgement (`A` acknowledged, `V` not) and the text `{target} DEFORMATION {LEVEL}`.
//!   `ALR` is the alarm sentence of IEC 61162-1 whose fields are public and which alarm panels
//!   and recorders without bridge alert management take; the newer `ALF`/`ALC`/`ACN` set belongs
//!   to bridge alert management (IEC 62923), which this output does not claim.
//!
//! Sentences are at most 82 characters with `$` and CR LF, as the standard requires; a long
//! target name is cut to fit. Fields never hold the reserved characters (`$ ! * , \ ^ ~`).

use super::{Counters, Inbox, Ordered, TargetFigures, Update, lock};
use crate::alarms::Level;
use crate::bank::TargetStatus;
use crate::config::NmeaSpec;
use crate::model::TargetId;
use crate::service::Service;
use crate::store::StoredAlarm;
use std::sync::Arc;
use std::sync::atomic::Ordering::Relaxed;
use std::time::Duration;
use tokio::sync::Notify;

/// The longest sentence: `$`, up to 79 characters, CR LF.
pub const MAX_SENTENCE: usize = 82;

/// How often an active alarm is said again.
const ALARM_REPEAT: Duration = Duration::from_secs(30);

/// The checksum: XOR of every byte between `$` and `*`.
pub fn checksum(body: &str) -> u8 {
    body.bytes().fold(0, |a, b| a ^ b)
}

/// `$body*hh\r\n`.
fn sentence(body: &str) -> String {
    format!("${body}*{:02X}\r\n", checksum(body))
}

/// `name` with what a field may not hold replaced by `_`, upper case.
fn field(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_ascii_graphic() && !"$!*,\\^~".contains(c) {
                c.to_ascii_uppercase()
            } else {
                '_'
            }
        })
        .collect()
}

/// A sentence of `talker` and `kind` with `fields`, the last field cut so that the whole stays
/// within [`MAX_SENTENCE`].
fn fitted(talker: &str, kind: &str, fields: &[String]) -> String {
    let mut body = format!("{talker}{kind},{}", fields.join(","));
    // `$`, `*hh`, CR LF: 6 characters around the body.
    let room = MAX_SENTENCE - 6;
    if body.len() > room {
        body.truncate(room);
    }
    sentence(&body)
}

/// The two `XDR` sentences of a target (rotation, translation); the values empty when
/// `figures` has no deformation or its status is not `ok`.
pub fn xdr(talker: &str, target: &str, figures: Option<&TargetFigures>) -> Vec<String> {
    let d = figures
        .filter(|f| f.status == TargetStatus::Ok)
        .and_then(|f| f.deformation);
    let name = field(target);
    let quads = |kind: &str, unit: &str, axes: [&str; 3], values: Option<[f64; 3]>| {
        let fields: Vec<[String; 4]> = axes
            .iter()
            .enumerate()
            .map(|(i, axis)| {
                [
                    kind.to_owned(),
                    values.map_or_else(String::new, |v| format!("{:.7}", v[i])),
                    unit.to_owned(),
                    format!("{name}_{axis}"),
                ]
            })
            .collect();
        fields
    };
    let rotation = quads(
        "A",
        "D",
        ["RX", "RY", "RZ"],
        d.map(|d| d.rotation_arcsec.map(|a| a / 3600.0)),
    );
    let translation = quads(
        "D",
        "M",
        ["TX", "TY", "TZ"],
        d.map(|d| d.translation_mm.map(|t| t / 1000.0)),
    );
    let mut out = Vec::new();
    for group in [rotation, translation] {
        let whole: Vec<String> = group.iter().flatten().cloned().collect();
        let body_len = talker.len() + 4 + whole.iter().map(|f| f.len() + 1).sum::<usize>();
        if body_len <= MAX_SENTENCE - 6 {
            out.push(sentence(&format!("{talker}XDR,{}", whole.join(","))));
        } else {
            // A long name: one transducer a sentence, its name cut to fit.
            for quad in &group {
                out.push(fitted(talker, "XDR", quad));
            }
        }
    }
    out
}

/// The `ALR` sentence of an alarm's state: its transition's time (UTC), the target's alarm
/// number, above a threshold or not, acknowledged or not.
pub fn alr(talker: &str, target: TargetId, name: &str, alarm: &StoredAlarm) -> String {
    let t = &alarm.transition;
    let active = t.to > Level::None;
    let (level, active_word) = (t.to, if active { "A" } else { "V" });
    let text = match level {
        Level::None => format!("{} DEFORMATION NORMAL", field(name)),
        Level::Warn => format!("{} DEFORMATION WARN", field(name)),
        Level::Alarm => format!("{} DEFORMATION ALARM", field(name)),
    };
    let ack = if alarm.ack.is_some() { "A" } else { "V" };
    fitted(
        talker,
        "ALR",
        &[
            hhmmss(t.time_ns),
            format!("{:03}", (target.0 + 1).min(999)),
            active_word.to_owned(),
            ack.to_owned(),
            text,
        ],
    )
}

/// `hhmmss.ss` of a time (UTC).
fn hhmmss(time_ns: i64) -> String {
    let day_ns = time_ns.rem_euclid(86_400 * 1_000_000_000);
    let cs = day_ns / 10_000_000;
    format!(
        "{:02}{:02}{:02}.{:02}",
        cs / 360_000,
        cs / 6_000 % 60,
        cs / 100 % 60,
        cs % 100
    )
}

/// The inbox of one receiver: the alarm transitions to say, in order.
struct NmeaInbox {
    alarms: std::sync::Mutex<Ordered<Arc<StoredAlarm>>>,
    wake: Notify,
    counters: Arc<Counters>,
}

impl Inbox for NmeaInbox {
    fn counters(&self) -> &Counters {
        &self.counters
    }

    fn put(&self, update: &Update) {
        if let Update::Alarm { alarm, .. } = update {
            let mut q = lock(&self.alarms);
            if q.push(Arc::clone(alarm)) {
                self.counters.dropped.fetch_add(1, Relaxed);
            }
            self.counters.queued.store(q.items.len() as u64, Relaxed);
            drop(q);
            self.wake.notify_one();
        }
    }
}

/// Opens the socket and starts the output of one receiver.
pub(super) fn spawn(
    service: Service,
    spec: NmeaSpec,
    counters: Arc<Counters>,
) -> std::io::Result<(Arc<dyn Inbox>, tokio::task::JoinHandle<()>)> {
    let local: std::net::SocketAddr = if spec.to.is_ipv4() {
        (std::net::Ipv4Addr::UNSPECIFIED, 0).into()
    } else {
        (std::net::Ipv6Addr::UNSPECIFIED, 0).into()
    };
    let socket = std::net::UdpSocket::bind(local)?;
    // Only reached when the installation allowed a broadcast address (`allow_broadcast`): the
    // same rule the configuration checks it with.
    if spec.to.is_ipv4() && crate::config::reaches_many(spec.to.ip()) {
        socket.set_broadcast(true)?;
    }
    socket.set_nonblocking(true)?;
    let socket = tokio::net::UdpSocket::from_std(socket)?;
    let inbox = Arc::new(NmeaInbox {
        alarms: std::sync::Mutex::new(Ordered::new()),
        wake: Notify::new(),
        counters: Arc::clone(&counters),
    });
    let task = service.clone().spawn_watched(
        "nmea output",
        run(service, spec, socket, Arc::clone(&inbox), counters),
    );
    Ok((inbox, task))
}

async fn run(
    service: Service,
    spec: NmeaSpec,
    socket: tokio::net::UdpSocket,
    inbox: Arc<NmeaInbox>,
    counters: Arc<Counters>,
) {
    let names: Vec<String> = (service.installation().model.targets)
        .iter()
        .map(|t| t.name.clone())
        .collect();
    let mut stop = service.stopping();
    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / spec.rate_hz));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut repeat = tokio::time::interval(ALARM_REPEAT);
    repeat.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    // The newest transition of each target, said again while active.
    let mut newest: Vec<Option<Arc<StoredAlarm>>> = vec![None; names.len()];
    counters.set_connected(true);
    loop {
        let mut out = Vec::new();
        tokio::select! {
            _ = stop.wait_for(|s| *s) => break,
            _ = tick.tick() => {
                for (i, name) in names.iter().enumerate() {
                    let figures = TargetFigures::live(&service, TargetId(i));
                    out.extend(xdr(&spec.talker, name, figures.as_ref()));
                }
            }
            _ = repeat.tick() => {
                for (i, alarm) in newest.iter().enumerate() {
                    if let Some(a) = alarm.as_ref().filter(|a| a.transition.to > Level::None) {
                        out.push(alr(&spec.talker, TargetId(i), &names[i], a));
                    }
                }
            }
            _ = inbox.wake.notified() => {
                let mut q = lock(&inbox.alarms);
                let taken: Vec<_> = q.items.drain(..).collect();
                counters.queued.store(0, Relaxed);
                drop(q);
                for a in taken {
                    let i = a.target.0;
                    if let Some(name) = names.get(i) {
                        out.push(alr(&spec.talker, a.target, name, &a));
                        // An acknowledgement of an older transition does not replace a newer one.
                        if newest[i].as_ref().is_none_or(|n| n.id <= a.id) {
                            newest[i] = Some(a);
                        }
                    }
                }
            }
        }
        let mut sent = 0;
        for s in &out {
            match socket.send_to(s.as_bytes(), spec.to).await {
                Ok(_) => sent += 1,
                Err(e) => {
                    counters.set_connected(false);
                    counters.error(service.now_ns(), format!("to {}: {e}", spec.to));
                }
            }
        }
        if sent > 0 {
            counters.set_connected(true);
            counters.sent(sent, service.now_ns());
        }
    }
    counters.set_connected(false);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_checksum_is_the_xor_between_dollar_and_star() {
        // A sentence from the standard's public examples: $GPGLL,4916.45,N,12311.12,W,225444,A*31
        assert_eq!(checksum("GPGLL,4916.45,N,12311.12,W,225444,A"), 0x31);
    }

    #[test]
    fn a_long_name_is_cut_so_that_every_sentence_fits() {
        let name = "A_VERY_LONG_TARGET_NAME_THAT_GOES_ON_AND_ON_FOR_EVER_AND_EVER";
        let figures = TargetFigures {
            time_ns: 0,
            status: TargetStatus::Ok,
            age_s: 0.0,
            alarm: Level::None,
            deformation: Some(crate::deformation::SmallMotion {
                rotation_arcsec: [-12345.678, 1.0, 2.0],
                translation_mm: [-1234.5, 3.0, 4.0],
                sigmas: crate::geometry::ReportedSigmas {
                    rotation_arcsec: [1.0; 3],
                    translation_mm: [1.0; 3],
                },
            }),
            correction: None,
        };
        let all = xdr("YX", name, Some(&figures));
        assert_eq!(all.len(), 6);
        for s in &all {
            assert!(s.len() <= MAX_SENTENCE, "{s:?} is {} long", s.len());
            assert!(s.starts_with("$YXXDR,"));
            let (body, sum) = s[1..s.len() - 2].split_once('*').unwrap();
            assert_eq!(u8::from_str_radix(sum, 16).unwrap(), checksum(body));
        }
        let short = xdr("YX", "MAST", Some(&figures));
        assert_eq!(short.len(), 2);
        assert!(short[0].contains("A,-3.4293550,D,MAST_RX"), "{}", short[0]);
        assert!(short[1].contains("D,-1.2345000,M,MAST_TX"), "{}", short[1]);
    }

    #[test]
    fn the_time_of_day_is_utc_hours_minutes_seconds_and_hundredths() {
        // 2026-01-02T03:04:05.678Z
        let ns = 1_767_323_045_678_000_000;
        assert_eq!(hhmmss(ns), "030405.67");
    }
}
