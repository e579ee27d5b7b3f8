//! The server's guard in front of tonic: what a request may hold while it is still arriving.
//!
//! tonic buffers a whole request message before any handler runs, so the queue's admission
//! (checked in the handler) came too late: a client that stalled its upload before the last
//! byte held its buffer for good, and a dozen such streams held most of a gigabyte while Health
//! said the queue was empty. [`UploadGuardLayer`] counts every request body as it arrives:
//! - at most `max_uploads` bodies arrive at once (more are answered RESOURCE_EXHAUSTED before a
//!   byte is read);
//! - together they may hold at most `max_upload_bytes` (the request that would pass it fails with
//!   RESOURCE_EXHAUSTED and its bytes are freed);
//! - a body that sends nothing for `stall` fails with DEADLINE_EXCEEDED and its bytes are freed.
//!
//! It also gives tonic's own errors the codes gRPC's conventions give them: a message that is not
//! valid protobuf is INVALID_ARGUMENT (tonic says INTERNAL), one over the size limit is
//! RESOURCE_EXHAUSTED (tonic says OUT_OF_RANGE).

use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use bytes::Bytes;
use http_body::Frame;
use tonic::body::Body;
use tonic::{Code, Status};

/// The guard's limits (see the module docs).
#[derive(Debug, Clone, Copy)]
pub struct UploadLimits {
    pub max_uploads: usize,
    pub max_upload_bytes: usize,
    pub stall: Duration,
}

impl Default for UploadLimits {
    fn default() -> Self {
        Self {
            max_uploads: 32,
            max_upload_bytes: 192 << 20,
            stall: Duration::from_secs(10),
        }
    }
}

/// What is arriving now, shared by every connection.
#[derive(Debug, Default)]
pub struct UploadState {
    /// Request bodies still arriving.
    pub uploads: AtomicUsize,
    /// Bytes they have delivered so far.
    pub bytes: AtomicUsize,
}

/// The tower layer (`Server::builder().layer(...)`).
#[derive(Clone)]
pub struct UploadGuardLayer {
    limits: UploadLimits,
    state: Arc<UploadState>,
}

impl UploadGuardLayer {
    pub fn new(limits: UploadLimits, state: Arc<UploadState>) -> Self {
        Self { limits, state }
    }
}

impl<S> tower_layer::Layer<S> for UploadGuardLayer {
    type Service = UploadGuard<S>;
    fn layer(&self, inner: S) -> UploadGuard<S> {
        UploadGuard {
            inner,
            limits: self.limits,
            state: self.state.clone(),
        }
    }
}

#[derive(Clone)]
pub struct UploadGuard<S> {
    inner: S,
    limits: UploadLimits,
    state: Arc<UploadState>,
}

type BoxFuture<T, E> = Pin<Box<dyn Future<Output = Result<T, E>> + Send>>;

impl<S, B> tower_service::Service<http::Request<Body>> for UploadGuard<S>
where
    S: tower_service::Service<http::Request<Body>, Response = http::Response<B>>
        + Clone
        + Send
        + 'static,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
    B: http_body::Body<Data = Bytes> + Send + 'static,
    B::Error: Into<Box<dyn std::error::Error + Send + Sync>>,
{
    type Response = http::Response<Body>;
    type Error = S::Error;
    type Future = BoxFuture<Self::Response, Self::Error>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: http::Request<Body>) -> Self::Future {
        let Some(slot) = Upload::begin(&self.state, self.limits.max_uploads) else {
            let status = Status::resource_exhausted(format!(
                "the server is receiving {} requests already; retry later",
                self.limits.max_uploads
            ));
            return Box::pin(std::future::ready(Ok(status.into_http())));
        };
        let (parts, body) = req.into_parts();
        let body = Body::new(GuardedBody {
            inner: body,
            slot,
            limits: self.limits,
            idle: Box::pin(tokio::time::sleep(self.limits.stall)),
        });
        // The clone that was made ready is the one called (tower's rule).
        let clone = self.inner.clone();
        let mut inner = std::mem::replace(&mut self.inner, clone);
        let fut = inner.call(http::Request::from_parts(parts, body));
        Box::pin(async move { fut.await.map(|r| conventional_codes(r.map(Body::new))) })
    }
}

/// tonic's codes for bad input, as gRPC's conventions have them.
fn conventional_codes(mut resp: http::Response<Body>) -> http::Response<Body> {
    let Some(status) = Status::from_header_map(resp.headers()) else {
        return resp;
    };
    let msg = status.message();
    let code = match status.code() {
        Code::Internal
            if msg.contains("decode Protobuf")
                || msg.contains("Unexpected EOF decoding")
                || msg.contains("invalid compression flag") =>
        {
            Code::InvalidArgument
        }
        Code::OutOfRange if msg.contains("message length too large") => Code::ResourceExhausted,
        _ => return resp,
    };
    let headers = resp.headers_mut();
    for h in ["grpc-status", "grpc-message", "grpc-status-details-bin"] {
        headers.remove(h);
    }
    if Status::new(code, format!("request: {msg}"))
        .add_header(headers)
        .is_err()
    {
        // Only a message that cannot be a header fails; keep the code at least.
        let _ = Status::new(code, "request: malformed").add_header(headers);
    }
    resp
}

/// One body arriving: counted in [`UploadState`] until it is dropped.
struct Upload {
    state: Arc<UploadState>,
    bytes: usize,
}

impl Upload {
    fn begin(state: &Arc<UploadState>, max: usize) -> Option<Self> {
        state
            .uploads
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n < max).then_some(n + 1)
            })
            .ok()?;
        Some(Self {
            state: state.clone(),
            bytes: 0,
        })
    }

    /// Counts `n` more bytes, or says how many are held if that would pass `max`.
    fn take(&mut self, n: usize, max: usize) -> Result<(), usize> {
        self.state
            .bytes
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |held| {
                (held + n <= max).then_some(held + n)
            })?;
        self.bytes += n;
        Ok(())
    }
}

impl Drop for Upload {
    fn drop(&mut self) {
        self.state.bytes.fetch_sub(self.bytes, Ordering::AcqRel);
        self.state.uploads.fetch_sub(1, Ordering::AcqRel);
    }
}

struct GuardedBody {
    inner: Body,
    slot: Upload,
    limits: UploadLimits,
    idle: Pin<Box<tokio::time::Sleep>>,
}

impl http_body::Body for GuardedBody {
    type Data = Bytes;
    type Error = Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Status>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(data) = frame.data_ref() {
                    if let Err(held) = this.slot.take(data.len(), this.limits.max_upload_bytes) {
                        return Poll::Ready(Some(Err(Status::resource_exhausted(format!(
                            "requests being received hold {held} bytes; this one would pass the \
                             server's limit of {} (retry later)",
                            this.limits.max_upload_bytes
                        )))));
                    }
                }
                let next = tokio::time::Instant::now() + this.limits.stall;
                this.idle.as_mut().reset(next);
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Pending => match this.idle.as_mut().poll(cx) {
                Poll::Ready(()) => Poll::Ready(Some(Err(Status::deadline_exceeded(format!(
                    "the request stopped arriving: nothing for {:?} after {} bytes",
                    this.limits.stall, this.slot.bytes
                ))))),
                Poll::Pending => Poll::Pending,
            },
            other => other,
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}
