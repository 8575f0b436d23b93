//! Reading a whole body within its route's limit, and the answer to a read that fails.

use axum::body::{Body, HttpBody};
use bytes::Bytes;
use futures_util::StreamExt;

use super::held::BodyRefused;
use super::rate::TooSlow;
use crate::backend::BackendError;
use crate::error::ApiError;
use crate::request::Limits;

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

/// Path of the one route with a body limit larger than the others' (`--max-capture-bytes`).
pub const CAPTURES_PATH: &str = "/v1/captures";

/// Path of the route whose body is a capture's listing, a JSON document (`--max-json-bytes`).
pub const CAPTURE_PLAN_PATH: &str = "/v1/captures/plan";

/// The largest body a route takes: a capture's files, a capture's listing, or any other request.
pub fn body_limit(limits: &Limits, path: &str) -> usize {
    match path {
        CAPTURES_PATH => limits.max_capture_bytes,
        CAPTURE_PLAN_PATH => limits.max_json_bytes,
        _ => limits.max_body_bytes,
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
pub(super) fn body_error(e: &(dyn std::error::Error + 'static), field: &str) -> ApiError {
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

pub(super) fn too_large(field: &str, limit: usize) -> ApiError {
    ApiError::TooLarge {
        field: Some(field.to_string()),
        message: format!("request body exceeds the limit of {limit} bytes"),
    }
}
