//! Every refusal reaches its client as its JSON answer, even one made before the request's
//! body was read (an unknown camera named in the query of a 1 MB frame, a missing token).
//!
//! A server that answers and closes while the client is still sending makes the client's
//! write fail (a broken pipe, a reset) before it reads the answer: the refusal is lost, more
//! often on a loaded machine. Here the handler reads the body through a shared handle; what it
//! left unread is read and discarded after its answer is made, up to the body limit and for a
//! few seconds, so that the client finishes sending and then reads the answer. A body over the
//! limit, or one that keeps coming, is still cut off.

use axum::body::Body;
use axum::extract::Request;
use axum::middleware::Next;
use axum::response::Response;
use http_body_util::BodyExt as _;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

/// How long what a handler left unread is read for, at most.
const DRAIN_FOR: Duration = Duration::from_secs(5);

/// A request body that the handler and, after it, [`drain_unread`] read in turn.
struct Shared(Arc<Mutex<Option<Body>>>);

impl hyper::body::Body for Shared {
    type Data = bytes::Bytes;
    type Error = axum::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<hyper::body::Frame<Self::Data>, Self::Error>>> {
        let mut body = self.0.lock().unwrap_or_else(|p| p.into_inner());
        match body.as_mut() {
            Some(b) => Pin::new(b).poll_frame(cx),
            None => Poll::Ready(None),
        }
    }

    fn is_end_stream(&self) -> bool {
        self.0
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .is_none_or(hyper::body::Body::is_end_stream)
    }

    fn size_hint(&self) -> hyper::body::SizeHint {
        self.0
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .as_ref()
            .map(hyper::body::Body::size_hint)
            .unwrap_or_default()
    }
}

/// Runs the request, then reads and discards what the handler left of its body (at most
/// `limit` bytes, for at most [`DRAIN_FOR`]) before the answer goes out.
pub(super) async fn drain_unread(limit: usize, request: Request, next: Next) -> Response {
    let (parts, body) = request.into_parts();
    let shared = Arc::new(Mutex::new(Some(body)));
    let request = Request::from_parts(parts, Body::new(Shared(Arc::clone(&shared))));
    let response = next.run(request).await;
    let rest = shared.lock().unwrap_or_else(|p| p.into_inner()).take();
    if let Some(mut body) = rest
        && !hyper::body::Body::is_end_stream(&body)
    {
        let _ = tokio::time::timeout(DRAIN_FOR, async {
            let mut read = 0usize;
            while let Some(Ok(frame)) = body.frame().await {
                read += frame.data_ref().map_or(0, bytes::Bytes::len);
                if read > limit {
                    break;
                }
            }
        })
        .await;
    }
    response
}
