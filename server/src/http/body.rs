//! Reading a render request body in any of the accepted forms.

use std::collections::BTreeMap;

use axum::body::Body;
use axum::extract::{FromRequest, Multipart, Request};
use axum::http::StatusCode;
use bytes::Bytes;

use super::negotiate::RequestFormat;
use crate::error::ApiError;
use crate::request::{check_json_size, HasSources, ImageMode, Limits, RenderRequest, SceneRequest, TargetRequest};

/// Largest number of `source_i` parts we look at; more is an error, not a loop.
const MAX_SOURCE_PARTS: usize = 16;

/// `POST /v1/render` in any of the three forms.
pub async fn read_render_request(
    format: RequestFormat,
    req: Request,
    limits: &Limits,
) -> Result<RenderRequest, ApiError> {
    let limit = limits.max_body_bytes;
    match format {
        RequestFormat::Json => {
            RenderRequest::from_json(&read_bytes(req.into_body(), limit).await?, ImageMode::Inline, limits)
        }
        RequestFormat::Protobuf => RenderRequest::from_protobuf(&read_bytes(req.into_body(), limit).await?),
        RequestFormat::Multipart => {
            read_multipart(req, limits, |json| RenderRequest::from_json(json, ImageMode::Parts, limits)).await
        }
    }
}

/// `POST /v1/scenes` in any of the three forms.
pub async fn read_scene_request(
    format: RequestFormat,
    req: Request,
    limits: &Limits,
) -> Result<SceneRequest, ApiError> {
    let limit = limits.max_body_bytes;
    match format {
        RequestFormat::Json => {
            SceneRequest::from_json(&read_bytes(req.into_body(), limit).await?, ImageMode::Inline, limits)
        }
        RequestFormat::Protobuf => SceneRequest::from_protobuf(&read_bytes(req.into_body(), limit).await?),
        RequestFormat::Multipart => {
            read_multipart(req, limits, |json| SceneRequest::from_json(json, ImageMode::Parts, limits)).await
        }
    }
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

/// Reads the whole body, refusing more than `limit` bytes with 413.
pub async fn read_bytes(body: Body, limit: usize) -> Result<Bytes, ApiError> {
    axum::body::to_bytes(body, limit).await.map_err(|e| {
        if is_length_limit(&e) {
            too_large("body", limit)
        } else {
            ApiError::malformed(Some("body".to_string()), format!("cannot read request body: {e}"))
        }
    })
}

fn is_length_limit(e: &(dyn std::error::Error + 'static)) -> bool {
    let mut cur: Option<&(dyn std::error::Error + 'static)> = Some(e);
    while let Some(err) = cur {
        if err.is::<http_body_util::LengthLimitError>() {
            return true;
        }
        cur = err.source();
    }
    false
}

fn too_large(field: &str, limit: usize) -> ApiError {
    ApiError::TooLarge {
        field: Some(field.to_string()),
        message: format!("request body exceeds the limit of {limit} bytes"),
    }
}

/// multipart/form-data: a `request` part (the JSON request without images) and parts
/// `source_0` .. `source_{V-1}` holding the image files.
async fn read_multipart<T: HasSources>(
    req: Request,
    limits: &Limits,
    parse: impl FnOnce(&[u8]) -> Result<T, ApiError>,
) -> Result<T, ApiError> {
    let limit = limits.max_body_bytes;
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

fn source_index(name: &str) -> Option<usize> {
    let digits = name.strip_prefix("source_")?;
    if digits.is_empty() || digits.len() > 2 || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    digits.parse().ok().filter(|&i| i < MAX_SOURCE_PARTS)
}

/// `field`: the part being read, or `body` between parts.
fn multipart_error(e: axum::extract::multipart::MultipartError, field: &str, limit: usize) -> ApiError {
    if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
        too_large(field, limit)
    } else {
        ApiError::malformed(Some(field.to_string()), format!("invalid multipart body: {}", e.body_text()))
    }
}

#[cfg(test)]
mod tests {
    use super::source_index;

    #[test]
    fn source_part_names() {
        assert_eq!(source_index("source_0"), Some(0));
        assert_eq!(source_index("source_12"), Some(12));
        assert_eq!(source_index("source_"), None);
        assert_eq!(source_index("source_x"), None);
        assert_eq!(source_index("source_99"), None);
        assert_eq!(source_index("image_0"), None);
    }
}
