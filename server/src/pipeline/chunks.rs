//! Splitting the target rays into renderer runs.
//!
//! The renderer's memory grows linearly with rays × samples (every sample point carries its
//! features through the MLP and the attention), so the chunk size comes from a memory budget.
//! Rays are independent in the renderer graph (depth normalisation uses a per-request range, not
//! per-chunk statistics), so the output does not depend on the chunk size.

use std::ops::Range;

use futures_util::{stream, StreamExt, TryStreamExt};
use ndarray::{arr1, s, ArcArray1, ArcArray2, Array1, Array2, Ix1, Ix2};

use super::rays::Rays;
use super::scene::Scene;
use crate::backend::{BackendError, NamedTensors, Outputs, Tensor, Ticket};
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

/// Per ray of a fine run (guided sampling) beside its samples: its guide ray's rectifier heads,
/// gathered (h·d_k x C floats per rectifier, twice over); paper size, both rectifiers.
pub const GUIDED_BYTES_PER_RAY: usize = 64 * 1024;

impl ChunkPolicy {
    pub fn rays_per_chunk(&self, samples: usize) -> usize {
        let by_memory = self.memory_budget_bytes / (samples.max(1) * BYTES_PER_SAMPLE);
        by_memory.clamp(1, self.max_rays.max(1))
    }

    /// Rays of a fine run of `samples` samples each (guided sampling): as many points as a full
    /// run's cap (`max_rays` x `full_samples`), within the memory budget.
    pub fn fine_rays_per_chunk(&self, samples: usize, full_samples: usize) -> usize {
        let per_ray = samples.max(1) * BYTES_PER_SAMPLE + GUIDED_BYTES_PER_RAY;
        let cap = self.max_rays.max(1) * full_samples / samples.max(1);
        (self.memory_budget_bytes / per_ray).clamp(1, cap.max(1))
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

/// Graph runs of one request queued at once. Two keep the executor busy while the previous
/// chunk's outputs are copied out; more would only hold memory (the executor picks requests by
/// deadline, so queuing more does not buy a larger share).
const CHUNKS_IN_FLIGHT: usize = 2;

/// Runs `graph` over `n` rays, `chunk` rays at a time: `inputs(range)` builds a run's inputs,
/// `units_per_ray` its work, and `put(range, outputs)` takes each run's outputs, in order.
/// `last`: this is the request's last run of the renderers, so its last chunk lets the executor
/// release the graph's arena when nothing else waits (`Ticket::run_last`).
#[allow(clippy::too_many_arguments)]
pub async fn run_chunks(
    ticket: &Ticket,
    graph: GraphKind,
    n: usize,
    chunk: usize,
    units_per_ray: f64,
    last: bool,
    inputs: impl Fn(Range<usize>) -> NamedTensors,
    mut put: impl FnMut(Range<usize>, Outputs) -> Result<(), BackendError>,
) -> Result<(), BackendError> {
    let ranges = (0..n).step_by(chunk.max(1)).map(|start| start..(start + chunk).min(n));
    let mut runs = stream::iter(ranges)
        .map(|range| {
            let inputs = inputs(range.clone());
            let (units, final_chunk) = (units_per_ray * range.len() as f64, last && range.end == n);
            let run = if final_chunk {
                futures_util::future::Either::Left(ticket.run_last(graph, units, inputs))
            } else {
                futures_util::future::Either::Right(ticket.run(graph, units, inputs))
            };
            async move { run.await.map(|outputs| (range, outputs)) }
        })
        .buffered(CHUNKS_IN_FLIGHT);
    while let Some((range, outputs)) = runs.try_next().await? {
        put(range, outputs)?;
    }
    Ok(())
}

/// Runs the renderer (whose inputs are `inputs`) over all rays, `chunk` rays at a time, and
/// concatenates the outputs.
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
    let build = |range: Range<usize>| chunk_inputs(scene, inputs, rays, range, depth_range, &|_, _| None);
    run_chunks(ticket, GraphKind::Renderer, n, chunk, 1.0, last, build, |range, mut outputs| {
        let (rgb, depth, opacity) = take_pixels(&mut outputs, range.len())?;
        out.rgb.slice_mut(s![range.clone(), ..]).assign(&rgb);
        out.depth.slice_mut(s![range.clone()]).assign(&depth);
        out.opacity.slice_mut(s![range]).assign(&opacity);
        Ok(())
    })
    .await?;
    Ok(out)
}

/// A run's rgb (R,3), depth (R) and opacity (R).
pub fn take_pixels(outputs: &mut Outputs, rays: usize) -> Result<PixelOutputs, BackendError> {
    let r = Some(rays);
    Ok((
        outputs.take::<Ix2>("rgb", &[r, Some(3)])?,
        outputs.take::<Ix1>("depth", &[r])?,
        outputs.take::<Ix1>("opacity", &[r])?,
    ))
}

/// rgb (R,3), depth (R), opacity (R) of one run.
pub type PixelOutputs = (ArcArray2<f32>, ArcArray1<f32>, ArcArray1<f32>);

/// A graph input the scene and the rays do not give: per chunk (the rows of `range`), by name.
pub type ChunkExtra<'a> = dyn Fn(&str, Range<usize>) -> Option<Tensor> + 'a;

/// Every input a renderer graph declares, by name (the bundle check guarantees we know them):
/// the scene's, the rays' rows `range`, and what `extra` gives.
pub fn chunk_inputs(
    scene: &Scene,
    inputs: &[TensorSpec],
    rays: &Rays,
    range: Range<usize>,
    depth_range: [f32; 2],
    extra: &ChunkExtra<'_>,
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
                other => return extra(other, range.clone()).map(|t| (spec.name.clone(), t)),
            };
            Some((spec.name.clone(), t))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// tests/fixtures/rules/chunks.json: the rule's numbers, which the exporter's twin
    /// (`runtime/chunks.py`) is held to as well.
    fn fixture() -> serde_json::Value {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/fixtures/rules/chunks.json");
        serde_json::from_str(&std::fs::read_to_string(path).expect("chunks.json")).expect("JSON")
    }

    fn policy(case: &serde_json::Value) -> ChunkPolicy {
        let n = |key: &str| case[key].as_u64().unwrap_or_else(|| panic!("{key} in {case}")) as usize;
        ChunkPolicy { max_rays: n("max_rays"), memory_budget_bytes: n("memory_mb") << 20 }
    }

    #[test]
    fn constants_and_defaults_are_the_fixtures() {
        let f = fixture();
        assert_eq!(BYTES_PER_SAMPLE as u64, f["bytes_per_sample"]);
        assert_eq!(GUIDED_BYTES_PER_RAY as u64, f["guided_bytes_per_ray"]);
        let (got, want) = (ChunkPolicy::default(), policy(&f["default"]));
        assert_eq!((got.max_rays, got.memory_budget_bytes), (want.max_rays, want.memory_budget_bytes));
    }

    #[test]
    fn chunk_size_from_budget() {
        for case in fixture()["rays_per_chunk"].as_array().unwrap() {
            let samples = case["samples"].as_u64().unwrap() as usize;
            assert_eq!(policy(case).rays_per_chunk(samples) as u64, case["rays"], "{case}");
        }
    }

    #[test]
    fn fine_chunks_hold_a_full_chunks_points() {
        for case in fixture()["fine_rays_per_chunk"].as_array().unwrap() {
            let (samples, full) =
                (case["samples"].as_u64().unwrap() as usize, case["full_samples"].as_u64().unwrap() as usize);
            assert_eq!(policy(case).fine_rays_per_chunk(samples, full) as u64, case["rays"], "{case}");
        }
    }
}
