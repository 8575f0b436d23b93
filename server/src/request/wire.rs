//! The JSON wire form. These types are the JSON contract: they are what serde parses and what
//! /openapi.json describes (utoipa), so the documentation cannot drift from the parser.

use bytes::Bytes;
use serde::{Deserialize, Deserializer};

use super::{Limits, OutputKind, RenderRequest, SceneRequest, SourceSpec, TargetRequest};
use crate::camera::{from_rows, Axes, CameraSpec, Intrinsics, Pose, PoseKind};

/// A 3x3 matrix on the wire: rows.
type Rows3 = [[f64; 3]; 3];
/// A 4x4 matrix on the wire: rows.
type Rows4 = [[f64; 4]; 4];
use crate::error::ApiError;

/// `POST /v1/render` JSON body (and the `request` part of a multipart body, without images).
#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = RenderRequest)]
pub struct JsonRenderRequest {
    /// Exactly as many views as the model takes (3); view 0 is the reference view.
    #[schema(min_items = 3, max_items = 3)]
    sources: Vec<JsonSource>,
    target: JsonCamera,
    /// Depth range of the scene along the reference view's axis; 0 < near < far.
    #[schema(exclusive_minimum = 0.0)]
    near: f64,
    #[schema(exclusive_minimum = 0.0)]
    far: f64,
    /// RGB in [0, 1] that transparent source pixels and empty space are composited on (default black).
    #[serde(default)]
    #[schema(min_items = 3, max_items = 3)]
    background: Option<Vec<f64>>,
    /// Subset of rgb, depth, opacity (default `["rgb"]`).
    #[serde(default)]
    #[schema(min_items = 1, max_items = 3)]
    outputs: Option<Vec<OutputKind>>,
    /// `full` (the paper's uniform samples on every ray) or `guided` (coarse to fine: the network
    /// near the surface only); default: the server's (`GET /v1/model`).
    #[serde(default)]
    #[schema(pattern = "^(full|guided)$")]
    sampling: Option<String>,
}

/// `POST /v1/scenes` and `PUT /v1/scenes/{id}` JSON body (and the `request` part of a multipart
/// body): a render request without `target` and `outputs`, with 3 views or a whole capture.
#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = SceneRequest)]
pub struct JsonSceneRequest {
    /// 3 views (rendered from in this order, view 0 the reference), or a capture of up to
    /// `max_scene_views` (GET /v1/model) views, from which each render picks 3.
    #[schema(min_items = 3)]
    sources: Vec<JsonSource>,
    #[schema(exclusive_minimum = 0.0)]
    near: f64,
    #[schema(exclusive_minimum = 0.0)]
    far: f64,
    #[serde(default)]
    #[schema(min_items = 3, max_items = 3)]
    background: Option<Vec<f64>>,
}

/// `POST /v1/scenes/{id}/render` JSON body.
#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = SceneRenderRequest)]
pub struct JsonTargetRequest {
    target: JsonCamera,
    #[serde(default)]
    #[schema(min_items = 1, max_items = 3)]
    outputs: Option<Vec<OutputKind>>,
    /// The scene's views to render from (indices in upload order, the volume's reference
    /// first). Default: a scene of 3 views renders from them in upload order; a larger scene
    /// from the 3 views nearest the target by camera-centre distance, among those facing its way.
    #[serde(default)]
    #[schema(min_items = 3, max_items = 3)]
    sources: Option<Vec<u32>>,
    /// As in `RenderRequest`.
    #[serde(default)]
    #[schema(pattern = "^(full|guided)$")]
    sampling: Option<String>,
}

#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = Source)]
pub struct JsonSource {
    camera: JsonCamera,
    /// Base64 PNG or JPEG (`application/json` bodies only; multipart sends part `source_i`).
    #[serde(default)]
    image: Option<String>,
}

#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = Camera)]
pub struct JsonCamera {
    #[schema(minimum = 1)]
    width: u32,
    #[schema(minimum = 1)]
    height: u32,
    /// `{fx, fy, cx, cy}` or a 3x3 matrix (rows); give this or `K`.
    #[serde(default, deserialize_with = "intrinsics_or_matrix")]
    #[schema(value_type = Option<JsonIntrinsicsSchema>)]
    intrinsics: Option<Intrinsics>,
    /// 3x3 intrinsic matrix (rows), instead of `intrinsics`.
    #[serde(default, rename = "K")]
    #[schema(value_type = Option<Matrix3Rows>)]
    k: Option<Rows3>,
    pose: JsonPose,
}

/// Schema of `intrinsics` (the parser is `intrinsics_or_matrix`).
#[derive(utoipa::ToSchema)]
#[schema(as = Intrinsics)]
#[allow(dead_code)]
pub enum JsonIntrinsicsSchema {
    Focal(JsonFocal),
    Matrix(Matrix3Rows),
}

/// An `n` x `n` matrix as `n` rows of `n` numbers (what serde's fixed-size arrays accept).
fn square_matrix_schema(n: usize) -> utoipa::openapi::schema::Array {
    use utoipa::openapi::schema::{ArrayBuilder, ObjectBuilder, Type};
    let row =
        ArrayBuilder::new().items(ObjectBuilder::new().schema_type(Type::Number)).min_items(Some(n)).max_items(Some(n));
    ArrayBuilder::new().items(row).min_items(Some(n)).max_items(Some(n)).build()
}

/// Schema of a 3x3 matrix (`Rows3`).
pub struct Matrix3Rows;

/// Schema of a 4x4 matrix (`Rows4`).
pub struct Matrix4Rows;

impl utoipa::PartialSchema for Matrix3Rows {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        square_matrix_schema(3).into()
    }
}

impl utoipa::ToSchema for Matrix3Rows {}

impl utoipa::PartialSchema for Matrix4Rows {
    fn schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
        square_matrix_schema(4).into()
    }
}

impl utoipa::ToSchema for Matrix4Rows {}

#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = Focal)]
pub struct JsonFocal {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = Pose)]
pub struct JsonPose {
    /// 4x4, row-major (a list of 4 rows of 4 numbers).
    #[schema(value_type = Matrix4Rows)]
    matrix: Rows4,
    #[schema(value_type = String, pattern = "^(world_to_camera|camera_to_world)$")]
    kind: PoseKind,
    #[schema(value_type = String, pattern = "^(opencv|opengl)$")]
    axes: Axes,
}

/// `intrinsics` is either `{fx, fy, cx, cy}` or a 3x3 matrix. Read straight from the document
/// (not through `serde_json::Value`, whose maps keep the last of duplicate keys), so that a
/// duplicate `fx` is refused like every other duplicate field.
fn intrinsics_or_matrix<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Intrinsics>, D::Error> {
    use serde::de::value::{MapAccessDeserializer, SeqAccessDeserializer};
    use serde::de::{MapAccess, SeqAccess, Visitor};
    struct FocalOrMatrix;
    impl<'de> Visitor<'de> for FocalOrMatrix {
        type Value = Intrinsics;

        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("{fx, fy, cx, cy} or a 3x3 matrix")
        }

        fn visit_seq<A: SeqAccess<'de>>(self, seq: A) -> Result<Intrinsics, A::Error> {
            Rows3::deserialize(SeqAccessDeserializer::new(seq)).map(|rows| Intrinsics::Matrix(from_rows(&rows)))
        }

        fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<Intrinsics, A::Error> {
            let f = JsonFocal::deserialize(MapAccessDeserializer::new(map))?;
            Ok(Intrinsics::Focal { fx: f.fx, fy: f.fy, cx: f.cx, cy: f.cy })
        }
    }
    d.deserialize_any(FocalOrMatrix).map(Some)
}

impl JsonCamera {
    fn into_spec(self, field: &str) -> Result<CameraSpec, ApiError> {
        let intrinsics = match (self.intrinsics, self.k) {
            (Some(i), None) => i,
            (None, Some(k)) => Intrinsics::Matrix(from_rows(&k)),
            (Some(_), Some(_)) => {
                return Err(ApiError::malformed(format!("{field}.K"), "give either intrinsics or K, not both"))
            }
            (None, None) => {
                return Err(ApiError::malformed(format!("{field}.intrinsics"), "missing field `intrinsics` (or `K`)"))
            }
        };
        Ok(CameraSpec {
            width: self.width,
            height: self.height,
            intrinsics,
            pose: Pose { matrix: from_rows(&self.pose.matrix), kind: self.pose.kind, axes: self.pose.axes },
        })
    }
}

/// Where source images come from in a JSON document.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ImageMode {
    /// `application/json`: each source carries a base64 `image`.
    Inline,
    /// multipart: images arrive as parts `source_i`; an `image` field is an error.
    Parts,
}

/// Parses a JSON document into `T`, naming the offending field on failure. The nesting depth is
/// checked first (a linear scan), so deeply nested input never reaches the recursive parser.
/// `root` names the whole document in errors about it (`body`, or the multipart part `request`).
fn parse_json<T: serde::de::DeserializeOwned>(
    body: &[u8],
    max_depth: usize,
    what: &str,
    root: &str,
) -> Result<T, ApiError> {
    check_json_depth(body, max_depth, root)?;
    let mut de = serde_json::Deserializer::from_slice(body);
    let value = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        let message = e.inner().to_string();
        let field = error_field(&e.path().to_string(), &message).unwrap_or_else(|| root.to_string());
        ApiError::malformed(Some(field), format!("invalid JSON {what}: {message}"))
    })?;
    // One document, nothing after it (serde stops at the end of the first value).
    de.end().map_err(|e| ApiError::malformed(Some(root.to_string()), format!("invalid JSON {what}: {e}")))?;
    Ok(value)
}

/// The field a serde error is about: its path, completed with the name of a missing field
/// (serde reports those at the enclosing object). `None`: the document as a whole.
fn error_field(path: &str, message: &str) -> Option<String> {
    // serde_path_to_error writes `?` for a segment it never learnt (input cut inside a key).
    let path = path.trim_end_matches('?').trim_end_matches('.');
    let path = if path == "." { "" } else { path };
    let missing = message.strip_prefix("missing field `").and_then(|m| m.split('`').next());
    match (path.is_empty(), missing) {
        (true, None) => None,
        (true, Some(name)) => Some(name.to_string()),
        (false, None) => Some(path.to_string()),
        (false, Some(name)) => Some(format!("{path}.{name}")),
    }
}

/// The name of the JSON document in errors: a JSON body, or the multipart `request` part.
fn json_root(mode: ImageMode) -> &'static str {
    match mode {
        ImageMode::Inline => "body",
        ImageMode::Parts => "request",
    }
}

/// Refuses JSON nested deeper than `max_depth` arrays/objects (brackets inside strings do not
/// count). Malformed input passes through: the parser reports it with a better message.
fn check_json_depth(body: &[u8], max_depth: usize, root: &str) -> Result<(), ApiError> {
    let (mut depth, mut in_string, mut escaped) = (0usize, false, false);
    for &b in body {
        if in_string {
            match (escaped, b) {
                (true, _) => escaped = false,
                (false, b'\\') => escaped = true,
                (false, b'"') => in_string = false,
                _ => {}
            }
            continue;
        }
        match b {
            b'"' => in_string = true,
            b'[' | b'{' => {
                depth += 1;
                if depth > max_depth {
                    return Err(ApiError::malformed(
                        Some(root.to_string()),
                        format!("JSON nested deeper than the limit of {max_depth} levels"),
                    ));
                }
            }
            b']' | b'}' => depth = depth.saturating_sub(1),
            _ => {}
        }
    }
    Ok(())
}

/// Refuses a JSON document (without images) larger than the limit, naming where it came from.
pub fn check_json_size(body: &[u8], limit: usize, field: Option<&str>) -> Result<(), ApiError> {
    if body.len() > limit {
        return Err(ApiError::TooLarge {
            field: field.map(str::to_string),
            message: format!("JSON document of {} bytes exceeds the limit of {limit} bytes", body.len()),
        });
    }
    Ok(())
}

fn sources_from_json(sources: Vec<JsonSource>, mode: ImageMode) -> Result<Vec<SourceSpec>, ApiError> {
    let mut out = Vec::with_capacity(sources.len());
    for (i, s) in sources.into_iter().enumerate() {
        let camera = s.camera.into_spec(&format!("sources[{i}].camera"))?;
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
        };
        let view = TargetRequest {
            target: parsed.target.into_spec("target")?,
            outputs: parsed.outputs,
            sources: None,
            sampling: parsed.sampling,
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
        })
    }
}

impl TargetRequest {
    pub fn from_json(body: &[u8], limits: &Limits) -> Result<TargetRequest, ApiError> {
        let parsed: JsonTargetRequest = parse_json(body, limits.max_json_depth, "scene render request", "body")?;
        Ok(TargetRequest {
            target: parsed.target.into_spec("target")?,
            outputs: parsed.outputs,
            sources: parsed.sources,
            sampling: parsed.sampling,
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_depth_counts_brackets_outside_strings() {
        assert!(check_json_depth(br#"{"a": [[1], {"b": 2}]}"#, 3, "body").is_ok());
        assert!(check_json_depth(br#"{"a": [[1], {"b": 2}]}"#, 2, "body").is_err());
        assert!(check_json_depth(br#"{"a": "[[[[[[\"[[[["}"#, 1, "body").is_ok());
        let deep = "[".repeat(100_000);
        let err = check_json_depth(deep.as_bytes(), 16, "request").unwrap_err();
        assert_eq!(err.field(), Some("request"));
    }

    #[test]
    fn serde_errors_name_the_field() {
        assert_eq!(error_field(".", "missing field `near`"), Some("near".into()));
        assert_eq!(error_field("target.pose", "missing field `axes`"), Some("target.pose.axes".into()));
        assert_eq!(error_field("sources[1]", "invalid type"), Some("sources[1]".into()));
        assert_eq!(error_field(".", "expected value"), None);
        assert_eq!(error_field("sources[0].camera.?", "EOF while parsing"), Some("sources[0].camera".into()));
    }
}
