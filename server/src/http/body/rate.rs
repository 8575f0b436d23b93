//! The upload-rate guard: a body that arrives too slowly fails instead of holding its slot.

use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, HttpBody};
use bytes::Bytes;
use http_body::{Frame, SizeHint};

/// How slowly a request body may arrive: any rate for `grace`, then on average at least
/// `min_bytes_per_sec` (each byte received buys 1/min_bytes_per_sec s more), and never `stall`
/// without a byte (bytes sent early buy no right to stall: a client that sent 2 MiB and then
/// nothing would otherwise keep its slot and its bytes for a minute). Separate from the render
/// deadline: a trickling upload would otherwise hold its slot, and the bytes it sent, until the
/// deadline (900 s by default).
#[derive(Debug, Clone, Copy)]
pub struct UploadPolicy {
    pub grace: Duration,
    pub min_bytes_per_sec: u64,
    pub stall: Duration,
}

impl Default for UploadPolicy {
    fn default() -> Self {
        UploadPolicy { grace: Duration::from_secs(30), min_bytes_per_sec: 32 * 1024, stall: Duration::from_secs(10) }
    }
}

impl UploadPolicy {
    /// `body`, failing with `TooSlow` once it falls behind the policy.
    pub fn apply(self, body: Body) -> Body {
        let started = tokio::time::Instant::now();
        Body::new(MinRateBody {
            inner: body,
            policy: self,
            started,
            received: 0,
            timer: Box::pin(tokio::time::sleep_until(self.until(started, started, 0))),
        })
    }

    /// When a body that started at `started` and has received `received` bytes, the last of
    /// them at `last`, falls behind.
    fn until(&self, started: tokio::time::Instant, last: tokio::time::Instant, received: u64) -> tokio::time::Instant {
        let by_rate = self.grace + Duration::from_secs_f64(received as f64 / self.min_bytes_per_sec as f64);
        (started + by_rate).min(last + self.stall)
    }
}

struct MinRateBody {
    inner: Body,
    policy: UploadPolicy,
    started: tokio::time::Instant,
    received: u64,
    /// Fires when the body, at `received` bytes, falls behind the policy.
    timer: Pin<Box<tokio::time::Sleep>>,
}

/// The error a too slow body fails with (found again in the error chain by `body_error`).
#[derive(Debug, thiserror::Error)]
#[error(
    "the request body arrived too slowly: {received} bytes in {secs} s (any rate for the first {grace} s, then at least \
     {rate} bytes/s, and never {stall} s without a byte)"
)]
pub(super) struct TooSlow {
    received: u64,
    secs: u64,
    grace: u64,
    rate: u64,
    stall: u64,
}

impl HttpBody for MinRateBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, axum::Error>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(data) = frame.data_ref() {
                    this.received += data.len() as u64;
                    let until = this.policy.until(this.started, tokio::time::Instant::now(), this.received);
                    this.timer.as_mut().reset(until);
                }
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Pending if this.timer.as_mut().poll(cx).is_ready() => {
                Poll::Ready(Some(Err(axum::Error::new(TooSlow {
                    received: this.received,
                    secs: this.started.elapsed().as_secs(),
                    grace: this.policy.grace.as_secs(),
                    rate: this.policy.min_bytes_per_sec,
                    stall: this.policy.stall.as_secs(),
                }))))
            }
            other => other,
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}
