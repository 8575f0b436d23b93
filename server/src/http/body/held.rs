//! A body's bytes held against the memory budget as they arrive.

use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};

use axum::body::{Body, HttpBody};
use bytes::Bytes;
use http_body::{Frame, SizeHint};

use crate::backend::{BackendError, MemoryLease};

/// What a request's body holds and whether it was read to its end; shared between the body (as
/// the handler reads it) and the in-flight layer, which keeps it until the answer is ready.
pub struct BodyUse {
    /// The body's bytes as they arrive, held against the memory budget: they stay in memory
    /// (parsed, or as the images of the request) until it is answered.
    lease: std::sync::Mutex<MemoryLease>,
    ended: AtomicBool,
}

impl BodyUse {
    /// `body`, whose bytes grow `lease` as they arrive (a body the budget cannot hold fails
    /// with `BodyRefused`), and its use.
    pub fn track(body: Body, lease: MemoryLease) -> (Body, Arc<BodyUse>) {
        let used =
            Arc::new(BodyUse { lease: std::sync::Mutex::new(lease), ended: AtomicBool::new(body.is_end_stream()) });
        (Body::new(HeldBody { inner: body, used: used.clone() }), used)
    }

    /// Whether the body was read to its end.
    pub fn ended(&self) -> bool {
        self.ended.load(Ordering::Acquire)
    }

    fn hold(&self, bytes: usize) -> Result<(), BackendError> {
        self.lease.lock().unwrap_or_else(|p| p.into_inner()).grow(bytes as u64)
    }
}

struct HeldBody {
    inner: Body,
    used: Arc<BodyUse>,
}

/// The error a body fails with when the memory budget cannot hold it (found again in the error
/// chain by `body_error`).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub(super) struct BodyRefused(pub(super) BackendError);

impl HttpBody for HeldBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        let this = &mut *self;
        let polled = Pin::new(&mut this.inner).poll_frame(cx);
        match &polled {
            Poll::Ready(Some(Ok(frame))) => {
                if let Err(e) = frame.data_ref().map_or(Ok(()), |data| this.used.hold(data.len())) {
                    return Poll::Ready(Some(Err(axum::Error::new(BodyRefused(e)))));
                }
                if this.inner.is_end_stream() {
                    this.used.ended.store(true, Ordering::Release);
                }
            }
            Poll::Ready(None) => this.used.ended.store(true, Ordering::Release),
            _ => {}
        }
        polled
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}
