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
//! * at most `max_connections` are open, and at most `max_connections_per_address` from one
//!   address. When a newcomer would pass either limit, a connection that is waiting for a
//!   request head (idle, none of its requests in progress) is closed to make room: the oldest
//!   of the newcomer's own address when that address is at its limit, else the oldest of the
//!   address holding the most connections. Only when every connection is busy with a request
//!   is the newcomer closed. A client that keeps refilling idle connections therefore closes
//!   its own, never another's, and never turns others away. Closed on arrival and closed to
//!   make room are counted ([`crate::service::ConnectionCounters`]);
//! * a request keeps its connection busy for at most the request deadline (60 s, its body
//!   included) and a few seconds of draining, but an event stream for as long as its client
//!   reads: event streams are capped per address ([`EVENT_STREAMS_PER_ADDRESS`]) and in all (a
//!   quarter of the connections), and one past a cap is answered 503 `busy`, which leaves its
//!   connection idle and so closable;
//! * when every connection an address or the server may hold is busy, a few more
//!   ([`HEALTH_RESERVE`]) are admitted for one request each that only `GET /healthz` may use
//!   (when they are all taken, the one that has waited longest without sending a request is
//!   closed to make room), so a monitor can still learn that the service is alive and why it is
//!   full;
//! * at shutdown the listener closes, every connection is asked to finish its current request
//!   (event streams end by themselves: they watch the same signal), and after
//!   `shutdown_grace_s` whatever is still open is cut off, with a log line saying how many.

use crate::api::ErrorCode;
use axum::Router;
use hyper::body::Incoming;
use hyper_util::rt::{TokioIo, TokioTimer};
use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use tokio::net::TcpListener;
use tokio::sync::{Notify, watch};
use tower::ServiceExt as _;

/// How the server loop behaves.
#[derive(Debug, Clone, Copy)]
pub struct ServerLimits {
    /// Most connections open at once.
    pub max_connections: usize,
    /// Most connections open at once from one address.
    pub max_connections_per_address: usize,
    /// Time allowed for a request's headers.
    pub header_timeout: Duration,
    /// Time allowed at shutdown for requests in progress.
    pub shutdown_grace: Duration,
}

/// Event streams one address may hold open: a dashboard holds one per tab.
pub const EVENT_STREAMS_PER_ADDRESS: usize = 32;

/// Connections admitted past the limits, one request each, for `GET /healthz` alone.
pub const HEALTH_RESERVE: usize = 16;

/// The path of the event stream, whose connections stay busy while it is read.
const EVENTS_PATH: &str = "/api/v1/events";

impl ServerLimits {
    /// Event streams open at once in all: a quarter of the connections, so that streams never
    /// fill the server.
    fn max_event_streams(&self) -> usize {
        (self.max_connections / 4).max(1)
    }
}

/// Open files kept for everything but client connections (the database, its journal, the
/// archive, Rerun, outgoing HTTP).
pub const FILES_RESERVED: u64 = 256;

/// Raises this process's soft limit of open files to its hard limit (once) and returns it.
pub fn raise_open_files_limit() -> std::io::Result<u64> {
    #[cfg(unix)]
    {
        let (_, hard) = rlimit::getrlimit(rlimit::Resource::NOFILE)?;
        rlimit::increase_nofile_limit(hard)
    }
    #[cfg(not(unix))]
    {
        Ok(u64::MAX)
    }
}

/// The process's soft limit of open files now (`u64::MAX` where unknown).
pub fn open_files_limit() -> u64 {
    #[cfg(unix)]
    {
        rlimit::getrlimit(rlimit::Resource::NOFILE).map_or(u64::MAX, |(soft, _)| soft)
    }
    #[cfg(not(unix))]
    {
        u64::MAX
    }
}

/// `max_connections` when the installation does not set it: 4096, or what the open-files
/// limit leaves after [`FILES_RESERVED`] (at least 16).
pub fn default_max_connections(open_files: u64) -> usize {
    usize::try_from(open_files.saturating_sub(FILES_RESERVED).clamp(16, 4096)).unwrap_or(4096)
}

/// Refuses a `max_connections` the process could not hold open (with [`FILES_RESERVED`] for
/// the rest): past the open-files limit, accepting fails and nobody gets in.
pub fn check_connections_fit(max_connections: usize, open_files: u64) -> Result<(), String> {
    let needed = max_connections as u64 + FILES_RESERVED;
    if needed > open_files {
        Err(format!(
            "[server] max_connections = {max_connections} needs about {needed} open files, but \
             this process may open {open_files} (`ulimit -n`, raised to the hard limit at \
             start): lower max_connections or raise the limit"
        ))
    } else {
        Ok(())
    }
}

/// One open connection, as the admission sees it.
struct Entry {
    peer: IpAddr,
    /// Requests in progress (a request counts until its answer's body has been sent).
    busy: AtomicUsize,
    /// When it last became idle (waiting for a request head), in ns since the server started.
    idle_since_ns: AtomicU64,
    /// Told when the connection must close to make room.
    evict: Notify,
    /// Admitted past the limits for one request to `/healthz` ([`HEALTH_RESERVE`]).
    reserve: bool,
}

/// The open connections, for admission and eviction.
struct Table {
    /// Where evictions are counted.
    metrics: Arc<crate::service::Metrics>,
    started: Instant,
    next_id: u64,
    entries: HashMap<u64, Arc<Entry>>,
    per_address: HashMap<IpAddr, usize>,
    /// Connections of the health reserve open.
    reserved: usize,
    /// Event streams open, per address and in all.
    streams_per_address: HashMap<IpAddr, usize>,
    streams: usize,
}

impl Table {
    fn elapsed_ns(&self) -> u64 {
        u64::try_from(self.started.elapsed().as_nanos()).unwrap_or(u64::MAX)
    }

    fn remove(&mut self, id: u64) {
        let Some(e) = self.entries.remove(&id) else {
            return;
        };
        if e.reserve {
            self.reserved -= 1;
        } else if let Some(n) = self.per_address.get_mut(&e.peer) {
            *n -= 1;
            if *n == 0 {
                self.per_address.remove(&e.peer);
            }
        }
    }

    /// Takes a slot for an event stream of `peer`; why not, past a cap.
    fn open_stream(&mut self, peer: IpAddr, limits: &ServerLimits) -> Result<(), String> {
        let of_peer = self.streams_per_address.get(&peer).copied().unwrap_or(0);
        if of_peer >= EVENT_STREAMS_PER_ADDRESS {
            return Err(format!(
                "this address holds {of_peer} event streams, the most one address may; close one"
            ));
        }
        if self.streams >= limits.max_event_streams() {
            return Err(format!(
                "{} event streams are open, the most this server keeps; retry later",
                self.streams
            ));
        }
        *self.streams_per_address.entry(peer).or_insert(0) += 1;
        self.streams += 1;
        Ok(())
    }

    fn close_stream(&mut self, peer: IpAddr) {
        self.streams = self.streams.saturating_sub(1);
        if let Some(n) = self.streams_per_address.get_mut(&peer) {
            *n -= 1;
            if *n == 0 {
                self.streams_per_address.remove(&peer);
            }
        }
    }

    /// Closes the idle connection of `peer` that has waited longest for a request head; false
    /// when every one of its connections is busy.
    fn evict_oldest_idle(&mut self, peer: IpAddr) -> bool {
        self.evict_oldest_where(|e| e.peer == peer && !e.reserve)
    }

    /// Closes the connection of the health reserve that has waited longest for its request
    /// head (one held open to fill the reserve); false when each is serving its request.
    fn evict_oldest_idle_reserve(&mut self) -> bool {
        self.evict_oldest_where(|e| e.reserve)
    }

    /// Closes the idle connection among those `which` takes that has waited longest.
    fn evict_oldest_where(&mut self, which: impl Fn(&Entry) -> bool) -> bool {
        let oldest = self
            .entries
            .iter()
            .filter(|(_, e)| which(e))
            .filter(|(_, e)| e.busy.load(Ordering::Acquire) == 0)
            .min_by_key(|(_, e)| e.idle_since_ns.load(Ordering::Acquire))
            .map(|(id, _)| *id);
        let Some(id) = oldest else {
            return false;
        };
        if let Some(e) = self.entries.get(&id) {
            e.evict.notify_one();
        }
        self.remove(id);
        self.metrics
            .connections
            .evicted
            .fetch_add(1, Ordering::Relaxed);
        true
    }

    /// Closes the oldest idle connection of the address that holds the most connections (the
    /// greediest pays, so one client filling the slots never closes another's), or of the next
    /// greediest when all of its are busy; false when every connection is busy.
    fn evict_from_greediest(&mut self) -> bool {
        let mut addresses: Vec<(IpAddr, usize)> =
            self.per_address.iter().map(|(a, n)| (*a, *n)).collect();
        addresses.sort_by_key(|a| std::cmp::Reverse(a.1));
        addresses
            .into_iter()
            .any(|(address, _)| self.evict_oldest_idle(address))
    }

    /// Admits a connection from `peer`, closing an idle one where a limit is reached, or into
    /// the health reserve when every one is busy; `None` when it must be refused.
    fn admit(&mut self, peer: IpAddr, limits: &ServerLimits) -> Option<(u64, Arc<Entry>)> {
        let from_peer = self.per_address.get(&peer).copied().unwrap_or(0);
        let full = (from_peer >= limits.max_connections_per_address
            && !self.evict_oldest_idle(peer))
            || (self.entries.len() - self.reserved >= limits.max_connections
                && !self.evict_from_greediest());
        if full && self.reserved >= HEALTH_RESERVE && !self.evict_oldest_idle_reserve() {
            return None;
        }
        let id = self.next_id;
        self.next_id += 1;
        let entry = Arc::new(Entry {
            peer,
            busy: AtomicUsize::new(0),
            idle_since_ns: AtomicU64::new(self.elapsed_ns()),
            evict: Notify::new(),
            reserve: full,
        });
        self.entries.insert(id, Arc::clone(&entry));
        if full {
            self.reserved += 1;
        } else {
            *self.per_address.entry(peer).or_insert(0) += 1;
        }
        Some((id, entry))
    }
}

/// A request in progress on a connection: idle again (since now) when the last one ends.
struct Busy {
    entry: Arc<Entry>,
    table: Arc<Mutex<Table>>,
}

impl Busy {
    fn new(entry: &Arc<Entry>, table: &Arc<Mutex<Table>>) -> Busy {
        entry.busy.fetch_add(1, Ordering::AcqRel);
        Busy {
            entry: Arc::clone(entry),
            table: Arc::clone(table),
        }
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        let now = self
            .table
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .elapsed_ns();
        self.entry.idle_since_ns.store(now, Ordering::Release);
        self.entry.busy.fetch_sub(1, Ordering::AcqRel);
    }
}

/// An event stream's slot, given back when its answer's body is dropped.
struct StreamSlot {
    peer: IpAddr,
    table: Arc<Mutex<Table>>,
}

impl Drop for StreamSlot {
    fn drop(&mut self) {
        self.table
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .close_stream(self.peer);
    }
}

/// An answer's body that keeps its request counted as in progress until it is sent (an event
/// stream's connection is never idle), and an event stream's slot taken.
struct Tracked {
    inner: axum::body::Body,
    _busy: Busy,
    _stream: Option<StreamSlot>,
}

/// What a request may do on its connection: go on (with an event stream's slot when it opens
/// one), or be answered 503 at once (a connection of the health reserve asked for more than
/// `/healthz`, or an event stream past its caps).
fn admit_request(
    entry: &Entry,
    table: &Arc<Mutex<Table>>,
    limits: &ServerLimits,
    path: &str,
) -> Result<Option<StreamSlot>, Box<axum::response::Response>> {
    use axum::response::IntoResponse as _;
    let busy = |message: String| {
        Box::new(
            crate::api::ApiError::new(
                hyper::StatusCode::SERVICE_UNAVAILABLE,
                ErrorCode::Busy,
                message,
            )
            .into_response(),
        )
    };
    if entry.reserve {
        if path == "/healthz" {
            return Ok(None);
        }
        return Err(busy(
            "every connection this address or the server may hold is busy with a request: \
             this one is kept for GET /healthz; retry later"
                .to_owned(),
        ));
    }
    if path != EVENTS_PATH {
        return Ok(None);
    }
    table
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .open_stream(entry.peer, limits)
        .map_err(busy)?;
    Ok(Some(StreamSlot {
        peer: entry.peer,
        table: Arc::clone(table),
    }))
}

impl hyper::body::Body for Tracked {
    type Data = bytes::Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Result<hyper::body::Frame<Self::Data>, Self::Error>>> {
        std::pin::Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> hyper::body::SizeHint {
        self.inner.size_hint()
    }
}

/// Serves `router` on `listener` until `stop` turns true; then stops accepting, lets requests
/// in progress finish for up to `shutdown_grace`, and cuts off the rest. Returns how many
/// connections were cut off.
pub async fn serve(
    listener: TcpListener,
    router: Router,
    limits: ServerLimits,
    metrics: Arc<crate::service::Metrics>,
    mut stop: watch::Receiver<bool>,
) -> usize {
    let table = Arc::new(Mutex::new(Table {
        metrics: Arc::clone(&metrics),
        started: Instant::now(),
        next_id: 0,
        entries: HashMap::new(),
        per_address: HashMap::new(),
        reserved: 0,
        streams_per_address: HashMap::new(),
        streams: 0,
    }));
    let mut connections = tokio::task::JoinSet::new();
    loop {
        let accepted = tokio::select! {
            biased;
            _ = stop.wait_for(|s| *s) => break,
            accepted = listener.accept() => accepted,
            // Reap finished connection tasks so the set does not grow.
            Some(_) = connections.join_next(), if !connections.is_empty() => continue,
        };
        let (stream, peer) = match accepted {
            Ok(a) => a,
            Err(e) => {
                // Out of file descriptors and the like: wait a moment rather than spin.
                tracing::warn!(error = %e, "accepting a connection failed");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let admitted = table
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .admit(peer.ip(), &limits);
        let Some((id, entry)) = admitted else {
            metrics.connections.refused.fetch_add(1, Ordering::Relaxed);
            drop(stream);
            continue;
        };
        let _ = stream.set_nodelay(true);
        let router = router.clone();
        let mut stop = stop.clone();
        let table = Arc::clone(&table);
        let metrics = Arc::clone(&metrics);
        connections.spawn(async move {
            metrics.connections.open.fetch_add(1, Ordering::Relaxed);
            let service = {
                let (entry, table) = (Arc::clone(&entry), Arc::clone(&table));
                hyper::service::service_fn(move |req: hyper::Request<Incoming>| {
                    let busy = Busy::new(&entry, &table);
                    let admitted = admit_request(&entry, &table, &limits, req.uri().path());
                    let router = router.clone();
                    async move {
                        let (response, stream) = match admitted {
                            Ok(stream) => (
                                router.oneshot(req.map(axum::body::Body::new)).await?,
                                stream,
                            ),
                            Err(refusal) => (*refusal, None),
                        };
                        Ok::<_, std::convert::Infallible>(response.map(|inner| Tracked {
                            inner,
                            _busy: busy,
                            _stream: stream,
                        }))
                    }
                })
            };
            let mut builder = hyper::server::conn::http1::Builder::new();
            builder
                .timer(TokioTimer::new())
                .header_read_timeout(limits.header_timeout)
                // A connection of the health reserve serves one request.
                .keep_alive(!entry.reserve);
            let mut conn = builder.serve_connection(
                TokioIo::new(HeadErrors::new(stream, Arc::clone(&metrics))),
                service,
            );
            let ended = tokio::select! {
                r = &mut conn => Some(r),
                // Closed to make room: it was waiting for a request head.
                () = entry.evict.notified() => None,
                () = async { let _ = stop.wait_for(|s| *s).await; } => {
                    std::pin::Pin::new(&mut conn).graceful_shutdown();
                    Some((&mut conn).await)
                }
            };
            if let Some(ended) = ended {
                if ended.as_ref().is_err_and(hyper::Error::is_timeout) {
                    // No request head in time: hyper closes without a word; say why.
                    let mut io = conn.into_parts().io.into_inner();
                    io.answer_timeout(limits.header_timeout).await;
                }
                log_connection_end(ended);
            }
            table.lock().unwrap_or_else(|p| p.into_inner()).remove(id);
            metrics.connections.open.fetch_sub(1, Ordering::Relaxed);
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
    metrics.connections.open.store(0, Ordering::Relaxed);
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
    /// Where the answers written here are counted.
    metrics: Arc<crate::service::Metrics>,
    /// A replacement being written: the bytes and how many are out.
    replacing: Option<(Vec<u8>, usize)>,
}

impl HeadErrors<tokio::net::TcpStream> {
    fn new(inner: tokio::net::TcpStream, metrics: Arc<crate::service::Metrics>) -> Self {
        Self {
            inner,
            metrics,
            replacing: None,
        }
    }

    /// Writes the 408 answer (for at most a second: a client that reads nothing gets nothing)
    /// and closes.
    async fn answer_timeout(&mut self, limit: Duration) {
        use tokio::io::AsyncWriteExt as _;
        self.metrics.count_rejection(408);
        let body = crate::api::raw_response(
            axum::http::StatusCode::REQUEST_TIMEOUT,
            ErrorCode::RequestTimeout,
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
fn replacement_for(head: &[u8]) -> Option<(u16, Vec<u8>)> {
    use axum::http::StatusCode;
    let own = |status: &[u8]| {
        head.starts_with(b"HTTP/1.")
            && head.get(9..13) == Some(status)
            && head
                .windows(19)
                .any(|w| w.eq_ignore_ascii_case(b"content-length: 0\r\n"))
    };
    if own(b"431 ") {
        Some((
            431,
            crate::api::raw_response(
                StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE,
                ErrorCode::HeadersTooLarge,
                "the request's header section is too large (at most 100 fields and about 400 KB)",
                Some("headers"),
            ),
        ))
    } else if own(b"400 ") {
        Some((
            400,
            crate::api::raw_response(
                StatusCode::BAD_REQUEST,
                ErrorCode::MalformedRequest,
                "the request is not valid HTTP/1.1",
                None,
            ),
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
            this.replacing = replacement_for(buf).map(|(status, r)| {
                this.metrics.count_rejection(status);
                (r, 0)
            });
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
