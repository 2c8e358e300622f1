//! `brokenray healthcheck`: asks a running service's `/healthz`.

use anyhow::Context as _;

/// Asks `GET /healthz` of the service listening on `listen` (an unspecified address is asked
/// on loopback) and returns the answer's body when the status is 200.
///
/// One plain HTTP/1.1 request over a std `TcpStream`: the answer is tiny and local, and an HTTP
/// client crate would add a second TLS-capable stack to the binary for this alone.
pub fn healthcheck(listen: std::net::SocketAddr, timeout_s: f64) -> anyhow::Result<String> {
    use std::io::{Read as _, Write as _};
    anyhow::ensure!(
        timeout_s.is_finite() && timeout_s > 0.0 && timeout_s <= 3600.0,
        "--timeout-s must be a number of seconds over 0 and at most 3600, not {timeout_s}"
    );
    let timeout = std::time::Duration::from_secs_f64(timeout_s);
    let mut addr = listen;
    if addr.ip().is_unspecified() {
        addr.set_ip(if addr.is_ipv4() {
            std::net::Ipv4Addr::LOCALHOST.into()
        } else {
            std::net::Ipv6Addr::LOCALHOST.into()
        });
    }
    let mut stream = std::net::TcpStream::connect_timeout(&addr, timeout)
        .with_context(|| format!("nothing answers on {addr}"))?;
    stream.set_read_timeout(Some(timeout))?;
    stream.set_write_timeout(Some(timeout))?;
    write!(
        stream,
        "GET /healthz HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )?;
    let mut response = String::new();
    stream
        .read_to_string(&mut response)
        .with_context(|| format!("no complete answer from {addr}"))?;
    let status_line = response.lines().next().unwrap_or_default();
    let body = response
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.trim())
        .unwrap_or_default();
    anyhow::ensure!(
        status_line.split_whitespace().nth(1) == Some("200"),
        "unhealthy: {status_line}: {body}"
    );
    Ok(body.to_owned())
}
