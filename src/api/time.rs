//! Times at the API edge: RFC 3339 UTC text or integer nanoseconds since the Unix epoch.

use time::OffsetDateTime;
use time::format_description::well_known::Rfc3339;

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
/// `latest_ns`: the server's clock plus `[server] max_future_s`.
pub fn parse_measurement_time(v: &serde_json::Value, latest_ns: i64) -> Result<i64, String> {
    let t = parse_json_time(v)?;
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

/// Parses the optional `from` and `to` of a query into `[from, to]` (open ends unbounded),
/// refusing a `to` before `from`.
pub fn parse_query_range(
    from: Option<&str>,
    to: Option<&str>,
) -> Result<(i64, i64), super::error::ApiError> {
    use super::error::ApiError;
    let from = match from {
        Some(f) => parse_query_time(f).map_err(|m| ApiError::invalid_field("from", m))?,
        None => i64::MIN,
    };
    let to = match to {
        Some(t) => parse_query_time(t).map_err(|m| ApiError::invalid_field("to", m))?,
        None => i64::MAX,
    };
    if from > to {
        return Err(ApiError::invalid_field("to", "`to` is before `from`"));
    }
    Ok((from, to))
}

/// Formats nanoseconds as RFC 3339 UTC text with nanosecond precision.
pub fn format_ns(ns: i64) -> String {
    OffsetDateTime::from_unix_timestamp_nanos(i128::from(ns))
        .ok()
        .and_then(|t| t.format(&Rfc3339).ok())
        .unwrap_or_else(|| ns.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

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
