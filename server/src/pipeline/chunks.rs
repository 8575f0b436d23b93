//! Splitting the target rays into renderer runs.
//!
//! The renderer's memory grows linearly with rays × samples (every sample point carries its
//! features through the MLP and the attention), so the chunk size comes from a memory budget.
//! Rays are independent in the renderer graph (depth normalisation uses a per-request range, not
//! per-chunk statistics), so the output does not depend on the chunk size.

use futures_util::{stream, StreamExt, TryStreamExt};

use super::rays::Rays;
use super::Scene;
use crate::backend::{BackendError, NamedTensors, Tensor, Ticket};
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

/// Raw renderer outputs for all rays, before background compositing.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RawView {
    pub rgb: Vec<f32>,
    pub depth: Vec<f32>,
    pub opacity: Vec<f32>,
}

/// Renderer runs of one request queued at once. Two keep the executor busy while the previous
/// chunk's outputs are copied out; more would only hold memory (the executor picks requests by
/// deadline, so queuing more does not buy a larger share).
const CHUNKS_IN_FLIGHT: usize = 2;

/// Runs the renderer (whose inputs are `inputs`) over all rays, `chunk` rays at a time, and
/// concatenates the outputs.
pub async fn render_rays(
    ticket: &Ticket,
    scene: &Scene,
    inputs: &[TensorSpec],
    rays: &Rays,
    depth_range: [f32; 2],
    chunk: usize,
) -> Result<RawView, BackendError> {
    let n = rays.len();
    let mut out =
        RawView { rgb: Vec::with_capacity(n * 3), depth: Vec::with_capacity(n), opacity: Vec::with_capacity(n) };
    let ranges = (0..n).step_by(chunk.max(1)).map(|start| (start, (start + chunk).min(n)));
    let mut runs = stream::iter(ranges)
        .map(|(start, end)| {
            let inputs = chunk_inputs(scene, inputs, rays, start, end, depth_range);
            let run = ticket.run(GraphKind::Renderer, (end - start) as f64, inputs);
            async move { run.await.map(|outputs| (end - start, outputs)) }
        })
        .buffered(CHUNKS_IN_FLIGHT);
    while let Some((r, mut outputs)) = runs.try_next().await? {
        out.rgb.extend_from_slice(&outputs.take("rgb", &[Some(r), Some(3)])?.data);
        out.depth.extend_from_slice(&outputs.take("depth", &[Some(r)])?.data);
        out.opacity.extend_from_slice(&outputs.take("opacity", &[Some(r)])?.data);
    }
    Ok(out)
}

/// Every input the renderer graph declares, by name (the bundle check guarantees we know them).
fn chunk_inputs(
    scene: &Scene,
    inputs: &[TensorSpec],
    rays: &Rays,
    start: usize,
    end: usize,
    depth_range: [f32; 2],
) -> NamedTensors {
    let r = end - start;
    let near_far = Tensor::new(vec![2], vec![scene.near as f32, scene.far as f32]);
    inputs
        .iter()
        .filter_map(|spec| {
            let t = match spec.name.as_str() {
                "ray_origins" => Tensor::new(vec![r, 3], rays.origins[start * 3..end * 3].to_vec()),
                "ray_directions" => Tensor::new(vec![r, 3], rays.directions[start * 3..end * 3].to_vec()),
                "near_far" => near_far.clone(),
                "depth_range" => Tensor::new(vec![2], depth_range.to_vec()),
                "volume" => scene.volume.clone(),
                "images" => scene.images.clone(),
                "features" => scene.features.clone(),
                "intrinsics" => scene.intrinsics.clone(),
                "extrinsics" => scene.extrinsics.clone(),
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
