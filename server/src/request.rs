//! Render requests: the JSON and protobuf wire forms are parsed into one domain type
//! (`RenderRequest`), then validated against the bundle and the limits (`ValidRequest`).
//!
//! Parsing is strict: unknown fields are errors (nothing the client sent is silently dropped) and
//! every error names the field as a path, e.g. `sources[1].camera.pose.kind`.

use bytes::Bytes;
use serde::{Deserialize, Deserializer};

use crate::bundle::ModelConfig;
use crate::camera::{Axes, Camera, CameraSpec, Intrinsics, Mat3, Mat4, Pose, PoseKind};
use crate::error::ApiError;

/// Request limits (configurable, see config.rs).
#[derive(Debug, Clone)]
pub struct Limits {
    pub max_body_bytes: usize,
    pub max_source_pixels: u64,
    pub max_target_pixels: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Limits { max_body_bytes: 64 << 20, max_source_pixels: 1024 * 1024, max_target_pixels: 2048 * 2048 }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
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

    fn from_kinds(kinds: &[OutputKind]) -> Result<OutputSet, ApiError> {
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

/// A parsed, not yet validated, render request.
#[derive(Debug, Clone)]
pub struct RenderRequest {
    pub sources: Vec<SourceSpec>,
    pub target: CameraSpec,
    pub near: f64,
    pub far: f64,
    pub background: Option<Vec<f64>>,
    pub outputs: Option<Vec<OutputKind>>,
}

/// A validated request: canonical cameras, checked numbers, images present (not yet decoded).
#[derive(Debug, Clone)]
pub struct ValidRequest {
    pub sources: Vec<(Camera, Bytes, String)>,
    pub target: Camera,
    pub near: f64,
    pub far: f64,
    pub background: [f32; 3],
    pub outputs: OutputSet,
}

// ---------------------------------------------------------------------------------------------
// JSON wire form

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonRequest {
    sources: Vec<JsonSource>,
    target: JsonCamera,
    near: f64,
    far: f64,
    #[serde(default)]
    background: Option<Vec<f64>>,
    #[serde(default)]
    outputs: Option<Vec<OutputKind>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonSource {
    camera: JsonCamera,
    #[serde(default)]
    image: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonCamera {
    width: u32,
    height: u32,
    #[serde(default, deserialize_with = "intrinsics_or_matrix")]
    intrinsics: Option<Intrinsics>,
    #[serde(default, rename = "K")]
    k: Option<Mat3>,
    pose: JsonPose,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonFocal {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct JsonPose {
    matrix: Mat4,
    kind: PoseKind,
    axes: Axes,
}

/// `intrinsics` is either `{fx, fy, cx, cy}` or a 3x3 matrix.
fn intrinsics_or_matrix<'de, D: Deserializer<'de>>(d: D) -> Result<Option<Intrinsics>, D::Error> {
    use serde::de::Error;
    let value = serde_json::Value::deserialize(d)?;
    let parsed = if value.is_array() {
        serde_json::from_value::<Mat3>(value).map(Intrinsics::Matrix)
    } else {
        serde_json::from_value::<JsonFocal>(value).map(|f| Intrinsics::Focal { fx: f.fx, fy: f.fy, cx: f.cx, cy: f.cy })
    };
    parsed.map(Some).map_err(|e| D::Error::custom(format!("expected {{fx, fy, cx, cy}} or a 3x3 matrix: {e}")))
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

impl RenderRequest {
    /// Parses the JSON form (the JSON body, or the `request` part of a multipart body).
    pub fn from_json(body: &[u8], mode: ImageMode) -> Result<RenderRequest, ApiError> {
        let de = &mut serde_json::Deserializer::from_slice(body);
        let parsed: JsonRequest = serde_path_to_error::deserialize(de).map_err(|e| {
            let path = e.path().to_string();
            let field = if path == "." || path.is_empty() { None } else { Some(path) };
            ApiError::malformed(field, format!("invalid JSON request: {}", e.inner()))
        })?;
        let mut sources = Vec::with_capacity(parsed.sources.len());
        for (i, s) in parsed.sources.into_iter().enumerate() {
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
            sources.push(SourceSpec { camera, image, image_field });
        }
        Ok(RenderRequest {
            sources,
            target: parsed.target.into_spec("target")?,
            near: parsed.near,
            far: parsed.far,
            background: parsed.background,
            outputs: parsed.outputs,
        })
    }

    /// Parses the protobuf form.
    pub fn from_protobuf(body: &[u8]) -> Result<RenderRequest, ApiError> {
        use prost::Message;
        let msg = scnerf_proto::v1::RenderRequest::decode(body)
            .map_err(|e| ApiError::malformed(None, format!("invalid protobuf RenderRequest: {e}")))?;
        proto::request_from_proto(msg)
    }

    /// Checks the request against the bundle and the limits and converts the cameras.
    pub fn validate(self, config: &ModelConfig, limits: &Limits) -> Result<ValidRequest, ApiError> {
        if self.sources.len() != config.views {
            return Err(ApiError::invalid(
                "sources",
                format!("this model takes exactly {} source views, got {}", config.views, self.sources.len()),
            ));
        }
        check_depth_range(self.near, self.far)?;
        let background = check_background(self.background.as_deref())?;
        let outputs = match &self.outputs {
            None => OutputSet::RGB,
            Some(kinds) => OutputSet::from_kinds(kinds)?,
        };
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
        let (near, far) = (self.near, self.far);
        let sources = self.validate_sources(limits)?;
        Ok(ValidRequest { sources, target, near, far, background, outputs })
    }

    fn validate_sources(self, limits: &Limits) -> Result<Vec<(Camera, Bytes, String)>, ApiError> {
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
        Ok(out)
    }
}

fn check_depth_range(near: f64, far: f64) -> Result<(), ApiError> {
    if !near.is_finite() || near <= 0.0 {
        return Err(ApiError::invalid("near", "near must be a finite number > 0"));
    }
    if !far.is_finite() {
        return Err(ApiError::invalid("far", "far must be a finite number"));
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

/// Conversion from the protobuf messages.
mod proto {
    use super::*;
    use scnerf_proto::v1 as pb;

    pub fn request_from_proto(msg: pb::RenderRequest) -> Result<RenderRequest, ApiError> {
        let mut sources = Vec::with_capacity(msg.sources.len());
        for (i, s) in msg.sources.into_iter().enumerate() {
            let field = format!("sources[{i}]");
            let camera = camera_from_proto(s.camera, &format!("{field}.camera"))?;
            let image = (!s.image.is_empty()).then(|| Bytes::from(s.image));
            sources.push(SourceSpec { camera, image, image_field: format!("{field}.image") });
        }
        let outputs = if msg.outputs.is_empty() {
            None
        } else {
            let mut kinds = Vec::new();
            for (i, o) in msg.outputs.iter().enumerate() {
                kinds.push(OutputKind::parse(o).ok_or_else(|| {
                    ApiError::malformed(
                        format!("outputs[{i}]"),
                        format!("unknown output \"{o}\" (rgb, depth, opacity)"),
                    )
                })?);
            }
            Some(kinds)
        };
        Ok(RenderRequest {
            sources,
            target: camera_from_proto(msg.target, "target")?,
            near: msg.near,
            far: msg.far,
            background: (!msg.background.is_empty()).then_some(msg.background),
            outputs,
        })
    }

    fn camera_from_proto(c: Option<pb::Camera>, field: &str) -> Result<CameraSpec, ApiError> {
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
