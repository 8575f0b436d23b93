//! Reading a request body in any of the accepted forms, and guarding it while it arrives.
//!
//! A POST or PUT body passes two guards before its handler reads a byte (the in-flight layer,
//! `middleware::limit_in_flight`, puts them on): `rate` fails it once it arrives more slowly than
//! [`UploadPolicy`] allows, and `memory` holds its bytes against the memory budget as they arrive
//! ([`BodyUse`]). Each fails the body with an error type of its own, which `read` finds again in
//! the error chain: whichever reader meets the failure (a whole body, a multipart part) answers
//! with the same status (408 too slow, 503 the budget in use, 413 more than it ever holds).
//!
//! The handler then reads the body in the form its Content-Type names (`negotiate`): JSON and
//! protobuf whole, within the route's limit (`read`), and parsed off the async workers; multipart
//! part by part (`multipart`: the request's JSON, then its images; `capture`: a capture folder's
//! files).

mod capture;
mod held;
mod multipart;
mod rate;
mod read;

use axum::extract::Request;

use super::negotiate::RequestFormat;
use crate::error::ApiError;
use crate::request::{HasSources, ImageMode, Limits, RenderRequest, SceneRequest, TargetRequest};
use multipart::read_multipart;

pub use capture::read_capture_files;
pub use held::BodyUse;
pub use rate::UploadPolicy;
pub use read::{body_limit, read_bytes, refuse_declared_length, CAPTURES_PATH, CAPTURE_PLAN_PATH};

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
