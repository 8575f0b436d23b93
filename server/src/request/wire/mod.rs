//! The JSON wire form. These types are the JSON contract: they are what serde parses and what
//! /openapi.json describes (utoipa), so the documentation cannot drift from the parser. Their
//! camera is `scnerf_capture::wire::WireCamera`, the one the client writes and `POST /v1/captures`
//! answers with.
//!
//! A document is read in two steps: `guards` checks its size and nesting and parses it, naming the
//! offending field on failure; `decode` turns it into the domain's requests (cameras as
//! `CameraSpec`, source images inline in base64 or as multipart parts).

mod decode;
mod guards;

use scnerf_capture::wire::WireCamera;
use serde::Deserialize;

use super::OutputKind;

pub use decode::ImageMode;
pub use guards::{check_json_size, parse_json};

/// `POST /v1/render` JSON body (and the `request` part of a multipart body, without images).
#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = RenderRequest)]
pub struct JsonRenderRequest {
    /// Exactly as many views as the model takes (3); view 0 is the reference view.
    #[schema(min_items = 3, max_items = 3)]
    sources: Vec<JsonSource>,
    target: WireCamera,
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
    /// The model to render with: a name `GET /v1/models` lists (default: the server's default
    /// model; an unknown name is 404 `model_not_found`).
    #[serde(default)]
    model: Option<String>,
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
    /// The model the scene belongs to: its renders use it (default: the server's default model).
    #[serde(default)]
    model: Option<String>,
}

/// `POST /v1/scenes/{id}/render` JSON body.
#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = SceneRenderRequest)]
pub struct JsonTargetRequest {
    target: WireCamera,
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
    /// The scene's model (default); another is refused with 409 `model_mismatch`.
    #[serde(default)]
    model: Option<String>,
}

#[derive(Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = Source)]
pub struct JsonSource {
    camera: WireCamera,
    /// Base64 PNG or JPEG (`application/json` bodies only; multipart sends part `source_i`).
    #[serde(default)]
    image: Option<String>,
}
