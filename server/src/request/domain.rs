//! What a request asks for, whatever its wire form: parsed (`RenderRequest`, `SceneRequest`,
//! `TargetRequest`) and then validated (`ValidRequest`, `ValidScene`, `ValidTarget`).

use bytes::Bytes;
use serde::{Deserialize, Serialize};

use super::cameras::CameraSpec;
use crate::camera::CanonicalCamera;

/// How a view's rays are sampled.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, utoipa::ToSchema, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Sampling {
    /// The paper's S uniform samples on every ray.
    Full,
    /// Coarse to fine: the network near the surface only (`pipeline::guided`).
    Guided,
}

impl Sampling {
    pub const ALL: [Sampling; 2] = [Sampling::Full, Sampling::Guided];

    pub fn name(self) -> &'static str {
        match self {
            Sampling::Full => "full",
            Sampling::Guided => "guided",
        }
    }

    pub fn parse(s: &str) -> Option<Sampling> {
        Sampling::ALL.into_iter().find(|m| m.name() == s)
    }
}

impl std::fmt::Display for Sampling {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
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
    /// The model named (a render request's too); `None`: the default. Resolved by the handler
    /// before validation, which needs the model's config.
    pub model: Option<String>,
}

/// The view part of a request: the body of `POST /v1/scenes/{id}/render`.
#[derive(Debug, Clone)]
pub struct TargetRequest {
    pub target: CameraSpec,
    pub outputs: Option<Vec<OutputKind>>,
    /// Views of the scene to render from (indices, the volume's reference first) instead of the
    /// server's choice; checked against the scene when it is rendered.
    pub sources: Option<Vec<u32>>,
    /// `full` or `guided` as sent (checked by `validate`); `None`: the server's default.
    pub sampling: Option<String>,
    /// The model named; `None`: the scene's. (A render request's model is its scene's.)
    pub model: Option<String>,
}

/// A parsed, not yet validated, render request (`POST /v1/render`): a scene and a view of it.
#[derive(Debug, Clone)]
pub struct RenderRequest {
    pub scene: SceneRequest,
    pub view: TargetRequest,
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

/// A validated source view: its canonical camera and its image (present, not yet decoded).
#[derive(Debug, Clone)]
pub struct ValidSource {
    pub camera: CanonicalCamera,
    pub image: Bytes,
    /// How the client named the image: errors found when decoding it name this field.
    pub image_field: String,
}

/// Validated sources: canonical cameras, checked numbers, images present.
#[derive(Debug, Clone)]
pub struct ValidScene {
    pub sources: Vec<ValidSource>,
    pub near: f64,
    pub far: f64,
    pub background: [f32; 3],
}

impl ValidScene {
    pub fn cameras(&self) -> Vec<CanonicalCamera> {
        self.sources.iter().map(|s| s.camera.clone()).collect()
    }
}

/// A validated target view.
#[derive(Debug, Clone)]
pub struct ValidTarget {
    pub target: CanonicalCamera,
    pub outputs: OutputSet,
    /// Pinned views, not yet checked against a scene (see `pipeline::views::choose`).
    pub sources: Option<Vec<u32>>,
    /// The sampling asked for; `None`: the server's default (the pipeline checks the bundle can).
    pub sampling: Option<Sampling>,
}

/// A validated render request.
#[derive(Debug, Clone)]
pub struct ValidRequest {
    pub scene: ValidScene,
    pub view: ValidTarget,
}
