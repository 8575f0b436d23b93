//! Render requests: the JSON and protobuf wire forms are parsed into one domain type
//! (`RenderRequest`), then validated against the bundle and the limits (`ValidRequest`).
//!
//! Parsing is strict: unknown fields are errors (nothing the client sent is silently dropped) and
//! every error names the field as a path, e.g. `sources[1].camera.pose.kind`.

use bytes::Bytes;
use serde::{Deserialize, Deserializer};

use crate::bundle::ModelConfig;
use crate::camera::{Axes, Camera, CameraSpec, Intrinsics, Mat3, Mat4, Pose, PoseKind, MAX_WORLD_EXTENT, MIN_NEAR};
use crate::error::ApiError;

/// Request limits (configurable, see config.rs).
#[derive(Debug, Clone)]
pub struct Limits {
    pub max_body_bytes: usize,
    pub max_source_pixels: u64,
    pub max_target_pixels: u64,
    /// Largest JSON document without images: the multipart `request` part and scene-render
    /// bodies. (An `application/json` render body carries base64 images: `max_body_bytes`.)
    pub max_json_bytes: usize,
    /// Deepest accepted nesting of JSON arrays/objects; checked before parsing so that a
    /// pathological document costs one linear scan, not recursion.
    pub max_json_depth: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_body_bytes: 64 << 20,
            max_source_pixels: 1024 * 1024,
            max_target_pixels: 2048 * 2048,
            max_json_bytes: 1 << 20,
            max_json_depth: 16,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum OutputKind {
    Rgb,
    Depth,
    Opacity,
}

impl OutputKind {
    pub fn parse(s: &str) -> Option<OutputKind> {
        match s {
            "rgb" => Some(OutputKind::Rgb),
            "depth" => Some(OutputKind::Depth),
            "opacity" => Some(OutputKind::Opacity),
            _ => None,
        }
    }
}

/// Which outputs the client asked for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OutputSet {
    pub rgb: bool,
    pub depth: bool,
    pub opacity: bool,
}

impl OutputSet {
    pub const RGB: OutputSet = OutputSet { rgb: true, depth: false, opacity: false };

    fn from_kinds(kinds: Option<&[OutputKind]>) -> Result<OutputSet, ApiError> {
        let Some(kinds) = kinds else { return Ok(OutputSet::RGB) };
        if kinds.is_empty() {
            return Err(ApiError::invalid("outputs", "outputs must name at least one of rgb, depth, opacity"));
        }
        let mut set = OutputSet { rgb: false, depth: false, opacity: false };
        for (i, k) in kinds.iter().enumerate() {
            let slot = match k {
                OutputKind::Rgb => &mut set.rgb,
                OutputKind::Depth => &mut set.depth,
                OutputKind::Opacity => &mut set.opacity,
            };
            if *slot {
                return Err(ApiError::invalid(format!("outputs[{i}]"), "output listed twice"));
            }
            *slot = true;
        }
        Ok(set)
    }
}

/// One source view: its camera and, once attached, its encoded image.
#[derive(Debug, Clone)]
pub struct SourceSpec {
    pub camera: CameraSpec,
    pub image: Option<Bytes>,
    /// How the client named the image (`sources[0].image` or the multipart part `source_0`).
    pub image_field: String,
}

/// The scene part of a request (sources and depth range), not yet validated. It is the body of
/// `POST /v1/scenes` and the part of a render request that a scene cache keeps.
#[derive(Debug, Clone)]
pub struct SceneRequest {
    pub sources: Vec<SourceSpec>,
    pub near: f64,
    pub far: f64,
    pub background: Option<Vec<f64>>,
}

/// The view part of a request: the body of `POST /v1/scenes/{id}/render`.
#[derive(Debug, Clone)]
pub struct TargetRequest {
    pub target: CameraSpec,
    pub outputs: Option<Vec<OutputKind>>,
}

/// A parsed, not yet validated, render request (`POST /v1/render`): a scene and a view of it.
#[derive(Debug, Clone)]
pub struct RenderRequest {
    pub scene: SceneRequest,
    pub view: TargetRequest,
}

/// Validated sources: canonical cameras, checked numbers, images present (not yet decoded).
#[derive(Debug, Clone)]
pub struct ValidScene {
    pub sources: Vec<(Camera, Bytes, String)>,
    pub near: f64,
    pub far: f64,
    pub background: [f32; 3],
}

impl ValidScene {
    pub fn cameras(&self) -> Vec<Camera> {
        self.sources.iter().map(|(c, _, _)| c.clone()).collect()
    }
}

/// A validated target view.
#[derive(Debug, Clone)]
pub struct ValidTarget {
    pub target: Camera,
    pub outputs: OutputSet,
}

/// A validated render request.
#[derive(Debug, Clone)]
pub struct ValidRequest {
    pub scene: ValidScene,
    pub view: ValidTarget,
}

// ---------------------------------------------------------------------------------------------
// JSON wire form. These types are the JSON contract: they are what serde parses and what
// /openapi.json describes (utoipa), so the documentation cannot drift from the parser.

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
}

/// `POST /v1/scenes` JSON body (and the `request` part of a multipart body): a render request
/// without `target` and `outputs`.
#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = SceneRequest)]
pub struct JsonSceneRequest {
    #[schema(min_items = 3, max_items = 3)]
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
    k: Option<Mat3>,
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

/// Schema of a 3x3 matrix (`Mat3`).
pub struct Matrix3Rows;

/// Schema of a 4x4 matrix (`Mat4`).
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
    matrix: Mat4,
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
            Mat3::deserialize(SeqAccessDeserializer::new(seq)).map(Intrinsics::Matrix)
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
            (None, Some(k)) => Intrinsics::Matrix(k),
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
            pose: Pose { matrix: self.pose.matrix, kind: self.pose.kind, axes: self.pose.axes },
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
pub fn check_json_depth(body: &[u8], max_depth: usize, root: &str) -> Result<(), ApiError> {
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

/// The parts of a request that carry source views, whatever the endpoint.
pub trait HasSources {
    fn sources_mut(&mut self) -> &mut Vec<SourceSpec>;
}

impl HasSources for SceneRequest {
    fn sources_mut(&mut self) -> &mut Vec<SourceSpec> {
        &mut self.sources
    }
}

impl HasSources for RenderRequest {
    fn sources_mut(&mut self) -> &mut Vec<SourceSpec> {
        &mut self.scene.sources
    }
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
        let view = TargetRequest { target: parsed.target.into_spec("target")?, outputs: parsed.outputs };
        Ok(RenderRequest { scene, view })
    }

    /// Parses the protobuf form.
    pub fn from_protobuf(body: &[u8]) -> Result<RenderRequest, ApiError> {
        use prost::Message;
        proto::check_repeated(body, &[proto::SOURCES, proto::OUTPUTS])?;
        let msg = scnerf_proto::v1::RenderRequest::decode(body).map_err(|e| {
            ApiError::malformed(Some("body".to_string()), format!("invalid protobuf RenderRequest: {e}"))
        })?;
        proto::request_from_proto(msg)
    }

    /// Checks the request against the bundle and the limits and converts the cameras.
    pub fn validate(self, config: &ModelConfig, limits: &Limits) -> Result<ValidRequest, ApiError> {
        // Cheap whole-request checks first, then the target, then the (costlier) sources.
        let header = self.scene.validate_header(config)?;
        let view = self.view.validate(limits)?;
        let scene = self.scene.validate_sources(header, limits)?;
        Ok(ValidRequest { scene, view })
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

    pub fn from_protobuf(body: &[u8]) -> Result<SceneRequest, ApiError> {
        use prost::Message;
        proto::check_repeated(body, &[proto::SOURCES])?;
        let msg = scnerf_proto::v1::SceneRequest::decode(body).map_err(|e| {
            ApiError::malformed(Some("body".to_string()), format!("invalid protobuf SceneRequest: {e}"))
        })?;
        proto::scene_from_proto(msg)
    }

    pub fn validate(self, config: &ModelConfig, limits: &Limits) -> Result<ValidScene, ApiError> {
        let header = self.validate_header(config)?;
        self.validate_sources(header, limits)
    }

    /// View count, depth range and background: everything but the cameras and images.
    fn validate_header(&self, config: &ModelConfig) -> Result<[f32; 3], ApiError> {
        if self.sources.len() != config.views {
            return Err(ApiError::invalid(
                "sources",
                format!("this model takes exactly {} source views, got {}", config.views, self.sources.len()),
            ));
        }
        check_depth_range(self.near, self.far)?;
        check_background(self.background.as_deref())
    }

    fn validate_sources(self, background: [f32; 3], limits: &Limits) -> Result<ValidScene, ApiError> {
        let mut out: Vec<(Camera, Bytes, String)> = Vec::with_capacity(self.sources.len());
        for (i, s) in self.sources.into_iter().enumerate() {
            let field = format!("sources[{i}].camera");
            let camera = s.camera.canonicalize(&field)?;
            if let Some((first, _, _)) = out.first() {
                if (first.width, first.height) != (camera.width, camera.height) {
                    return Err(ApiError::invalid(
                        format!("{field}.width"),
                        format!(
                            "all source views must have the same size: source 0 is {}x{}, source {i} is {}x{}",
                            first.width, first.height, camera.width, camera.height
                        ),
                    ));
                }
            }
            let pixels = u64::from(camera.width) * u64::from(camera.height);
            if pixels > limits.max_source_pixels {
                return Err(ApiError::invalid(
                    format!("{field}.width"),
                    format!(
                        "source view of {}x{} exceeds the limit of {} pixels",
                        camera.width, camera.height, limits.max_source_pixels
                    ),
                ));
            }
            let image = s.image.ok_or_else(|| ApiError::malformed(s.image_field.clone(), "missing source image"))?;
            out.push((camera, image, s.image_field));
        }
        Ok(ValidScene { sources: out, near: self.near, far: self.far, background })
    }
}

impl TargetRequest {
    pub fn from_json(body: &[u8], limits: &Limits) -> Result<TargetRequest, ApiError> {
        let parsed: JsonTargetRequest = parse_json(body, limits.max_json_depth, "scene render request", "body")?;
        Ok(TargetRequest { target: parsed.target.into_spec("target")?, outputs: parsed.outputs })
    }

    pub fn from_protobuf(body: &[u8]) -> Result<TargetRequest, ApiError> {
        use prost::Message;
        proto::check_repeated(body, &[proto::OUTPUTS])?;
        let msg = scnerf_proto::v1::SceneRenderRequest::decode(body).map_err(|e| {
            ApiError::malformed(Some("body".to_string()), format!("invalid protobuf SceneRenderRequest: {e}"))
        })?;
        Ok(TargetRequest {
            target: proto::camera_from_proto(msg.target, "target")?,
            outputs: proto::outputs_from_proto(&msg.outputs)?,
        })
    }

    pub fn validate(self, limits: &Limits) -> Result<ValidTarget, ApiError> {
        let outputs = OutputSet::from_kinds(self.outputs.as_deref())?;
        let target = self.target.canonicalize("target")?;
        let target_pixels = u64::from(target.width) * u64::from(target.height);
        if target_pixels > limits.max_target_pixels {
            return Err(ApiError::invalid(
                "target.width",
                format!(
                    "target view of {}x{} exceeds the limit of {} pixels",
                    target.width, target.height, limits.max_target_pixels
                ),
            ));
        }
        Ok(ValidTarget { target, outputs })
    }
}

fn check_depth_range(near: f64, far: f64) -> Result<(), ApiError> {
    if !near.is_finite() || near <= 0.0 {
        return Err(ApiError::invalid("near", "near must be a finite number > 0"));
    }
    if near < MIN_NEAR {
        return Err(ApiError::invalid("near", format!("near must be at least {MIN_NEAR:e}")));
    }
    if !far.is_finite() {
        return Err(ApiError::invalid("far", "far must be a finite number"));
    }
    if far > MAX_WORLD_EXTENT {
        return Err(ApiError::invalid("far", format!("far must be at most {MAX_WORLD_EXTENT:e}")));
    }
    if near >= far {
        return Err(ApiError::invalid("far", format!("near ({near}) must be smaller than far ({far})")));
    }
    Ok(())
}

fn check_background(bg: Option<&[f64]>) -> Result<[f32; 3], ApiError> {
    let Some(bg) = bg else { return Ok([0.0; 3]) };
    if bg.len() != 3 {
        return Err(ApiError::invalid("background", format!("background must be 3 numbers (RGB), got {}", bg.len())));
    }
    if bg.iter().any(|v| !(0.0..=1.0).contains(v)) {
        return Err(ApiError::invalid("background", "background components must be in [0, 1]"));
    }
    Ok([bg[0] as f32, bg[1] as f32, bg[2] as f32])
}

pub fn decode_base64(s: &str, field: &str) -> Result<Bytes, ApiError> {
    use base64::Engine;
    base64::engine::general_purpose::STANDARD
        .decode(s.trim())
        .map(Bytes::from)
        .map_err(|e| ApiError::malformed(field.to_string(), format!("invalid base64: {e}")))
}

/// Most source views a request may carry, in any form (multipart parts `source_0..15`, protobuf
/// `sources` entries); the model's own view count is checked after parsing.
pub const MAX_SOURCES: usize = 16;

/// Conversion from the protobuf messages.
mod proto {
    use super::*;
    use scnerf_proto::v1 as pb;

    /// A repeated field of the request messages: number, name, most entries a request can use.
    pub type Bound = (u64, &'static str, usize);
    /// Field numbers are shared by RenderRequest, SceneRequest and SceneRenderRequest.
    pub const SOURCES: Bound = (1, "sources", MAX_SOURCES);
    pub const OUTPUTS: Bound = (6, "outputs", 3);

    /// Refuses a message whose repeated fields hold more entries than a request can use, before
    /// prost materialises them: an empty `sources` entry is 2 bytes on the wire and a struct of
    /// ~150 bytes in memory (63 MiB of them took 3.5 GB). One pass over the top-level fields in
    /// constant memory; malformed wire data ends the pass and is left to prost to report.
    pub fn check_repeated(body: &[u8], bounds: &[Bound]) -> Result<(), ApiError> {
        let mut counts = vec![0usize; bounds.len()];
        let mut buf = body;
        while let Some(key) = varint(&mut buf) {
            let skipped = match key & 7 {
                0 => varint(&mut buf).map(drop),
                1 => skip(&mut buf, 8),
                2 => varint(&mut buf).and_then(|len| skip(&mut buf, usize::try_from(len).ok()?)),
                5 => skip(&mut buf, 4),
                _ => None,
            };
            if skipped.is_none() {
                break;
            }
            let Some(i) = bounds.iter().position(|b| b.0 == key >> 3) else { continue };
            counts[i] += 1;
            if counts[i] > bounds[i].2 {
                let (_, name, max) = bounds[i];
                return Err(ApiError::invalid(name, format!("a request carries at most {max} {name} entries")));
            }
        }
        Ok(())
    }

    /// A base-128 varint (at most 10 bytes), advancing `buf`.
    fn varint(buf: &mut &[u8]) -> Option<u64> {
        let mut value = 0u64;
        for (i, &b) in buf.iter().take(10).enumerate() {
            value |= u64::from(b & 0x7f) << (7 * i);
            if b & 0x80 == 0 {
                *buf = &buf[i + 1..];
                return Some(value);
            }
        }
        None
    }

    fn skip(buf: &mut &[u8], n: usize) -> Option<()> {
        *buf = buf.get(n..)?;
        Some(())
    }

    pub fn request_from_proto(msg: pb::RenderRequest) -> Result<RenderRequest, ApiError> {
        let scene = SceneRequest {
            sources: sources_from_proto(msg.sources)?,
            near: msg.near,
            far: msg.far,
            background: (!msg.background.is_empty()).then_some(msg.background),
        };
        let view = TargetRequest {
            target: camera_from_proto(msg.target, "target")?,
            outputs: outputs_from_proto(&msg.outputs)?,
        };
        Ok(RenderRequest { scene, view })
    }

    pub fn scene_from_proto(msg: pb::SceneRequest) -> Result<SceneRequest, ApiError> {
        Ok(SceneRequest {
            sources: sources_from_proto(msg.sources)?,
            near: msg.near,
            far: msg.far,
            background: (!msg.background.is_empty()).then_some(msg.background),
        })
    }

    fn sources_from_proto(sources: Vec<pb::Source>) -> Result<Vec<SourceSpec>, ApiError> {
        let mut out = Vec::with_capacity(sources.len());
        for (i, s) in sources.into_iter().enumerate() {
            let field = format!("sources[{i}]");
            let camera = camera_from_proto(s.camera, &format!("{field}.camera"))?;
            let image = (!s.image.is_empty()).then(|| Bytes::from(s.image));
            out.push(SourceSpec { camera, image, image_field: format!("{field}.image") });
        }
        Ok(out)
    }

    pub fn outputs_from_proto(outputs: &[String]) -> Result<Option<Vec<OutputKind>>, ApiError> {
        if outputs.is_empty() {
            return Ok(None);
        }
        let mut kinds = Vec::with_capacity(outputs.len());
        for (i, o) in outputs.iter().enumerate() {
            kinds.push(OutputKind::parse(o).ok_or_else(|| {
                ApiError::malformed(format!("outputs[{i}]"), format!("unknown output \"{o}\" (rgb, depth, opacity)"))
            })?);
        }
        Ok(Some(kinds))
    }

    pub fn camera_from_proto(c: Option<pb::Camera>, field: &str) -> Result<CameraSpec, ApiError> {
        let c = c.ok_or_else(|| ApiError::malformed(field.to_string(), "missing camera"))?;
        let intrinsics = match c.intrinsics_kind {
            Some(pb::camera::IntrinsicsKind::Intrinsics(i)) => {
                Intrinsics::Focal { fx: i.fx, fy: i.fy, cx: i.cx, cy: i.cy }
            }
            Some(pb::camera::IntrinsicsKind::K(m)) => {
                Intrinsics::Matrix(mat3(&m.values, &format!("{field}.k.values"))?)
            }
            None => return Err(ApiError::malformed(format!("{field}.intrinsics"), "missing intrinsics (or k)")),
        };
        let pose = c.pose.ok_or_else(|| ApiError::malformed(format!("{field}.pose"), "missing pose"))?;
        let kind = match pb::PoseKind::try_from(pose.kind) {
            Ok(pb::PoseKind::WorldToCamera) => PoseKind::WorldToCamera,
            Ok(pb::PoseKind::CameraToWorld) => PoseKind::CameraToWorld,
            _ => {
                return Err(ApiError::malformed(
                    format!("{field}.pose.kind"),
                    "kind must be WORLD_TO_CAMERA or CAMERA_TO_WORLD",
                ))
            }
        };
        let axes = match pb::Axes::try_from(pose.axes) {
            Ok(pb::Axes::Opencv) => Axes::Opencv,
            Ok(pb::Axes::Opengl) => Axes::Opengl,
            _ => return Err(ApiError::malformed(format!("{field}.pose.axes"), "axes must be OPENCV or OPENGL")),
        };
        Ok(CameraSpec {
            width: c.width,
            height: c.height,
            intrinsics,
            pose: Pose { matrix: mat4(&pose.matrix, &format!("{field}.pose.matrix"))?, kind, axes },
        })
    }

    fn mat3(v: &[f64], field: &str) -> Result<Mat3, ApiError> {
        if v.len() != 9 {
            return Err(ApiError::malformed(
                field.to_string(),
                format!("expected 9 values (row-major 3x3), got {}", v.len()),
            ));
        }
        Ok([[v[0], v[1], v[2]], [v[3], v[4], v[5]], [v[6], v[7], v[8]]])
    }

    fn mat4(v: &[f64], field: &str) -> Result<Mat4, ApiError> {
        if v.len() != 16 {
            return Err(ApiError::malformed(
                field.to_string(),
                format!("expected 16 values (row-major 4x4), got {}", v.len()),
            ));
        }
        let mut m = [[0.0; 4]; 4];
        for (i, x) in v.iter().enumerate() {
            m[i / 4][i % 4] = *x;
        }
        Ok(m)
    }
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
    fn protobuf_repeated_fields_are_counted_before_decoding() {
        let empty_sources = [0x0a, 0x00].repeat(17);
        let err = RenderRequest::from_protobuf(&empty_sources).unwrap_err();
        assert_eq!((err.status().as_u16(), err.field()), (422, Some("sources")));
        // Other fields in between are skipped by wire type: varint, 64-bit, bytes, 32-bit.
        let mut outputs = vec![0x18, 0x96, 0x01, 0x21, 0, 0, 0, 0, 0, 0, 0, 0, 0x2d, 0, 0, 0, 0];
        outputs.extend([0x32, 0x03, b'r', b'g', b'b'].repeat(4));
        let err = TargetRequest::from_protobuf(&outputs).unwrap_err();
        assert_eq!(err.field(), Some("outputs"));
        assert!(proto::check_repeated(&[0x0a, 0x00].repeat(16), &[proto::SOURCES]).is_ok());
        // Truncated input is prost's to report.
        assert!(proto::check_repeated(&[0x0a, 0x05, 0x00], &[proto::SOURCES]).is_ok());
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
