//! `[cameras.source]`: a camera the service takes frames from itself, over GigE Vision or USB3
//! Vision ([`crate::acquire`]). What can be checked without the camera is checked here; what
//! needs it (a pixel format the camera has, a feature it takes) is checked when it is opened.

use std::net::Ipv4Addr;

crate::words! {
    /// How frames are stored in the camera's buffers (`pixel_format`).
    pub enum PixelFormat("pixel format") {
        /// 8 bits a pixel.
        Mono8 = "Mono8",
        /// 10 bits in a 16-bit word.
        Mono10 = "Mono10",
        /// 12 bits in a 16-bit word.
        Mono12 = "Mono12",
        /// 16 bits.
        Mono16 = "Mono16",
    }
}

impl PixelFormat {
    /// Bytes a pixel takes in a buffer.
    pub fn bytes_per_pixel(self) -> usize {
        match self {
            PixelFormat::Mono8 => 1,
            _ => 2,
        }
    }
}

crate::words! {
    /// What starts an exposure (`trigger`).
    pub enum TriggerMode("trigger") {
        /// The camera exposes at its own rate (`rate_hz`).
        FreeRun = "free_run",
        /// The service triggers every camera of the group at once, `rate_hz` times a second.
        Software = "software",
        /// A pulse on an input line (`trigger_line`), wired to every camera of the group.
        Line = "line",
    }
}

crate::words! {
    /// Where a frame's time comes from (`timestamp`).
    pub enum TimestampMode("timestamp mode") {
        /// The camera's IEEE 1588 clock (TAI, `tai_offset_s` ahead of UTC), required enabled and
        /// synchronised to a grandmaster.
        Ptp = "ptp",
        /// The camera's clock, its offset and drift against the host's clock fitted from
        /// latched pairs (or, without a latch, from the arrival of frames).
        HostFit = "host_fit",
        /// The host's clock when the frame arrived, minus `latency_us`: an approximation.
        Host = "host",
    }
}

/// Where the camera is: a GigE Vision camera's IPv4 address, or a USB3 Vision camera by vendor,
/// model and serial number. Neither is found by a broadcast.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CameraAddress {
    /// GigE Vision: opened at this address from the interface that routes to it.
    Gige(Ipv4Addr),
    /// USB3 Vision: `usb:VENDOR:MODEL:SERIAL`.
    Usb {
        /// The vendor's name, as the camera reports it.
        vendor: String,
        /// The model's name.
        model: String,
        /// The serial number.
        serial: String,
    },
}

impl CameraAddress {
    /// Parses `192.168.10.11` or `usb:VENDOR:MODEL:SERIAL`.
    pub fn parse(text: &str) -> Result<CameraAddress, String> {
        if let Some(rest) = text.strip_prefix("usb:") {
            let parts: Vec<&str> = rest.split(':').collect();
            return match parts.as_slice() {
                [vendor, model, serial]
                    if parts.iter().all(|p| {
                        (1..=64).contains(&p.len()) && p.chars().all(|c| c.is_ascii_graphic())
                    }) =>
                {
                    Ok(CameraAddress::Usb {
                        vendor: (*vendor).to_owned(),
                        model: (*model).to_owned(),
                        serial: (*serial).to_owned(),
                    })
                }
                _ => Err(format!(
                    "`{}` is not `usb:VENDOR:MODEL:SERIAL` (three parts of 1 to 64 printable \
                     characters)",
                    text.chars()
                        .take(80)
                        .map(|c| if c.is_control() { '?' } else { c })
                        .collect::<String>()
                )),
            };
        }
        match text.parse::<Ipv4Addr>() {
            Ok(ip) if ip.is_unspecified() || ip.is_broadcast() || ip.is_multicast() => {
                Err(format!(
                    "`{text}` is not one camera's address (a camera is opened at its own address, never found by a broadcast)"
                ))
            }
            // The last address of a /24 (or larger) network is its broadcast, the first its
            // network's own: neither is a camera's on the networks cameras sit on.
            Ok(ip) if !ip.is_loopback() && matches!(ip.octets()[3], 0 | 255) => Err(format!(
                "`{text}` ends in .{}: on a camera network (a /24) that is the {} address, no \
                 camera's; give the camera's own address",
                ip.octets()[3],
                if ip.octets()[3] == 0 {
                    "network"
                } else {
                    "broadcast"
                }
            )),
            Ok(ip) => Ok(CameraAddress::Gige(ip)),
            Err(_) => Err(format!(
                "`{text}` is neither an IPv4 address (GigE Vision) nor `usb:VENDOR:MODEL:SERIAL` (USB3 Vision); cameras are opened by address, never found by name"
            )),
        }
    }
}

impl std::fmt::Display for CameraAddress {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            CameraAddress::Gige(ip) => write!(f, "{ip}"),
            CameraAddress::Usb {
                vendor,
                model,
                serial,
            } => write!(f, "usb:{vendor}:{model}:{serial}"),
        }
    }
}

/// One GenICam feature set at connection, after the keys' own (`features = ["Name=value"]`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FeatureSetting {
    /// The feature's name (`BalanceWhiteAuto`).
    pub name: String,
    /// Its value as written; typed by the feature's node when set.
    pub value: String,
}

impl FeatureSetting {
    /// Parses `Name=value`: a GenICam name (letters, digits, `_`, starting with a letter).
    pub fn parse(text: &str) -> Result<FeatureSetting, String> {
        let Some((name, value)) = text.split_once('=') else {
            return Err(format!("`{text}` is not `Name=value`"));
        };
        let (name, value) = (name.trim(), value.trim());
        let well_named = name.chars().next().is_some_and(|c| c.is_ascii_alphabetic())
            && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
        if !well_named {
            return Err(format!(
                "`{name}` is not a GenICam feature name (letters, digits and `_`, starting with a letter)"
            ));
        }
        if value.is_empty() || value.chars().any(char::is_control) {
            return Err(format!(
                "feature `{name}` has no value (or a control character in it)"
            ));
        }
        Ok(FeatureSetting {
            name: name.to_owned(),
            value: value.to_owned(),
        })
    }
}

/// A camera's source, validated.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraSource {
    /// The camera (its frame in the installation).
    pub camera: String,
    /// Where it is.
    pub address: CameraAddress,
    /// The buffers' pixel format.
    pub pixel_format: PixelFormat,
    /// What starts an exposure.
    pub trigger: TriggerMode,
    /// Cameras of one group are triggered together and their frames of one trigger carry one
    /// time (`software`, `line`).
    pub trigger_group: String,
    /// The input line of a `line` trigger.
    pub trigger_line: String,
    /// Frames a second (`free_run`, `software`); the pulse rate a `line` trigger expects.
    pub rate_hz: f64,
    /// Exposure time set on the camera (µs); `None` leaves the camera's.
    pub exposure_us: Option<f64>,
    /// Gain set on the camera (dB); `None` leaves the camera's.
    pub gain_db: Option<f64>,
    /// Where frame times come from.
    pub timestamp: TimestampMode,
    /// From the camera's stamp to the middle of the exposure (µs); `None`: half the exposure
    /// (cameras stamp the exposure's start unless their manual says otherwise).
    pub stamp_offset_us: Option<f64>,
    /// `host` mode: from the middle of the exposure to the frame's arrival (µs); `None`: half
    /// the exposure.
    pub latency_us: Option<f64>,
    /// `ptp` mode: how far TAI runs ahead of UTC (s).
    pub tai_offset_s: f64,
    /// A frame whose time disagrees with the host's clock at its arrival by more than this
    /// (beyond half its exposure) is refused and counted (ms).
    pub tolerance_ms: f64,
    /// GigE Vision packet size (bytes); `None` negotiates the largest the path carries.
    pub packet_size_bytes: Option<u32>,
    /// Features set after the keys', in order.
    pub features: Vec<FeatureSetting>,
}

impl CameraSource {
    /// The offset from the camera's stamp to the middle of the exposure (ns), given the
    /// exposure in force.
    pub fn stamp_offset_ns(&self, exposure_us: f64) -> i64 {
        (self.stamp_offset_us.unwrap_or(exposure_us / 2.0) * 1e3).round() as i64
    }

    /// `host` mode: from the middle of the exposure to the arrival (ns).
    pub fn latency_ns(&self, exposure_us: f64) -> i64 {
        (self.latency_us.unwrap_or(exposure_us / 2.0) * 1e3).round() as i64
    }
}
