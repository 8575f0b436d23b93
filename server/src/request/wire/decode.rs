//! JSON documents into the domain's requests: cameras as `CameraSpec`, source images inline
//! (base64) or as multipart parts.

use bytes::Bytes;

use super::guards::parse_json;
use super::{JsonRenderRequest, JsonSceneRequest, JsonSource, JsonTargetRequest};
use crate::error::ApiError;
use crate::request::cameras::CameraSpec;
use crate::request::{Limits, RenderRequest, SceneRequest, SourceSpec, TargetRequest};

/// Where source images come from in a JSON document.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ImageMode {
    /// `application/json`: each source carries a base64 `image`.
    Inline,
    /// multipart: images arrive as parts `source_i`; an `image` field is an error.
    Parts,
}

/// The name of the JSON document in errors: a JSON body, or the multipart `request` part.
fn json_root(mode: ImageMode) -> &'static str {
    match mode {
        ImageMode::Inline => "body",
        ImageMode::Parts => "request",
    }
}

fn sources_from_json(sources: Vec<JsonSource>, mode: ImageMode) -> Result<Vec<SourceSpec>, ApiError> {
    let mut out = Vec::with_capacity(sources.len());
    for (i, s) in sources.into_iter().enumerate() {
        let camera = CameraSpec::from_wire(&s.camera, &format!("sources[{i}].camera"))?;
        let (image, image_field) = match (mode, s.image) {
            (ImageMode::Inline, Some(b64)) => {
                (Some(decode_base64(&b64, &format!("sources[{i}].image"))?), format!("sources[{i}].image"))
            }
            (ImageMode::Inline, None) => (None, format!("sources[{i}].image")),
            (ImageMode::Parts, Some(_)) => {
                return Err(ApiError::malformed(
                    format!("sources[{i}].image"),
                    format!(
                        "multipart requests carry images as parts; send part source_{i} instead of sources[{i}].image"
                    ),
                ))
            }
            (ImageMode::Parts, None) => (None, format!("source_{i}")),
        };
        out.push(SourceSpec { camera, image, image_field });
    }
    Ok(out)
}

impl RenderRequest {
    /// Parses the JSON form (the JSON body, or the `request` part of a multipart body).
    pub fn from_json(body: &[u8], mode: ImageMode, limits: &Limits) -> Result<RenderRequest, ApiError> {
        let parsed: JsonRenderRequest = parse_json(body, limits.max_json_depth, "request", json_root(mode))?;
        let scene = SceneRequest {
            sources: sources_from_json(parsed.sources, mode)?,
            near: parsed.near,
            far: parsed.far,
            background: parsed.background,
            model: parsed.model,
        };
        let view = TargetRequest {
            target: CameraSpec::from_wire(&parsed.target, "target")?,
            outputs: parsed.outputs,
            sources: None,
            sampling: parsed.sampling,
            model: None,
        };
        Ok(RenderRequest { scene, view })
    }
}

impl SceneRequest {
    pub fn from_json(body: &[u8], mode: ImageMode, limits: &Limits) -> Result<SceneRequest, ApiError> {
        let parsed: JsonSceneRequest = parse_json(body, limits.max_json_depth, "scene request", json_root(mode))?;
        Ok(SceneRequest {
            sources: sources_from_json(parsed.sources, mode)?,
            near: parsed.near,
            far: parsed.far,
            background: parsed.background,
            model: parsed.model,
        })
    }
}

impl TargetRequest {
    pub fn from_json(body: &[u8], limits: &Limits) -> Result<TargetRequest, ApiError> {
        let parsed: JsonTargetRequest = parse_json(body, limits.max_json_depth, "scene render request", "body")?;
        Ok(TargetRequest {
            target: CameraSpec::from_wire(&parsed.target, "target")?,
            outputs: parsed.outputs,
            sources: parsed.sources,
            sampling: parsed.sampling,
            model: parsed.model,
        })
    }
}

fn decode_base64(s: &str, field: &str) -> Result<Bytes, ApiError> {
    use base64::Engine;
    base64::engine::general_purpose::STANDARD
        .decode(s.trim())
        .map(Bytes::from)
        .map_err(|e| ApiError::malformed(field.to_string(), format!("invalid base64: {e}")))
}
