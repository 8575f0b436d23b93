//! Admission: a request's work and memory estimate, reckoned from its sizes before anything is
//! decoded, and the refusal that names them.

use super::guided::Guidance;
use super::{estimate, sources, volume, DepthRange, Pipeline};
use crate::backend::{BackendError, Due, Ticket, Work};
use crate::bundle::GraphKind;
use crate::camera::CanonicalCamera;
use crate::error::ApiError;
use crate::request::{Sampling, ValidScene};

impl Pipeline {
    /// Admits a request with `work` and at most `memory` bytes to the inference executor until
    /// `due` (503 when it is full, short of memory, or the request could not finish in time;
    /// 422 when it needs more memory than the executor ever has).
    pub fn admit(&self, due: impl Into<Due>, work: Work, memory: u64) -> Result<Ticket, ApiError> {
        Ok(self.backend.admit(due, work, memory)?)
    }

    /// Admits a request that builds the volume of `sources` (`None`: a cached scene), decoding
    /// them first when `decodes`, and renders `target` (`None`: a scene only), before anything
    /// is decoded. Too large for the memory budget: 422 naming the sizes.
    pub(super) fn admit_request(
        &self,
        due: Due,
        sources: Option<&[CanonicalCamera]>,
        decodes: bool,
        target: Option<(&CanonicalCamera, Sampling)>,
    ) -> Result<Ticket, ApiError> {
        let work = self.request_work(sources, target);
        let memory = self.memory_estimate(sources, decodes, sources.is_some(), target);
        self.backend.admit(due, work, memory).map_err(|e| refusal(e, sources, target.map(|(t, _)| t)))
    }

    /// The work of a request that builds the scene of `sources` (`None`: a cached scene) and
    /// renders `target` (`None`: a scene only).
    pub(super) fn request_work(
        &self,
        sources: Option<&[CanonicalCamera]>,
        target: Option<(&CanonicalCamera, Sampling)>,
    ) -> Work {
        let scene = sources.map_or_else(Work::default, |s| self.scene_work(s));
        target.map_or(scene, |(t, sampling)| scene.plus(self.view_work(t, sampling)))
    }

    /// Whether a scene of `views` views gets its volume on upload: only the model's view count
    /// makes one triple; a larger scene builds the triple each render picks.
    pub(super) fn builds_on_upload(&self, views: usize) -> bool {
        views == self.bundle.config.views
    }

    /// The most memory a request over `sources` adds to the process (see [`estimate::estimate`]):
    /// it decodes them when `decodes`, builds a volume from the model's view count of them when
    /// `builds`, renders `target` with its sampling.
    pub fn memory_estimate(
        &self,
        sources: Option<&[CanonicalCamera]>,
        decodes: bool,
        builds: bool,
        target: Option<(&CanonicalCamera, Sampling)>,
    ) -> u64 {
        let sizes = estimate::RequestSizes {
            sources: sources.and_then(|s| self.padded_source_size(s)),
            decoded_views: sources.filter(|_| decodes).map_or(0, <[CanonicalCamera]>::len),
            builds_volume: builds,
            target_pixels: target.map_or(0, |(t, _)| u64::from(t.width) * u64::from(t.height)),
            sampling_bytes: target.map_or(0, |(t, sampling)| self.sampling_bytes(t, sampling)),
        };
        let plan =
            estimate::MemoryPlan { build: self.volume.build(), slabs: *self.volume.policy(), chunking: self.chunking };
        estimate::estimate(&self.bundle.config, &plan, &sizes)
    }

    /// Refuses a scene of `views` views of `width` x `height` whose memory estimate exceeds what
    /// requests may have at all (422 naming the sizes, as its admission would), from the sizes
    /// alone; else what the scene will hold in the scene cache. A capture calls it before its
    /// photos are decoded and resized.
    pub fn check_scene_size(&self, width: u32, height: u32, views: usize) -> Result<u64, ApiError> {
        let camera = CanonicalCamera { width, height, k: Default::default(), w2c: Default::default() };
        let cameras = vec![camera; views];
        let builds = self.builds_on_upload(views);
        let memory = self.memory_estimate(Some(&cameras), true, builds, None);
        let budget = self.backend.stats().memory.for_requests();
        if memory > budget {
            let e = BackendError::TooLarge { needed_mib: memory.div_ceil(1 << 20), budget_mib: budget >> 20 };
            return Err(too_large(Some(&cameras), None, &e));
        }
        let size = self.padded_source_size(&cameras).unwrap_or_default();
        Ok(estimate::scene_bytes(&self.bundle.config, size, views, builds))
    }

    /// One renderer run's working memory (see [`estimate::renderer_run_bytes`]).
    pub fn renderer_run_bytes(&self) -> u64 {
        estimate::renderer_run_bytes(&self.bundle.config, &self.chunking)
    }

    /// What the scene of `req` will hold in the scene cache (see [`estimate::scene_bytes`]).
    pub fn scene_bytes(&self, req: &ValidScene) -> u64 {
        let cameras = req.cameras();
        let builds = self.builds_on_upload(cameras.len());
        self.padded_source_size(&cameras)
            .map_or(0, |size| estimate::scene_bytes(&self.bundle.config, size, cameras.len(), builds))
    }

    /// The work of building a scene from `sources` (the encoder and the volume net over the
    /// padded images).
    pub fn scene_work(&self, sources: &[CanonicalCamera]) -> Work {
        let config = &self.bundle.config;
        let Some((w, h)) = self.padded_source_size(sources) else { return Work::default() };
        let pixels = (sources.len() * w * h) as f64;
        let cells = volume::plane_cells(config, w, h);
        let volume = self.volume.work(config, pixels, cells);
        Work::of(GraphKind::Encoder, pixels).plus(volume)
    }

    /// The padded size of the sources (all of the first's size: validation checked it).
    fn padded_source_size(&self, sources: &[CanonicalCamera]) -> Option<(usize, usize)> {
        let c = sources.first()?;
        Some(sources::padded_size(c.width as usize, c.height as usize, self.bundle.config.image_multiple))
    }

    /// The work of rendering `target`: its rays, once per renderer pass; by guided sampling its
    /// guide rays and at most its fine rays' samples (the pixels rendered again among them).
    pub fn view_work(&self, target: &CanonicalCamera, sampling: Sampling) -> Work {
        let (width, height) = (target.width as usize, target.height as usize);
        match (sampling, self.bundle.guided()) {
            (Sampling::Guided, Some(policy)) => {
                let (guide_rays, fine_samples) = policy.most_work(width, height, self.bundle.config.samples);
                Work::of(GraphKind::RendererGuide, guide_rays as f64)
                    .plus(Work::of(GraphKind::RendererFine, fine_samples as f64))
            }
            _ => Work::of(GraphKind::Renderer, DepthRange::of(&self.bundle).passes() * (width * height) as f64),
        }
    }

    /// What guided sampling holds for a view beside the full renderer's: the weights later levels
    /// read and the guide rays' rectifier heads.
    pub(super) fn sampling_bytes(&self, target: &CanonicalCamera, sampling: Sampling) -> u64 {
        let (Sampling::Guided, Some(policy)) = (sampling, self.bundle.guided()) else { return 0 };
        let c = &self.bundle.config;
        let (width, height) = (target.width as usize, target.height as usize);
        let guide_rays = policy.guide_rays(width, height);
        let rectifiers =
            self.bundle.graph(GraphKind::RendererGuide).outputs.iter().filter(|t| t.name.ends_with("_heads")).count();
        let heads = (guide_rays * rectifiers * c.heads * c.head_dim * c.width * 4) as u64;
        Guidance::bytes(width, height, c.samples) + heads
    }
}

/// An admission's refusal; the 422 of a request whose memory estimate exceeds the whole budget
/// names the sizes.
pub(super) fn refusal(
    e: BackendError,
    sources: Option<&[CanonicalCamera]>,
    target: Option<&CanonicalCamera>,
) -> ApiError {
    match e {
        BackendError::TooLarge { .. } => too_large(sources, target, &e),
        other => other.into(),
    }
}

/// The 422 of a request whose memory estimate exceeds the whole budget: it names the sizes.
fn too_large(sources: Option<&[CanonicalCamera]>, target: Option<&CanonicalCamera>, e: &BackendError) -> ApiError {
    let size = |c: &CanonicalCamera| format!("{}x{}", c.width, c.height);
    match (sources.and_then(|s| Some((s.len(), s.first()?))), target) {
        (Some((n, first)), Some(t)) => ApiError::invalid(
            "sources",
            format!("{n} source views of {} with a {} target need {e}", size(first), size(t)),
        ),
        (Some((n, first)), None) => {
            ApiError::invalid("sources", format!("{n} source views of {} need {e}", size(first)))
        }
        (None, Some(t)) => ApiError::invalid("target.width", format!("a {} target needs {e}", size(t))),
        (None, None) => e.clone().into(),
    }
}
