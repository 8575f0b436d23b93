//! The render pipeline, one module per stage:
//!
//! request (validated) -> source images decoded and padded -> [encoder] features ->
//! [volume] encoding volume -> target rays -> chunks -> [renderer] -> image assembly.
//!
//! `build_scene` (sources only) and `render_view` (target only) are separate so that a scene
//! cache can keep a `Scene` and render further views with the renderer alone.

pub mod assemble;
pub mod chunks;
pub mod encoder;
pub mod rays;
pub mod volume;

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::backend::{BackendError, BackendHandle, Tensor, Ticket, Work};
use crate::bundle::{Bundle, DepthNorm, GraphKind};
use crate::camera::Camera;
use crate::error::ApiError;
use crate::image_io::{self, RgbF32};
use crate::request::{Limits, ValidRequest, ValidScene};
use chunks::{ChunkPolicy, RawView};

/// Wall time per stage, in the order the stages ran.
#[derive(Debug, Clone, Default)]
pub struct Timings(pub Vec<(&'static str, Duration)>);

impl Timings {
    pub fn add(&mut self, stage: &'static str, d: Duration) {
        self.0.push((stage, d));
    }

    /// Times one async stage.
    pub async fn time<T, F: std::future::Future<Output = T>>(&mut self, stage: &'static str, f: F) -> T {
        let start = Instant::now();
        let out = f.await;
        self.add(stage, start.elapsed());
        out
    }

    pub fn millis(&self) -> Vec<(&'static str, f64)> {
        self.0.iter().map(|(s, d)| (*s, d.as_secs_f64() * 1e3)).collect()
    }
}

/// Everything the renderer needs about the sources; reusable for any number of target views.
#[derive(Debug, Clone)]
pub struct Scene {
    /// (V, 3, H, W) padded source images in [0, 1].
    pub images: Tensor,
    /// (V, C, H/4, W/4) encoder output.
    pub features: Tensor,
    /// (1, Cv, D, H/4 + 2·pad, W/4 + 2·pad) encoding volume.
    pub volume: Tensor,
    /// (V, 3, 3) full-resolution K per view.
    pub intrinsics: Tensor,
    /// (V, 4, 4) OpenCV world-to-camera per view.
    pub extrinsics: Tensor,
    pub near: f64,
    pub far: f64,
}

impl Scene {
    /// Approximate memory held by the scene (for cache accounting).
    pub fn bytes(&self) -> usize {
        4 * (self.images.len() + self.features.len() + self.volume.len())
    }
}

/// Names of the renderer graph's inputs (the graph of a variant declares only what it uses).
#[derive(Debug, Clone)]
pub struct SceneInputs {
    pub renderer_inputs: Vec<String>,
}

/// A rendered view: composited RGB (H·W·3, in [0, 1]), depth and opacity (H·W).
#[derive(Debug, Clone)]
pub struct View {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<f32>,
    pub depth: Vec<f32>,
    pub opacity: Vec<f32>,
}

/// The pipeline's shared, read-only context.
#[derive(Clone)]
pub struct Pipeline {
    pub backend: BackendHandle,
    pub bundle: Arc<Bundle>,
    pub chunking: ChunkPolicy,
    pub limits: Limits,
}

impl From<BackendError> for ApiError {
    fn from(e: BackendError) -> Self {
        match e {
            BackendError::QueueFull => {
                ApiError::Unavailable { message: "server busy: inference queue is full".into(), retry_after_secs: 2 }
            }
            BackendError::WouldMissDeadline { ahead_secs } => ApiError::Unavailable {
                message: format!("server busy: {e}"),
                retry_after_secs: ahead_secs.ceil().max(1.0) as u64,
            },
            // The handler's own timer normally fires first and knows the deadline; this is the
            // executor noticing it between two graph runs.
            BackendError::DeadlineExceeded => ApiError::DeadlineExceeded { ms: 0 },
            other => ApiError::Internal(other.to_string()),
        }
    }
}

/// Work units of an encoder or volume run over `images` (V, 3, H, W): its pixels.
pub fn pixel_units(images: &Tensor) -> f64 {
    (images.len() / 3) as f64
}

impl Pipeline {
    /// Admits a request with `work` to the inference executor until `deadline` (503 when it is
    /// full or the request could not finish in time).
    pub fn admit(&self, deadline: Instant, work: Work) -> Result<Ticket, ApiError> {
        Ok(self.backend.admit(deadline, work)?)
    }

    /// The work of building a scene from `sources` (the encoder and the volume net over the
    /// padded images).
    pub fn scene_work(&self, sources: &[Camera]) -> Work {
        let multiple = self.bundle.config.image_multiple;
        let pixels: f64 = sources
            .iter()
            .map(|c| {
                (c.width as usize).div_ceil(multiple) * (c.height as usize).div_ceil(multiple) * multiple * multiple
            })
            .sum::<usize>() as f64;
        Work::of(GraphKind::Encoder, pixels).plus(Work::of(GraphKind::Volume, pixels))
    }

    /// The work of rendering `target` (one renderer pass over its rays, two for image_minmax).
    pub fn view_work(&self, target: &Camera) -> Work {
        let passes = match self.bundle.config.depth_norm {
            DepthNorm::NearFar => 1.0,
            DepthNorm::ImageMinmax => 2.0,
        };
        Work::of(GraphKind::Renderer, passes * f64::from(target.width) * f64::from(target.height))
    }

    fn inputs(&self) -> SceneInputs {
        let names = self.bundle.graph(GraphKind::Renderer).inputs.iter().map(|t| t.name.clone()).collect();
        SceneInputs { renderer_inputs: names }
    }

    /// Decodes the source images off the async runtime and stacks them padded.
    pub async fn decode_sources(&self, req: &ValidScene) -> Result<Tensor, ApiError> {
        let sources = req.sources.clone();
        let background = req.background;
        let max_pixels = self.limits.max_source_pixels;
        let multiple = self.bundle.config.image_multiple;
        tokio::task::spawn_blocking(move || {
            let images = sources
                .iter()
                .map(|(cam, bytes, field)| decode_one(cam, bytes, field, background, max_pixels))
                .collect::<Result<Vec<RgbF32>, ApiError>>()?;
            Ok(image_io::stack_padded(&images, multiple, background))
        })
        .await
        .map_err(|e| ApiError::Internal(format!("image decoding task failed: {e}")))?
    }

    /// Encoder and volume net over the source views.
    pub async fn build_scene(
        &self,
        ticket: &Ticket,
        cameras: &[Camera],
        images: Tensor,
        near: f64,
        far: f64,
        timings: &mut Timings,
    ) -> Result<Scene, BackendError> {
        let config = &self.bundle.config;
        let features = timings.time("encoder", encoder::run(ticket, config, &images)).await?;
        let volume =
            timings.time("volume", volume::run(ticket, config, &features, &images, cameras, near, far)).await?;
        let intrinsics = cameras.iter().flat_map(|c| c.k.into_iter().flatten().map(|x| x as f32)).collect();
        let extrinsics = cameras.iter().flat_map(|c| c.w2c.into_iter().flatten().map(|x| x as f32)).collect();
        Ok(Scene {
            images,
            features,
            volume,
            intrinsics: Tensor::new(vec![cameras.len(), 3, 3], intrinsics),
            extrinsics: Tensor::new(vec![cameras.len(), 4, 4], extrinsics),
            near,
            far,
        })
    }

    /// Renders one target view of a scene, `chunk` rays per renderer run (`None`: from the
    /// memory budget).
    pub async fn render_view(
        &self,
        ticket: &Ticket,
        scene: &Scene,
        target: &Camera,
        background: [f32; 3],
        chunk: Option<usize>,
        timings: &mut Timings,
    ) -> Result<View, BackendError> {
        let start = Instant::now();
        let rays = rays::generate(target);
        let chunk = chunk.unwrap_or_else(|| self.chunking.rays_per_chunk(self.bundle.config.samples)).max(1);
        let inputs = self.inputs();
        let near_far = [scene.near as f32, scene.far as f32];
        let raw = match self.bundle.config.depth_norm {
            DepthNorm::NearFar => chunks::render_rays(ticket, scene, &inputs, &rays, near_far, chunk).await?,
            DepthNorm::ImageMinmax => {
                // Depth does not depend on depth_range: a first pass gives the depth image whose
                // min/max normalise the rectification queries of the colour pass.
                let first = chunks::render_rays(ticket, scene, &inputs, &rays, near_far, chunk).await?;
                let range = min_max(&first.depth).unwrap_or(near_far);
                chunks::render_rays(ticket, scene, &inputs, &rays, range, chunk).await?
            }
        };
        timings.add("renderer", start.elapsed());
        let start = Instant::now();
        let view = assemble_view(target, raw, background);
        timings.add("assemble", start.elapsed());
        Ok(view)
    }

    /// Decode, encoder, volume: the part of a request that a scene cache keeps.
    pub async fn prepare_scene(
        &self,
        ticket: &Ticket,
        req: &ValidScene,
        timings: &mut Timings,
    ) -> Result<Scene, ApiError> {
        let images = timings.time("decode", self.decode_sources(req)).await?;
        Ok(self.build_scene(ticket, &req.cameras(), images, req.near, req.far, timings).await?)
    }

    /// The whole request: decode, encoder, volume, renderer, assembly. A cached scene goes
    /// through exactly the same `render_view`, so its views are bit-identical to these.
    pub async fn render(&self, ticket: &Ticket, req: &ValidRequest, timings: &mut Timings) -> Result<View, ApiError> {
        let scene = self.prepare_scene(ticket, &req.scene, timings).await?;
        Ok(self.render_view(ticket, &scene, &req.view.target, req.scene.background, None, timings).await?)
    }
}

fn decode_one(
    cam: &Camera,
    bytes: &[u8],
    field: &str,
    background: [f32; 3],
    max_pixels: u64,
) -> Result<RgbF32, ApiError> {
    // The header alone tells the size: a mismatch is refused before anything is decoded.
    let (_, width, height) = image_io::probe(bytes, field)?;
    if (width, height) != (cam.width, cam.height) {
        return Err(ApiError::invalid(
            field.to_string(),
            format!("image is {width}x{height} but its camera says {}x{}", cam.width, cam.height),
        ));
    }
    image_io::decode_source(bytes, field, background, max_pixels)
}

fn min_max(values: &[f32]) -> Option<[f32; 2]> {
    let mut it = values.iter().copied().filter(|v| v.is_finite());
    let first = it.next()?;
    Some(it.fold([first, first], |[lo, hi], v| [lo.min(v), hi.max(v)]))
}

fn assemble_view(target: &Camera, raw: RawView, background: [f32; 3]) -> View {
    let rgb = assemble::composite(&raw, background);
    View { width: target.width, height: target.height, rgb, depth: raw.depth, opacity: raw.opacity }
}
