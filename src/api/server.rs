//! The HTTP/1.1 server loop: accepts connections up to a limit, gives each a header-read
//! deadline, and stops gracefully with a deadline of its own.
//!
//! `axum::serve` has neither a header-read timeout nor a connection limit, and its graceful
//! stop waits for every connection for ever: a client that drip-feeds header lines, or an open
//! event stream, would hold the process. Here:
//!
//! * a connection must deliver a request's headers within `header_timeout_s` of being opened
//!   or of its previous response (hyper's header-read timer), so idle and slow clients are
//!   closed;
//! * at most `max_connections` are open; a connection past the limit is closed at once and
//!   counted ([`CONNECTIONS_REFUSED`]);
//! * at shutdown the listener closes, every connection is asked to finish its current request
//!   (event streams end by themselves: they watch the same signal), and after
//!   `shutdown_grace_s` whatever is still open is cut off, with a log line saying how many.

use axum::Router;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;
use tokio::net::TcpListener;
use tokio::sync::{Semaphore, watch};
use tower::ServiceExt as _;

/// Connections closed on arrival because `max_connections` were open.
pub static CONNECTIONS_REFUSED: AtomicU64 = AtomicU64::new(0);
/// Connections open now.
pub static CONNECTIONS_OPEN: AtomicU64 = AtomicU64::new(0);

/// How the server loop behaves.
#[derive(Debug, Clone, Copy)]
pub struct ServerLimits {
    /// Most connections open at once.
    pub max_connections: usize,
    /// Time allowed for a request's headers.
    pub header_timeout: Duration,
    /// Time allowed at shutdown for requests in progress.
    pub shutdown_grace: Duration,
}

/// Serves `router` on `listener` until `stop` turns true; then stops accepting, lets requests
/// in progress finish for up to `shutdown_grace`, and cuts off the rest. Returns how many
/// connections were cut off.
pub async fn serve(
    listener: TcpListener,
    router: Router,
    limits: ServerLimits,
    mut stop: watch::Receiver<bool>,
) -> usize {
    let permits = Arc::new(Semaphore::new(limits.max_connections));
    let mut connections = tokio::task::JoinSet::new();
    loop {
        let accepted = tokio::select! {
            biased;
            _ = stop.wait_for(|s| *s) => break,
            accepted = listener.accept() => accepted,
            // Reap finished connection tasks so the set does not grow.
            Some(_) = connections.join_next(), if !connections.is_empty() => continue,
        };
        let (stream, _peer) = match accepted {
            Ok(a) => a,
            Err(e) => {
                // Out of file descriptors and the like: wait a moment rather than spin.
                tracing::warn!(error = %e, "accepting a connection failed");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let Ok(permit) = Arc::clone(&permits).try_acquire_owned() else {
            CONNECTIONS_REFUSED.fetch_add(1, Ordering::Relaxed);
            drop(stream);
            continue;
        };
        let _ = stream.set_nodelay(true);
        let router = router.clone();
        let mut stop = stop.clone();
        connections.spawn(async move {
            CONNECTIONS_OPEN.fetch_add(1, Ordering::Relaxed);
            let service = hyper::service::service_fn(move |req: hyper::Request<Incoming>| {
                router.clone().oneshot(req.map(axum::body::Body::new))
            });
            let mut builder = hyper::server::conn::http1::Builder::new();
            builder
                .timer(TokioTimer::new())
                .header_read_timeout(limits.header_timeout);
            let conn = builder.serve_connection(TokioIo::new(stream), service);
            tokio::pin!(conn);
            tokio::select! {
                r = conn.as_mut() => log_connection_end(r),
                () = async { let _ = stop.wait_for(|s| *s).await; } => {
                    conn.as_mut().graceful_shutdown();
                    log_connection_end(conn.await);
                }
            }
            CONNECTIONS_OPEN.fetch_sub(1, Ordering::Relaxed);
            drop(permit);
        });
    }
    drop(listener);
    let open = connections.len();
    let deadline = tokio::time::sleep(limits.shutdown_grace);
    tokio::pin!(deadline);
    loop {
        tokio::select! {
            next = connections.join_next() => if next.is_none() { return 0 },
            () = &mut deadline => break,
        }
    }
    let cut = connections.len();
    tracing::warn!(
        open_at_shutdown = open,
        cut_off = cut,
        grace_s = limits.shutdown_grace.as_secs_f64(),
        "shutdown: {cut} connection(s) still busy after the grace period were cut off"
    );
    connections.abort_all();
    while connections.join_next().await.is_some() {}
    CONNECTIONS_OPEN.store(0, Ordering::Relaxed);
    cut
}

fn log_connection_end(r: Result<(), hyper::Error>) {
    if let Err(e) = r {
        // Timeouts, resets and malformed requests: the client's business, not an error here.
        tracing::debug!(error = %e, "connection ended");
    }
}
