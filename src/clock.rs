//! Time: the server's clock, and times as text.
//!
//! The server's clock is the wall-clock time against which liveness (how old the newest sample
//! is), the future-time check of ingest, retention and creation stamps are judged. Measurement
//! times come with the data and order everything the filters do; the server's clock only says
//! how that data relates to "now". It sits behind [`Clock`] so that a test (or a replay tool)
//! can set it instead of sleeping.
//!
//! Times travel as RFC 3339 UTC text (any offset accepted, nanoseconds kept) or integer
//! nanoseconds since the Unix epoch. Imports nothing of the crate.

use std::sync::Arc;
use std::sync::atomic::{AtomicI64, Ordering};
use time::OffsetDateTime;
use time::format_description::well_known::Rfc3339;

/// Nanoseconds in a second.
pub const NS_PER_S: f64 = 1e9;

/// A source of the current time (ns since the Unix epoch, UTC).
pub trait Clock: Send + Sync + std::fmt::Debug {
    /// Now (ns since the Unix epoch).
    fn now_ns(&self) -> i64;
}

/// The operating system's wall clock.
#[derive(Debug, Default, Clone, Copy)]
pub struct SystemClock;

impl Clock for SystemClock {
    fn now_ns(&self) -> i64 {
        wall_now_ns()
    }
}

/// A clock that moves only when told (tests, replays). Clones share the same time.
#[derive(Debug, Clone)]
pub struct ManualClock(Arc<AtomicI64>);

impl ManualClock {
    /// A clock reading `now_ns`.
    pub fn new(now_ns: i64) -> Self {
        Self(Arc::new(AtomicI64::new(now_ns)))
    }

    /// Sets the time.
    pub fn set_ns(&self, now_ns: i64) {
        self.0.store(now_ns, Ordering::SeqCst);
    }

    /// Moves the time on by `seconds` (back when negative).
    pub fn advance_s(&self, seconds: f64) {
        self.0
            .fetch_add((seconds * NS_PER_S).round() as i64, Ordering::SeqCst);
    }
}

impl Clock for ManualClock {
    fn now_ns(&self) -> i64 {
        self.0.load(Ordering::SeqCst)
    }
}

/// The shared handle the service keeps.
pub type SharedClock = Arc<dyn Clock>;

/// The system clock as a shared handle.
pub fn system() -> SharedClock {
    Arc::new(SystemClock)
}

/// The operating system's wall-clock time (ns since the Unix epoch); 0 before 1970, saturating
/// in 2262.
pub fn wall_now_ns() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
        .unwrap_or(0)
}

/// Parses a time given as RFC 3339 text (any offset; converted to UTC).
pub fn parse_rfc3339_ns(text: &str) -> Result<i64, String> {
    let t = OffsetDateTime::parse(text, &Rfc3339)
        .map_err(|e| format!("`{text}` is not an RFC 3339 time ({e})"))?;
    i64::try_from(t.unix_timestamp_nanos())
        .map_err(|_| format!("`{text}` is outside the representable range (years 1678 to 2261)"))
}

/// Parses a JSON time: RFC 3339 text or integer nanoseconds.
pub fn parse_json_time(v: &serde_json::Value) -> Result<i64, String> {
    match v {
        serde_json::Value::String(s) => parse_rfc3339_ns(s),
        serde_json::Value::Number(n) => n.as_i64().ok_or_else(|| {
            format!("{n} is not an integer number of nanoseconds within the representable range")
        }),
        other => Err(format!(
            "must be RFC 3339 text or integer nanoseconds since the Unix epoch, not {other}"
        )),
    }
}

/// Parses a measurement time (as [`parse_json_time`]) and refuses one later than
/// `latest_ns` (the server's clock plus `[server] max_future_s`) or earlier than
/// [`EARLIEST_NS`].
pub fn parse_measurement_time(v: &serde_json::Value, latest_ns: i64) -> Result<i64, String> {
    accepted_time(parse_json_time(v)?, latest_ns)
}

/// The earliest measurement time accepted, 2000-01-01T00:00:00Z: an earlier one comes from a
/// clock that was never set, and the far past is where time arithmetic (buckets, partitions)
/// would wrap around.
pub const EARLIEST_NS: i64 = 946_684_800_000_000_000;

/// A measurement time `t`, refused when later than `latest_ns` (see [`latest_accepted_ns`]) or
/// earlier than [`EARLIEST_NS`].
pub fn accepted_time(t: i64, latest_ns: i64) -> Result<i64, String> {
    if t < EARLIEST_NS {
        return Err(format!(
            "{} is before {}: check the sender's clock",
            format_ns(t),
            format_ns(EARLIEST_NS)
        ));
    }
    if t > latest_ns {
        return Err(format!(
            "{} is in the future: the server's clock allows times up to {} (`[server] max_future_s`); check the sender's clock",
            format_ns(t),
            format_ns(latest_ns)
        ));
    }
    Ok(t)
}

/// The latest measurement time the server accepts at `now_ns` (its clock): plus
/// `max_future_s`.
pub fn latest_accepted_ns(now_ns: i64, max_future_s: f64) -> i64 {
    now_ns.saturating_add((max_future_s * 1e9) as i64)
}

/// Parses a query-string time: RFC 3339 text, or integer nanoseconds.
pub fn parse_query_time(text: &str) -> Result<i64, String> {
    if let Ok(ns) = text.parse::<i64>() {
        return Ok(ns);
    }
    parse_rfc3339_ns(text)
}

/// Formats nanoseconds as RFC 3339 UTC text with nanosecond precision.
pub fn format_ns(ns: i64) -> String {
    OffsetDateTime::from_unix_timestamp_nanos(i128::from(ns))
        .ok()
        .and_then(|t| t.format(&Rfc3339).ok())
        .unwrap_or_else(|| ns.to_string())
}

/// Formats nanoseconds as RFC 3339 UTC text with all nine fractional digits, so that names
/// made of times sort in time order (`2026-11-21T10:00:00.040000000Z`).
pub fn format_ns_fixed(ns: i64) -> String {
    let text = format_ns(ns);
    match (text.strip_suffix('Z'), text.find('.')) {
        (Some(body), Some(dot)) => format!("{body:0<width$}Z", width = dot + 10),
        (Some(body), None) if body.contains('T') => format!("{body}.000000000Z"),
        _ => text,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fixed_width_times_sort_in_time_order_and_parse_back() {
        let t0 = 1_795_255_200_000_000_000;
        let names: Vec<String> = [0, 40_000_000, 200_000_000, 1_000_000_001]
            .iter()
            .map(|d| format_ns_fixed(t0 + d))
            .collect();
        assert_eq!(names[0], "2026-11-21T10:00:00.000000000Z");
        assert_eq!(names[1], "2026-11-21T10:00:00.040000000Z");
        assert_eq!(names[3], "2026-11-21T10:00:01.000000001Z");
        let mut sorted = names.clone();
        sorted.sort();
        assert_eq!(sorted, names);
        for (name, d) in names
            .iter()
            .zip([0, 40_000_000, 200_000_000, 1_000_000_001])
        {
            assert_eq!(parse_query_time(name), Ok(t0 + d));
        }
    }

    #[test]
    fn a_manual_clock_moves_only_when_told_and_its_clones_share_it() {
        let c = ManualClock::new(1_000);
        let shared: SharedClock = Arc::new(c.clone());
        assert_eq!(shared.now_ns(), 1_000);
        c.advance_s(2.5);
        assert_eq!(shared.now_ns(), 2_500_001_000);
        c.set_ns(7);
        assert_eq!(shared.now_ns(), 7);
    }

    #[test]
    fn the_system_clock_reads_after_2026() {
        // 2026-01-01T00:00:00Z: a clock reading earlier is broken, not merely skewed.
        assert!(SystemClock.now_ns() > 1_767_225_600_000_000_000);
    }

    #[test]
    fn rfc3339_round_trips_to_the_nanosecond() {
        let ns = parse_rfc3339_ns("2026-11-21T10:00:00.040000001Z").unwrap();
        assert_eq!(format_ns(ns), "2026-11-21T10:00:00.040000001Z");
        assert_eq!(
            parse_rfc3339_ns("2026-11-21T11:00:00.04+01:00").unwrap(),
            ns - 1
        );
    }

    #[test]
    fn times_outside_i64_nanoseconds_are_refused() {
        assert!(
            parse_rfc3339_ns("2500-01-01T00:00:00Z")
                .unwrap_err()
                .contains("representable")
        );
        assert!(
            parse_rfc3339_ns("1500-01-01T00:00:00Z")
                .unwrap_err()
                .contains("representable")
        );
    }
}
