//! Reading a render request body in any of the accepted forms.

use std::collections::BTreeMap;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, HttpBody};
use axum::extract::{FromRequest, Multipart, Request};
use axum::http::StatusCode;
use bytes::Bytes;
use futures_util::StreamExt;
use http_body::{Frame, SizeHint};

use super::negotiate::RequestFormat;
use crate::backend::{BackendError, MemoryLease};
use crate::error::ApiError;
use crate::request::{check_json_size, HasSources, ImageMode, Limits, RenderRequest, SceneRequest, TargetRequest};

/// `POST /v1/render` in any of the three forms.
pub async fn read_render_request(
    format: RequestFormat,
    req: Request,
    limits: &Limits,
) -> Result<RenderRequest, ApiError> {
    read_with_sources(format, req, limits, RenderRequest::from_json, RenderRequest::from_protobuf).await
}

/// `POST /v1/scenes` in any of the three forms.
pub async fn read_scene_request(
    format: RequestFormat,
    req: Request,
    limits: &Limits,
) -> Result<SceneRequest, ApiError> {
    read_with_sources(format, req, limits, SceneRequest::from_json, SceneRequest::from_protobuf).await
}

/// A request that carries source images, parsed by `from_json` (JSON with base64 images, or the
/// `request` part of a multipart body) or `from_protobuf`.
async fn read_with_sources<T: HasSources + Send + 'static>(
    format: RequestFormat,
    req: Request,
    limits: &Limits,
    from_json: fn(&[u8], ImageMode, &Limits) -> Result<T, ApiError>,
    from_protobuf: fn(&[u8], &Limits) -> Result<T, ApiError>,
) -> Result<T, ApiError> {
    let limit = limits.max_body_bytes;
    let owned = limits.clone();
    match format {
        RequestFormat::Json => {
            let body = read_bytes(req.into_body(), limit).await?;
            parse_blocking(move || from_json(&body, ImageMode::Inline, &owned)).await
        }
        RequestFormat::Protobuf => {
            let body = read_bytes(req.into_body(), limit).await?;
            parse_blocking(move || from_protobuf(&body, &owned)).await
        }
        RequestFormat::Multipart => read_multipart(req, limits, |json| from_json(json, ImageMode::Parts, limits)).await,
    }
}

/// A body of up to `--max-body-bytes` (base64 images, protobuf) takes CPU time to parse in
/// proportion: off the async workers, so that health checks and other connections stay served.
async fn parse_blocking<T: Send + 'static>(
    parse: impl FnOnce() -> Result<T, ApiError> + Send + 'static,
) -> Result<T, ApiError> {
    tokio::task::spawn_blocking(parse)
        .await
        .map_err(|e| ApiError::Internal(format!("request parsing task failed: {e}")))?
}

/// `POST /v1/scenes/{id}/render`: a small JSON or protobuf document (no images).
pub async fn read_target_request(
    format: RequestFormat,
    req: Request,
    limits: &Limits,
) -> Result<TargetRequest, ApiError> {
    let body = read_bytes(req.into_body(), limits.max_json_bytes).await?;
    match format {
        RequestFormat::Json => TargetRequest::from_json(&body, limits),
        RequestFormat::Protobuf => TargetRequest::from_protobuf(&body),
        RequestFormat::Multipart => Err(ApiError::UnsupportedMediaType {
            field: Some("content-type".into()),
            message: "a scene render request carries no images: send application/json or application/x-protobuf".into(),
        }),
    }
}

/// Reads the whole body, refusing more than `limit` bytes with 413. The bytes go into one
/// buffer of the declared size rather than a list of the frames as they came: no copy at the
/// end, and an abandoned upload frees one large block, which the allocator returns to the
/// system at once, instead of thousands of frames that stay in its heap.
pub async fn read_bytes(body: Body, limit: usize) -> Result<Bytes, ApiError> {
    refuse_declared_length(&body, limit)?;
    let mut buf = Vec::with_capacity(body.size_hint().lower() as usize);
    let mut frames = body.into_data_stream();
    while let Some(frame) = frames.next().await {
        let frame = frame.map_err(|e| body_error(&e, "body"))?;
        if buf.len() + frame.len() > limit {
            return Err(too_large("body", limit));
        }
        buf.extend_from_slice(&frame);
    }
    Ok(Bytes::from(buf))
}

/// Path of the one route with its own body limit (`--max-capture-bytes`).
pub const CAPTURES_PATH: &str = "/v1/captures";

/// The largest body a route takes: a capture's files, or any other request.
pub fn body_limit(limits: &Limits, path: &str) -> usize {
    if path == CAPTURES_PATH {
        limits.max_capture_bytes
    } else {
        limits.max_body_bytes
    }
}

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
struct BodyRefused(BackendError);

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

/// A body whose Content-Length exceeds `limit` is refused before any of it is read.
pub fn refuse_declared_length(body: &Body, limit: usize) -> Result<(), ApiError> {
    if body.size_hint().lower() > limit as u64 {
        return Err(too_large("body", limit));
    }
    Ok(())
}

/// A failure while reading the body: too slow (408), more than the memory budget holds now
/// (503) or ever (413), or broken off or malformed (400).
fn body_error(e: &(dyn std::error::Error + 'static), field: &str) -> ApiError {
    let mut cur: Option<&(dyn std::error::Error + 'static)> = Some(e);
    while let Some(err) = cur {
        if let Some(slow) = err.downcast_ref::<TooSlow>() {
            return ApiError::BodyTimeout { message: slow.to_string() };
        }
        if let Some(BodyRefused(refusal)) = err.downcast_ref::<BodyRefused>() {
            return match refusal {
                BackendError::TooLarge { .. } => ApiError::TooLarge {
                    field: Some(field.to_string()),
                    message: format!("the request body needs {refusal}"),
                },
                other => other.clone().into(),
            };
        }
        cur = err.source();
    }
    ApiError::malformed(Some(field.to_string()), format!("cannot read request body: {e}"))
}

fn too_large(field: &str, limit: usize) -> ApiError {
    ApiError::TooLarge {
        field: Some(field.to_string()),
        message: format!("request body exceeds the limit of {limit} bytes"),
    }
}

/// multipart/form-data: a `request` part (the JSON request without images) and parts
/// `source_0` .. `source_{V-1}` holding the image files (V at most `--max-scene-views`).
async fn read_multipart<T: HasSources>(
    req: Request,
    limits: &Limits,
    parse: impl FnOnce(&[u8]) -> Result<T, ApiError>,
) -> Result<T, ApiError> {
    let limit = limits.max_body_bytes;
    refuse_declared_length(req.body(), limit)?;
    let mut multipart = Multipart::from_request(req, &()).await.map_err(|e| {
        ApiError::malformed(Some("content-type".to_string()), format!("invalid multipart request: {}", e.body_text()))
    })?;
    let mut request_json: Option<Bytes> = None;
    let mut images: BTreeMap<usize, Bytes> = BTreeMap::new();
    loop {
        let field = multipart.next_field().await.map_err(|e| multipart_error(e, "body", limit))?;
        let Some(field) = field else { break };
        let name = field
            .name()
            .map(str::to_string)
            .ok_or_else(|| ApiError::malformed(Some("body".to_string()), "multipart part without a name"))?;
        let data = field.bytes().await.map_err(|e| multipart_error(e, &name, limit))?;
        if name == "request" {
            check_json_size(&data, limits.max_json_bytes, Some("request"))?;
            if request_json.replace(data).is_some() {
                return Err(ApiError::malformed(Some(name), "part sent twice"));
            }
        } else if let Some(index) = source_index(&name) {
            if index >= limits.max_scene_views {
                return Err(too_many_views(&name, limits.max_scene_views));
            }
            if images.insert(index, data).is_some() {
                return Err(ApiError::malformed(Some(name), "part sent twice"));
            }
        } else {
            return Err(ApiError::malformed(
                Some(name.clone()),
                format!("unknown multipart part \"{name}\" (expected request, source_0, source_1, ...)"),
            ));
        }
    }
    let json = request_json
        .ok_or_else(|| ApiError::malformed(Some("request".to_string()), "missing multipart part \"request\""))?;
    let mut request = parse(&json)?;
    let sources = request.sources_mut();
    for (index, data) in images {
        let source = sources.get_mut(index).ok_or_else(|| {
            ApiError::malformed(
                Some(format!("source_{index}")),
                format!("part source_{index} has no matching entry in request.sources"),
            )
        })?;
        source.image = Some(data);
    }
    Ok(request)
}

/// The index of a part named `source_<i>` (decimal, no leading zeros).
fn source_index(name: &str) -> Option<usize> {
    let digits = name.strip_prefix("source_")?;
    let canonical = digits == "0" || !digits.starts_with('0');
    if digits.is_empty() || digits.len() > 9 || !canonical || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    digits.parse().ok()
}

/// A part beyond the scene limit: refused as it arrives, before its image is read.
fn too_many_views(part: &str, max: usize) -> ApiError {
    ApiError::invalid(part, format!("a scene holds at most {max} views (parts source_0 .. source_{})", max - 1))
}

/// `field`: the part being read, or `body` between parts.
pub(super) fn multipart_error(e: axum::extract::multipart::MultipartError, field: &str, limit: usize) -> ApiError {
    if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
        return too_large(field, limit);
    }
    match body_error(&e, field) {
        ApiError::Malformed { .. } => {
            ApiError::malformed(Some(field.to_string()), format!("invalid multipart body: {}", e.body_text()))
        }
        slow_or_refused => slow_or_refused,
    }
}

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
struct TooSlow {
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

#[cfg(test)]
mod tests {
    use super::source_index;

    #[test]
    fn source_part_names() {
        assert_eq!(source_index("source_0"), Some(0));
        assert_eq!(source_index("source_12"), Some(12));
        assert_eq!(source_index("source_640"), Some(640));
        assert_eq!(source_index("source_"), None);
        assert_eq!(source_index("source_x"), None);
        assert_eq!(source_index("source_01"), None);
        assert_eq!(source_index("source_99999999999"), None);
        assert_eq!(source_index("image_0"), None);
    }
}
