//! Render requests, in the order they are handled: a wire form (JSON in `wire`, protobuf in
//! `proto`) is parsed into the domain types of `domain`, which `validate` then checks against
//! the bundle and the limits, giving canonical cameras (`ValidRequest`, `ValidScene`,
//! `ValidTarget`).
//!
//! Parsing is strict: unknown fields are errors (nothing the client sent is silently dropped) and
//! every error names the field as a path, e.g. `sources[1].camera.pose.kind`.

pub mod cameras;
mod domain;
mod proto;
mod validate;
pub mod wire;

pub use domain::{
    HasSources, OutputKind, OutputSet, RenderRequest, Sampling, SceneRequest, SourceSpec, TargetRequest, ValidRequest,
    ValidScene, ValidSource, ValidTarget,
};
pub use validate::check_depth_range;
pub use wire::{check_json_size, ImageMode};

/// Request limits (configurable, see config.rs).
#[derive(Debug, Clone)]
pub struct Limits {
    pub max_body_bytes: usize,
    pub max_source_pixels: u64,
    pub max_target_pixels: u64,
    /// Largest JSON document without images: the multipart `request` part, scene-render bodies
    /// and a capture's listing. (An `application/json` render body carries base64 images:
    /// `max_body_bytes`.)
    pub max_json_bytes: usize,
    /// Deepest accepted nesting of JSON arrays/objects; checked before parsing so that a
    /// pathological document costs one linear scan, not recursion.
    pub max_json_depth: usize,
    /// Most views a scene may hold (a capture); also the most source entries or parts any
    /// request may carry, counted before anything is decoded.
    pub max_scene_views: usize,
    /// Largest body of `POST /v1/captures` (every file of a capture).
    pub max_capture_bytes: usize,
    /// Most bytes of a capture's files other than images (transforms, COLMAP models, poses):
    /// they are parsed in memory, images are not.
    pub max_capture_metadata_bytes: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_body_bytes: 64 << 20,
            max_source_pixels: 1024 * 1024,
            max_target_pixels: 2048 * 2048,
            max_json_bytes: 1 << 20,
            max_json_depth: 16,
            max_scene_views: 64,
            max_capture_bytes: 256 << 20,
            max_capture_metadata_bytes: 64 << 20,
        }
    }
}
