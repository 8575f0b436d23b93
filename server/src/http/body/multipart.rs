//! multipart/form-data bodies: the request's JSON in one part, its images in the others.

use std::collections::BTreeMap;

use axum::extract::{FromRequest, Multipart, Request};
use axum::http::StatusCode;
use bytes::Bytes;

use super::read::{body_error, refuse_declared_length, too_large};
use crate::error::ApiError;
use crate::request::{check_json_size, HasSources, Limits};

/// multipart/form-data: a `request` part (the JSON request without images) and parts
/// `source_0` .. `source_{V-1}` holding the image files (V at most `--max-scene-views`).
pub(super) async fn read_multipart<T: HasSources>(
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
