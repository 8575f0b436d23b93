//! The render pipeline, one module per stage, in the order the data flows:
//!
//! validated request -> [`sources`] images decoded and padded -> ([`views`]: a scene's views,
//! and the three a target is rendered from) -> [`encoder`] features -> [`volume`] cost volume
//! and encoding volume -> [`rays`] target rays -> [`chunks`] renderer runs -> [`band`] the
//! pixels a source does not see -> [`assemble`] image.
//!
//! A request is admitted to the inference executor with its deadline and its estimated work
//! (`scene_work`, `view_work`) before any graph runs. `build_scene` (sources only) and
//! `render_view` (target only) are separate so that a scene cache can keep a `Scene` and render
//! further views with the renderer alone.

mod admit;
pub mod assemble;
pub mod band;
pub mod chunks;
pub mod encoder;
pub mod estimate;
pub mod first_conv;
pub mod guided;
pub mod rays;
pub mod scene;
pub mod sources;
pub mod sweep;
#[cfg(test)]
mod tests;
pub mod views;
pub mod volume;
pub mod volume_tail;

use std::sync::Arc;
use std::time::Instant;

use admit::refusal;
use band::BandFill;
use ndarray::{ArcArray4, Array1, Array4};
use views::Views;

use crate::backend::{BackendError, BackendHandle, Due, Ticket};
use crate::bundle::{Bundle, DepthNorm, GraphKind, Manifest, ModelConfig};
use crate::camera::{stack_rows, CanonicalCamera};
use crate::error::ApiError;
use crate::request::{Limits, Sampling, ValidRequest, ValidScene};
use crate::sysmem::MemoryProbe;
use chunks::{ChunkPolicy, RawView};
use rays::Rays;
use scene::{SamplingReport, Scene, Timings, View};
use volume::{SlabPolicy, VolumeBuilder};

/// The pipeline's shared, read-only context: the executor, the bundle, the chunking policy and
/// the request limits.
#[derive(Clone)]
pub struct Pipeline {
    backend: BackendHandle,
    bundle: Arc<Bundle>,
    chunking: ChunkPolicy,
    volume: Arc<VolumeBuilder>,
    limits: Limits,
    /// How a view is sampled when its request does not say.
    sampling: Sampling,
    /// What colours the pixels whose surface a source does not see (`band`).
    band: BandFill,
}

/// Work units of an encoder or volume run over `images` (V, 3, H, W): its pixels.
pub fn pixel_units(images: &ArcArray4<f32>) -> f64 {
    (images.len() / 3) as f64
}

/// Where the renderer's `depth_range` input (the range that normalises the rectifiers' depth
/// queries) comes from: the one home of the `depth_norm` rule.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum DepthRange {
    /// The request's [near, far]: one renderer pass per view.
    NearFar,
    /// The min/max of the view's own depth image: a first pass renders the depth (which does not
    /// depend on `depth_range`), the second the colours.
    FirstPass,
}

impl DepthRange {
    /// `image_minmax` needs two passes only when the renderer takes the range at all.
    fn of(bundle: &Bundle) -> DepthRange {
        match bundle.config.depth_norm {
            DepthNorm::ImageMinmax if bundle.renderer_takes("depth_range") => DepthRange::FirstPass,
            _ => DepthRange::NearFar,
        }
    }

    fn passes(self) -> f64 {
        match self {
            DepthRange::NearFar => 1.0,
            DepthRange::FirstPass => 2.0,
        }
    }
}

impl Pipeline {
    pub fn new(
        backend: BackendHandle,
        bundle: Bundle,
        chunking: ChunkPolicy,
        slabs: SlabPolicy,
        limits: Limits,
    ) -> Pipeline {
        let sampling = if bundle.guided().is_some() { Sampling::Guided } else { Sampling::Full };
        let volume = Arc::new(VolumeBuilder::new(bundle.volume_build(), bundle.volume_tail(), slabs));
        Pipeline { backend, bundle: Arc::new(bundle), chunking, volume, limits, sampling, band: BandFill::default() }
    }

    /// The sampling of views whose request does not name one (`--sampling`); guided only when
    /// the bundle can, else full.
    pub fn with_default_sampling(mut self, sampling: Sampling) -> Pipeline {
        self.sampling = if self.bundle.guided().is_some() { sampling } else { Sampling::Full };
        self
    }

    /// What colours the pixels whose surface a source does not see (`--band`).
    pub fn with_band(mut self, band: BandFill) -> Pipeline {
        self.band = band;
        self
    }

    /// The sampling views get when their request does not name one.
    pub fn default_sampling(&self) -> Sampling {
        self.sampling
    }

    /// The ways this bundle can sample a view.
    pub fn samplings(&self) -> Vec<Sampling> {
        Sampling::ALL.into_iter().filter(|&s| s == Sampling::Full || self.bundle.guided().is_some()).collect()
    }

    /// The sampling of a view: what its request asks for (422 naming `sampling` when the bundle
    /// cannot), else the server's default.
    pub fn sampling_of(&self, requested: Option<Sampling>) -> Result<Sampling, ApiError> {
        match requested {
            None => Ok(self.sampling),
            Some(s) if self.samplings().contains(&s) => Ok(s),
            Some(s) => Err(ApiError::invalid(
                "sampling",
                format!(
                    "this model cannot render with \"{s}\" sampling (it has no guided-sampling graphs); use \"full\""
                ),
            )),
        }
    }

    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    pub fn config(&self) -> &ModelConfig {
        &self.bundle.config
    }

    pub fn bundle(&self) -> &Bundle {
        &self.bundle
    }

    pub fn manifest(&self) -> &Manifest {
        &self.bundle.manifest
    }

    /// The inference executor (its queue figures are served as metrics).
    pub fn executor(&self) -> &BackendHandle {
        &self.backend
    }

    /// The whole request, admitted until `due`: decode, encoder, volume, renderer, assembly.
    /// A cached scene goes through exactly the same `render_view`, so its views are
    /// bit-identical to these.
    pub async fn render(&self, req: &ValidRequest, due: Due, timings: &mut Timings) -> Result<View, ApiError> {
        let sampling = self.sampling_of(req.view.sampling)?;
        let target = Some((&req.view.target, sampling));
        let ticket = self.admit_request(due, Some(&req.scene.cameras()), true, target)?;
        let scene = self.prepare_scene(&ticket, &req.scene, timings).await?;
        Ok(self.render_view(&ticket, &scene, &req.view.target, req.scene.background, sampling, None, timings).await?)
    }

    /// The scene of `POST /v1/scenes`: its views decoded; a scene of exactly the model's view
    /// count also gets its encoder features and volume now (admitted until `due`), as scenes
    /// always did. A larger one (a capture) builds the volume of each triple a render needs; its
    /// decoding holds its memory estimate against the budget (a lease: no graph runs).
    pub async fn encode_scene(
        &self,
        req: &ValidScene,
        due: Due,
        timings: &mut Timings,
    ) -> Result<(Views, Option<Scene>), ApiError> {
        let cameras = req.cameras();
        let (ticket, _decoding) = match self.builds_on_upload(cameras.len()) {
            true => (Some(self.admit_request(due, Some(&cameras), true, None)?), None),
            false => {
                let estimate = self.memory_estimate(Some(&cameras), true, false, None);
                (None, Some(self.backend.lease(estimate).map_err(|e| refusal(e, Some(&cameras), None))?))
            }
        };
        let images = timings.time("decode", self.decode_sources(req)).await?.into_shared();
        let views = Views { images, cameras, near: req.near, far: req.far };
        let scene = match ticket {
            Some(ticket) => {
                Some(self.build_scene(&ticket, &views.cameras, views.images.clone(), req.near, req.far, timings).await?)
            }
            None => None,
        };
        Ok((views, scene))
    }

    /// A view of a scene rendered from `sources`, admitted until `due`: the renderer alone
    /// when their scene is `cached`, else the encoder and volume net first; a scene built here is
    /// returned for the cache.
    #[allow(clippy::too_many_arguments)]
    pub async fn render_sources(
        &self,
        views: &Views,
        sources: &[usize],
        cached: Option<Arc<Scene>>,
        target: &CanonicalCamera,
        sampling: Option<Sampling>,
        background: [f32; 3],
        due: Due,
        timings: &mut Timings,
    ) -> Result<(View, Option<Arc<Scene>>), ApiError> {
        let cameras = views.cameras_of(sources);
        let sampling = self.sampling_of(sampling)?;
        // A cached triple costs the renderer alone; otherwise its scene is built here too.
        let ticket =
            self.admit_request(due, cached.is_none().then_some(&cameras[..]), false, Some((target, sampling)))?;
        let (scene, built) = match cached {
            Some(scene) => (scene, None),
            None => {
                let images = views.images_of(sources);
                let scene =
                    Arc::new(self.build_scene(&ticket, &cameras, images, views.near, views.far, timings).await?);
                (scene.clone(), Some(scene))
            }
        };
        let view = self.render_view(&ticket, &scene, target, background, sampling, None, timings).await?;
        Ok((view, built))
    }

    /// Decodes the source images off the async runtime and stacks them padded.
    pub async fn decode_sources(&self, req: &ValidScene) -> Result<Array4<f32>, ApiError> {
        let multiple = self.bundle.config.image_multiple;
        let probe = self.backend.probe().map(MemoryProbe::start);
        let decoded = sources::decode(&req.sources, req.background, self.limits.max_source_pixels, multiple).await;
        if let Some(probe) = probe {
            probe.finish("decode");
        }
        decoded
    }

    /// Decode, encoder, volume: the part of a request that a scene cache keeps.
    pub async fn prepare_scene(
        &self,
        ticket: &Ticket,
        req: &ValidScene,
        timings: &mut Timings,
    ) -> Result<Scene, ApiError> {
        let images = timings.time("decode", self.decode_sources(req)).await?;
        Ok(self.build_scene(ticket, &req.cameras(), images.into_shared(), req.near, req.far, timings).await?)
    }

    /// Encoder and volume net over the source views.
    pub async fn build_scene(
        &self,
        ticket: &Ticket,
        cameras: &[CanonicalCamera],
        images: ArcArray4<f32>,
        near: f64,
        far: f64,
        timings: &mut Timings,
    ) -> Result<Scene, BackendError> {
        let config = &self.bundle.config;
        let features = timings.time("encoder", encoder::run(ticket, config, &images)).await?;
        let inputs = volume::VolumeInputs::new(config, &features, &images, cameras, near, far);
        let volume = timings.time("volume", self.volume.run(ticket, config, inputs)).await?;
        let source_sizes = cameras.iter().map(|c| (c.width as usize, c.height as usize)).collect();
        let intrinsics: Vec<_> = cameras.iter().map(|c| c.k).collect();
        let extrinsics: Vec<_> = cameras.iter().map(|c| c.w2c).collect();
        Ok(Scene {
            images,
            features,
            volume,
            intrinsics: stack_rows(&intrinsics).into_shared(),
            extrinsics: stack_rows(&extrinsics).into_shared(),
            source_sizes,
            near,
            far,
        })
    }

    /// Renders one target view of a scene, `chunk` rays per renderer run (`None`: from the
    /// memory budget).
    #[allow(clippy::too_many_arguments)]
    pub async fn render_view(
        &self,
        ticket: &Ticket,
        scene: &Scene,
        target: &CanonicalCamera,
        background: [f32; 3],
        sampling: Sampling,
        chunk: Option<usize>,
        timings: &mut Timings,
    ) -> Result<View, BackendError> {
        let start = Instant::now();
        let rays = rays::generate(target);
        let (mut raw, report) = match (sampling, self.bundle.guided()) {
            (Sampling::Guided, Some(policy)) => {
                let (bundle, chunking) = (&self.bundle, &self.chunking);
                guided::render(ticket, bundle, policy, chunking, scene, target, &rays, background).await?
            }
            _ => self.render_full(ticket, scene, &rays, chunk).await?,
        };
        timings.add("renderer", start.elapsed());
        if self.band == BandFill::Sources {
            let start = Instant::now();
            band::fill_from_sources(&mut raw, &rays, &band::Sources::of(scene), self.bundle.band_rule());
            timings.add("band", start.elapsed());
        }
        let start = Instant::now();
        let view = assemble_view(target, raw, background, report);
        timings.add("assemble", start.elapsed());
        Ok(view)
    }

    /// Every one of the target's `rays` at the S uniform samples, `chunk` rays per renderer run
    /// (`None`: from the memory budget).
    async fn render_full(
        &self,
        ticket: &Ticket,
        scene: &Scene,
        rays: &Rays,
        chunk: Option<usize>,
    ) -> Result<(RawView, SamplingReport), BackendError> {
        let chunk = chunk.unwrap_or_else(|| self.chunking.rays_per_chunk(self.bundle.config.samples)).max(1);
        let inputs = &self.bundle.graph(GraphKind::Renderer).inputs;
        let near_far = [scene.near as f32, scene.far as f32];
        let two_passes = DepthRange::of(&self.bundle) == DepthRange::FirstPass;
        let mut raw = chunks::render_rays(ticket, scene, inputs, rays, near_far, chunk, !two_passes).await?;
        if two_passes {
            let range = min_max(&raw.depth).unwrap_or(near_far);
            raw = chunks::render_rays(ticket, scene, inputs, rays, range, chunk, true).await?;
        }
        let samples_per_ray = self.bundle.config.samples as f64;
        Ok((raw, SamplingReport { mode: Sampling::Full, samples_per_ray }))
    }
}

fn min_max(values: &Array1<f32>) -> Option<[f32; 2]> {
    let mut it = values.iter().copied().filter(|v| v.is_finite());
    let first = it.next()?;
    Some(it.fold([first, first], |[lo, hi], v| [lo.min(v), hi.max(v)]))
}

/// The rays' outputs as images: rays are ordered row by row.
fn assemble_view(target: &CanonicalCamera, raw: RawView, background: [f32; 3], sampling: SamplingReport) -> View {
    let (h, w) = (target.height as usize, target.width as usize);
    let image = |a: Array1<f32>| a.into_shape_with_order((h, w)).expect("one ray per pixel");
    let rgb = assemble::composite(&raw, background).into_shape_with_order((h, w, 3)).expect("one ray per pixel");
    View { rgb, depth: image(raw.depth), opacity: image(raw.opacity), sampling }
}
