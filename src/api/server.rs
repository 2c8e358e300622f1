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
            let mut conn = builder.serve_connection(TokioIo::new(HeadErrors::new(stream)), service);
            let ended = tokio::select! {
                r = &mut conn => r,
                () = async { let _ = stop.wait_for(|s| *s).await; } => {
                    std::pin::Pin::new(&mut conn).graceful_shutdown();
                    (&mut conn).await
                }
            };
            if ended.as_ref().is_err_and(hyper::Error::is_timeout) {
                // No request head in time: hyper closes without a word; say why.
                let mut io = conn.into_parts().io.into_inner();
                io.answer_timeout(limits.header_timeout).await;
            }
            log_connection_end(ended);
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

/// hyper answers a request whose head it cannot parse (400) or whose head is too large (431)
/// by itself, before any handler runs, with an empty body; and it closes a connection whose
/// request head does not arrive in time without an answer. This wrapper of the connection
/// gives those answers the JSON error envelope every other refusal has (and counts them):
/// hyper's bodiless 400 and 431 heads are replaced as they are written, and the timeout gets a
/// 408 written after hyper has given the connection up.
struct HeadErrors<S> {
    inner: S,
    /// A replacement being written: the bytes and how many are out.
    replacing: Option<(Vec<u8>, usize)>,
}

impl HeadErrors<tokio::net::TcpStream> {
    fn new(inner: tokio::net::TcpStream) -> Self {
        Self {
            inner,
            replacing: None,
        }
    }

    /// Writes the 408 answer (for at most a second: a client that reads nothing gets nothing)
    /// and closes.
    async fn answer_timeout(&mut self, limit: Duration) {
        use tokio::io::AsyncWriteExt as _;
        let body = super::error::raw_response(
            axum::http::StatusCode::REQUEST_TIMEOUT,
            "request_timeout",
            &format!(
                "no complete request head within {} s (`[server] header_timeout_s`)",
                limit.as_secs_f64()
            ),
            None,
        );
        let _ = tokio::time::timeout(Duration::from_secs(1), async {
            let _ = self.inner.write_all(&body).await;
            let _ = self.inner.shutdown().await;
        })
        .await;
    }
}

/// The JSON answer to write instead of `head`, when `head` is one of hyper's own bodiless
/// error answers.
fn replacement_for(head: &[u8]) -> Option<Vec<u8>> {
    use axum::http::StatusCode;
    let own = |status: &[u8]| {
        head.starts_with(b"HTTP/1.")
            && head.get(9..13) == Some(status)
            && head
                .windows(19)
                .any(|w| w.eq_ignore_ascii_case(b"content-length: 0\r\n"))
    };
    if own(b"431 ") {
        Some(super::error::raw_response(
            StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
            "headers_too_large",
            "the request's header section is too large (at most 100 fields and about 400 KB)",
            Some("headers"),
        ))
    } else if own(b"400 ") {
        Some(super::error::raw_response(
            StatusCode::BAD_REQUEST,
            "malformed_request",
            "the request is not valid HTTP/1.1",
            None,
        ))
    } else {
        None
    }
}

impl<S: tokio::io::AsyncRead + Unpin> tokio::io::AsyncRead for HeadErrors<S> {
    fn poll_read(
        self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &mut tokio::io::ReadBuf<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        std::pin::Pin::new(&mut self.get_mut().inner).poll_read(cx, buf)
    }
}

impl<S: tokio::io::AsyncWrite + Unpin> tokio::io::AsyncWrite for HeadErrors<S> {
    fn poll_write(
        self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &[u8],
    ) -> std::task::Poll<std::io::Result<usize>> {
        use std::task::Poll;
        let this = self.get_mut();
        if this.replacing.is_none() {
            this.replacing = replacement_for(buf).map(|r| (r, 0));
        }
        let Some((bytes, done)) = &mut this.replacing else {
            return std::pin::Pin::new(&mut this.inner).poll_write(cx, buf);
        };
        while *done < bytes.len() {
            match std::pin::Pin::new(&mut this.inner).poll_write(cx, &bytes[*done..]) {
                Poll::Ready(Ok(0)) => {
                    return Poll::Ready(Err(std::io::ErrorKind::WriteZero.into()));
                }
                Poll::Ready(Ok(n)) => *done += n,
                Poll::Ready(Err(e)) => return Poll::Ready(Err(e)),
                Poll::Pending => return Poll::Pending,
            }
        }
        // hyper's answer counts as written; it closes the connection after it.
        Poll::Ready(Ok(buf.len()))
    }

    fn poll_write_vectored(
        self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> std::task::Poll<std::io::Result<usize>> {
        let this = self.get_mut();
        // hyper's own answers are one buffer; a head with a body is never replaced.
        if this.replacing.is_none() && bufs.iter().filter(|b| !b.is_empty()).count() > 1 {
            return std::pin::Pin::new(&mut this.inner).poll_write_vectored(cx, bufs);
        }
        let first = bufs
            .iter()
            .find(|b| !b.is_empty())
            .map_or(&[][..], |b| &b[..]);
        std::pin::Pin::new(this).poll_write(cx, first)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(
        self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        std::pin::Pin::new(&mut self.get_mut().inner).poll_flush(cx)
    }

    fn poll_shutdown(
        self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        std::pin::Pin::new(&mut self.get_mut().inner).poll_shutdown(cx)
    }
}

fn log_connection_end(r: Result<(), hyper::Error>) {
    if let Err(e) = r {
        // Timeouts, resets and malformed requests: the client's business, not an error here.
        tracing::debug!(error = %e, "connection ended");
    }
}
