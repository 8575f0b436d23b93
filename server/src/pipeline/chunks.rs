//! Splitting the target rays into renderer runs.
//!
//! The renderer's memory grows linearly with rays × samples (every sample point carries its
//! features through the MLP and the attention), so the chunk size comes from a memory budget.
//! Rays are independent in the renderer graph (depth normalisation uses a per-request range, not
//! per-chunk statistics), so the output does not depend on the chunk size.

use std::ops::Range;

use futures_util::{stream, StreamExt, TryStreamExt};
use ndarray::{arr1, s, ArcArray2, Array1, Array2, Ix1, Ix2};

use super::rays::Rays;
use super::Scene;
use crate::backend::{BackendError, NamedTensors, Ticket};
use crate::bundle::{GraphKind, TensorSpec};

/// Peak bytes of renderer activations per sample point. Measured with the paper-size `scnerf`
/// renderer (width 128, both rectifiers), ONNX Runtime 1.31 CPU: about 4.7 GB of resident memory
/// at 2048 rays x 128 samples, i.e. ~18 KiB per point.
pub const BYTES_PER_SAMPLE: usize = 18 * 1024;

#[derive(Debug, Clone, Copy)]
pub struct ChunkPolicy {
    pub max_rays: usize,
    pub memory_budget_bytes: usize,
}

impl Default for ChunkPolicy {
    fn default() -> Self {
        // `--max-rays-per-chunk` and `--chunk-memory-mb` (1 GiB).
        ChunkPolicy { max_rays: 512, memory_budget_bytes: 1024 << 20 }
    }
}

impl ChunkPolicy {
    pub fn rays_per_chunk(&self, samples: usize) -> usize {
        let by_memory = self.memory_budget_bytes / (samples.max(1) * BYTES_PER_SAMPLE);
        by_memory.clamp(1, self.max_rays.max(1))
    }
}

/// Raw renderer outputs for all N rays, before background compositing.
#[derive(Debug, Clone, PartialEq)]
pub struct RawView {
    /// (N, 3)
    pub rgb: Array2<f32>,
    /// (N)
    pub depth: Array1<f32>,
    /// (N)
    pub opacity: Array1<f32>,
}

/// Renderer runs of one request queued at once. Two keep the executor busy while the previous
/// chunk's outputs are copied out; more would only hold memory (the executor picks requests by
/// deadline, so queuing more does not buy a larger share).
const CHUNKS_IN_FLIGHT: usize = 2;

/// Runs the renderer (whose inputs are `inputs`) over all rays, `chunk` rays at a time, and
/// concatenates the outputs. `last`: this is the request's last pass, so its last chunk lets
/// the executor release the renderer's arena when nothing else waits (`Ticket::run_last`).
pub async fn render_rays(
    ticket: &Ticket,
    scene: &Scene,
    inputs: &[TensorSpec],
    rays: &Rays,
    depth_range: [f32; 2],
    chunk: usize,
    last: bool,
) -> Result<RawView, BackendError> {
    let n = rays.len();
    let mut out = RawView { rgb: Array2::zeros((n, 3)), depth: Array1::zeros(n), opacity: Array1::zeros(n) };
    let ranges = (0..n).step_by(chunk.max(1)).map(|start| start..(start + chunk).min(n));
    let mut runs = stream::iter(ranges)
        .map(|range| {
            let inputs = chunk_inputs(scene, inputs, rays, range.clone(), depth_range);
            let (units, final_chunk) = (range.len() as f64, last && range.end == n);
            let run = if final_chunk {
                futures_util::future::Either::Left(ticket.run_last(GraphKind::Renderer, units, inputs))
            } else {
                futures_util::future::Either::Right(ticket.run(GraphKind::Renderer, units, inputs))
            };
            async move { run.await.map(|outputs| (range, outputs)) }
        })
        .buffered(CHUNKS_IN_FLIGHT);
    while let Some((range, mut outputs)) = runs.try_next().await? {
        let r = Some(range.len());
        out.rgb.slice_mut(s![range.clone(), ..]).assign(&outputs.take::<Ix2>("rgb", &[r, Some(3)])?);
        out.depth.slice_mut(s![range.clone()]).assign(&outputs.take::<Ix1>("depth", &[r])?);
        out.opacity.slice_mut(s![range]).assign(&outputs.take::<Ix1>("opacity", &[r])?);
    }
    Ok(out)
}

/// Every input the renderer graph declares, by name (the bundle check guarantees we know them).
fn chunk_inputs(
    scene: &Scene,
    inputs: &[TensorSpec],
    rays: &Rays,
    range: Range<usize>,
    depth_range: [f32; 2],
) -> NamedTensors {
    // The rays' rows and the scene's tensors are shared with the chunk, not copied.
    let rows = |a: &ArcArray2<f32>| a.clone().slice_move(s![range.clone(), ..]).into_dyn();
    let pair = |p: [f32; 2]| arr1(&p).into_shared().into_dyn();
    inputs
        .iter()
        .filter_map(|spec| {
            let t = match spec.name.as_str() {
                "ray_origins" => rows(&rays.origins),
                "ray_directions" => rows(&rays.directions),
                "near_far" => pair([scene.near as f32, scene.far as f32]),
                "depth_range" => pair(depth_range),
                "volume" => scene.volume.clone().into_dyn(),
                "images" => scene.images.clone().into_dyn(),
                "features" => scene.features.clone().into_dyn(),
                "intrinsics" => scene.intrinsics.clone().into_dyn(),
                "extrinsics" => scene.extrinsics.clone().into_dyn(),
                _ => return None,
            };
            Some((spec.name.clone(), t))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chunk_size_from_budget() {
        let p = ChunkPolicy { max_rays: 4096, memory_budget_bytes: 4096 << 20 };
        assert_eq!(p.rays_per_chunk(128), 1820);
        assert_eq!(p.rays_per_chunk(1), 4096);
        let tiny = ChunkPolicy { max_rays: 4096, memory_budget_bytes: 1 };
        assert_eq!(tiny.rays_per_chunk(128), 1);
    }
}
