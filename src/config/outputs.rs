//! `[[outputs.mqtt]]`, `[[outputs.modbus]]`, `[[outputs.nmea]]`: the buses of a plant or a ship
//! the service publishes its compensations and alarms on ([`crate::outputs`]). What can be
//! checked without the network is checked here (a URL's scheme and host, a UDP address that
//! would reach a whole network); what needs it (a port already taken) when the service starts.

use super::raw::{RawFile, RawMqtt, RawNmea};
use super::validate::Validator;
use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;

/// Every output, in file order per kind.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct OutputSettings {
    /// MQTT brokers published to.
    pub mqtt: Vec<MqttSpec>,
    /// Modbus/TCP servers that answer register reads.
    pub modbus: Vec<ModbusSpec>,
    /// NMEA 0183 (IEC 61162-1) sentences sent by UDP.
    pub nmea: Vec<NmeaSpec>,
}

impl OutputSettings {
    /// True when no output is configured.
    pub fn is_empty(&self) -> bool {
        self.mqtt.is_empty() && self.modbus.is_empty() && self.nmea.is_empty()
    }
}

/// An MQTT broker the service publishes to.
#[derive(Clone, PartialEq)]
pub struct MqttSpec {
    /// The broker's host (a name or an address).
    pub host: String,
    /// Its port (1883 for `mqtt://`, 8883 for `mqtts://` unless the URL says).
    pub port: u16,
    /// TLS (`mqtts://`).
    pub tls: bool,
    /// PEM file of the certificate authorities trusted for TLS; the system's when `None`.
    pub ca_file: Option<PathBuf>,
    /// The client id the broker knows the service by.
    pub client_id: String,
    /// What every topic starts with.
    pub topic_prefix: String,
    /// 0 (at most once) or 1 (at least once).
    pub qos: u8,
    /// Most compensations a second per target.
    pub rate_hz: f64,
    /// User name and password, when the broker asks for them.
    pub credentials: Option<(String, String)>,
}

impl MqttSpec {
    /// `host:port`: what logs, metrics and the status name.
    pub fn address(&self) -> String {
        format!("{}:{}", self.host, self.port)
    }
}

impl std::fmt::Debug for MqttSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MqttSpec")
            .field("address", &self.address())
            .field("tls", &self.tls)
            .field("client_id", &self.client_id)
            .field("topic_prefix", &self.topic_prefix)
            .field("qos", &self.qos)
            .field("rate_hz", &self.rate_hz)
            .field(
                "credentials",
                &self.credentials.as_ref().map(|_| "<redacted>"),
            )
            .finish()
    }
}

/// A Modbus/TCP server of the register map ([`crate::outputs::modbus`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ModbusSpec {
    /// The address it listens on.
    pub listen: SocketAddr,
}

/// Where NMEA 0183 sentences go.
#[derive(Debug, Clone, PartialEq)]
pub struct NmeaSpec {
    /// The receiver's address (a serial gateway, the voyage data recorder's input).
    pub to: SocketAddr,
    /// The two-letter talker id the sentences start with.
    pub talker: String,
    /// Transducer sentences a second per target.
    pub rate_hz: f64,
}

/// Most MQTT compensations a second per target.
pub const MAX_MQTT_RATE_HZ: f64 = 100.0;
/// Most NMEA transducer sentences a second per target (a 4800-baud line takes about 8 a second).
pub const MAX_NMEA_RATE_HZ: f64 = 10.0;

/// True when `ip` reaches more than one receiver (a broadcast or multicast address), as far as
/// the address alone tells: the limited broadcast, a multicast group, and IPv4 addresses ending
/// in `.255` (the broadcast address of every network of /24 or wider).
pub fn reaches_many(ip: IpAddr) -> bool {
    match ip {
        IpAddr::V4(v4) => v4.is_broadcast() || v4.is_multicast() || v4.octets()[3] == 255,
        IpAddr::V6(v6) => v6.is_multicast(),
    }
}

impl Validator {
    pub(super) fn outputs(&mut self, raw: &RawFile) -> OutputSettings {
        let mut out = OutputSettings::default();
        for (i, spanned) in raw.outputs.mqtt.iter().enumerate() {
            let at = spanned.span().start;
            if let Some(spec) = self.mqtt(at, &format!("outputs.mqtt[{i}]"), spanned.get_ref()) {
                out.mqtt.push(spec);
            }
        }
        let mut listening = std::collections::HashSet::new();
        for (i, spanned) in raw.outputs.modbus.iter().enumerate() {
            let at = spanned.span().start;
            let what = format!("outputs.modbus[{i}].listen");
            let text = &spanned.get_ref().listen;
            match text.parse::<SocketAddr>() {
                Ok(listen) => {
                    if !listening.insert(listen) {
                        self.problem(at, format!("{what} `{listen}` is named twice"));
                    } else if listen.ip().is_multicast() {
                        self.problem(
                            at,
                            format!(
                                "{what} `{listen}` is a multicast address, not one to listen on"
                            ),
                        );
                    } else {
                        if !listen.ip().is_loopback() {
                            self.warning(
                                at,
                                format!(
                                    "{what} `{listen}` is not loopback: Modbus has no authentication, and anyone who reaches that address reads the registers"
                                ),
                            );
                        }
                        out.modbus.push(ModbusSpec { listen });
                    }
                }
                Err(_) => self.problem(
                    at,
                    format!(
                        "{what} must be an address and port such as `127.0.0.1:5020`, not `{text}`"
                    ),
                ),
            }
        }
        for (i, spanned) in raw.outputs.nmea.iter().enumerate() {
            let at = spanned.span().start;
            if let Some(spec) = self.nmea(at, &format!("outputs.nmea[{i}]"), spanned.get_ref()) {
                out.nmea.push(spec);
            }
        }
        out
    }

    fn mqtt(&mut self, at: usize, what: &str, m: &RawMqtt) -> Option<MqttSpec> {
        let mut ok = true;
        let url = match url::Url::parse(&m.url) {
            Ok(u) => Some(u),
            Err(e) => {
                self.problem(
                    at,
                    format!(
                        "{what}.url must be an mqtt:// or mqtts:// URL such as `mqtt://127.0.0.1:1883`, not `{}`: {e}",
                        m.url
                    ),
                );
                None
            }
        };
        let (mut host, mut port, mut tls) = (String::new(), 0, false);
        if let Some(u) = &url {
            tls = match u.scheme() {
                "mqtt" => false,
                "mqtts" => true,
                other => {
                    self.problem(
                        at,
                        format!(
                            "{what}.url has the scheme `{other}`; it must be mqtt:// or mqtts://"
                        ),
                    );
                    ok = false;
                    false
                }
            };
            if !u.username().is_empty() || u.password().is_some() {
                self.problem(
                    at,
                    format!("{what}.url carries credentials; give them as `username` and `password`, which are never logged"),
                );
                ok = false;
            }
            if !matches!(u.path(), "" | "/") || u.query().is_some() || u.fragment().is_some() {
                self.problem(
                    at,
                    format!("{what}.url may name only a host and a port, not a path or a query"),
                );
                ok = false;
            }
            port = u.port().unwrap_or(if tls { 8883 } else { 1883 });
            match u.host() {
                None => {
                    self.problem(at, format!("{what}.url names no host"));
                    ok = false;
                }
                Some(h) => {
                    let ip = match h {
                        url::Host::Ipv4(a) => Some(IpAddr::V4(a)),
                        url::Host::Ipv6(a) => Some(IpAddr::V6(a)),
                        // An `mqtt://` URL's host is opaque to the URL parser: an address
                        // written as text is read here.
                        url::Host::Domain(d) => d.parse::<IpAddr>().ok(),
                    };
                    if let Some(ip) = ip
                        && (ip.is_unspecified() || reaches_many(ip))
                    {
                        self.problem(
                            at,
                            format!("{what}.url host `{ip}` cannot be a broker: it is not one machine's address"),
                        );
                        ok = false;
                    }
                    host = match h {
                        url::Host::Ipv6(a) => a.to_string(),
                        other => other.to_string(),
                    };
                }
            }
            if port == 0 {
                self.problem(
                    at,
                    format!("{what}.url has port 0, which no broker listens on"),
                );
                ok = false;
            }
        } else {
            ok = false;
        }
        if m.ca_file.is_some() && !tls {
            self.problem(
                at,
                format!(
                    "{what}.ca_file is given but the url is not mqtts://: nothing would use it"
                ),
            );
            ok = false;
        }
        let client_id = m
            .client_id
            .clone()
            .unwrap_or_else(|| "brokenray".to_owned());
        if client_id.is_empty()
            || client_id.len() > 64
            || !client_id.chars().all(|c| c.is_ascii_graphic())
        {
            self.problem(
                at,
                format!(
                    "{what}.client_id must be 1 to 64 visible ASCII characters, not `{client_id}`"
                ),
            );
            ok = false;
        }
        let topic_prefix = m
            .topic_prefix
            .clone()
            .unwrap_or_else(|| "brokenray".to_owned());
        if topic_prefix.is_empty()
            || topic_prefix.len() > 200
            || topic_prefix.starts_with('/')
            || topic_prefix.ends_with('/')
            || topic_prefix.contains("//")
            || topic_prefix
                .chars()
                .any(|c| matches!(c, '+' | '#' | '\0') || c.is_control() || c.is_whitespace())
        {
            self.problem(
                at,
                format!(
                    "{what}.topic_prefix must be topic levels joined by `/`, without `+`, `#`, spaces or an empty level, not `{topic_prefix}`"
                ),
            );
            ok = false;
        }
        let qos = m.qos.unwrap_or(1);
        if qos > 1 {
            self.problem(at, format!("{what}.qos must be 0 or 1, not {qos}"));
            ok = false;
        }
        let rate_hz = m.rate_hz.unwrap_or(5.0);
        ok &= self.within(
            at,
            &format!("{what}.rate_hz"),
            rate_hz,
            0.01,
            MAX_MQTT_RATE_HZ,
        );
        let credentials = match (&m.username, &m.password) {
            (Some(u), Some(p)) if !u.is_empty() => Some((u.clone(), p.clone())),
            (None, None) => None,
            _ => {
                self.problem(
                    at,
                    format!(
                        "{what}: `username` and `password` are given together, the name not empty"
                    ),
                );
                ok = false;
                None
            }
        };
        ok.then(|| MqttSpec {
            host,
            port,
            tls,
            ca_file: m.ca_file.clone().map(PathBuf::from),
            client_id,
            topic_prefix,
            qos,
            rate_hz,
            credentials,
        })
    }

    fn nmea(&mut self, at: usize, what: &str, n: &RawNmea) -> Option<NmeaSpec> {
        let mut ok = true;
        let to = match n.to.parse::<SocketAddr>() {
            Ok(to) => {
                if to.ip().is_unspecified() || to.port() == 0 {
                    self.problem(
                        at,
                        format!("{what}.to `{to}` is not a receiver's address and port"),
                    );
                    ok = false;
                } else if reaches_many(to.ip()) && !n.allow_broadcast.unwrap_or(false) {
                    self.problem(
                        at,
                        format!(
                            "{what}.to `{to}` is a broadcast or multicast address, which reaches every receiver of a network; set `allow_broadcast = true` if that is meant"
                        ),
                    );
                    ok = false;
                }
                Some(to)
            }
            Err(_) => {
                self.problem(
                    at,
                    format!(
                        "{what}.to must be an address and port such as `127.0.0.1:10110`, not `{}`",
                        n.to
                    ),
                );
                None
            }
        };
        let talker = n.talker.clone().unwrap_or_else(|| "YX".to_owned());
        if talker.len() != 2 || !talker.chars().all(|c| c.is_ascii_uppercase()) {
            self.problem(
                at,
                format!("{what}.talker must be two capital letters (such as `YX`, a transducer), not `{talker}`"),
            );
            ok = false;
        }
        let rate_hz = n.rate_hz.unwrap_or(1.0);
        ok &= self.within(
            at,
            &format!("{what}.rate_hz"),
            rate_hz,
            0.01,
            MAX_NMEA_RATE_HZ,
        );
        match (ok, to) {
            (true, Some(to)) => Some(NmeaSpec {
                to,
                talker,
                rate_hz,
            }),
            _ => None,
        }
    }
}
