//! The most memory a request adds to the process, estimated from its sizes and the bundle's
//! config before anything is decoded (admission by memory, `backend`'s module doc).
//!
//! A request holds, from its decode to its last renderer run: the padded source images, their
//! features and the encoding volume (and, while a slab-built volume is assembled, G2's first
//! convolution over it). On top of that, one stage at a time adds its working memory: the
//! encoder's activations, the cost volume (all of it with `volume.onnx`, one slab of planes with
//! `cost_slab.onnx`, a band of rows with the plane sweep), G2, or one renderer chunk. The renderer's chunk is added to the other
//! stages rather than maxed with them: the renderer's session keeps ONNX Runtime's arena (see
//! `backend::ort`), so a chunk's worth of memory may still be held from an earlier request while
//! this one builds its volume.
//!
//! The per-unit figures are calibrated on measured peaks (`bench/memory.py`, the table in
//! docs/results.md, "Memory at paper size"; the rows are the fixture `tests/fixtures/memory/measured.json`,
//! and a test checks that the estimate never falls below any of them), rounded up by ~10-25 %.

use crate::bundle::{ModelConfig, VolumeBuild};
use crate::pipeline::chunks::{ChunkPolicy, BYTES_PER_SAMPLE};
use crate::pipeline::volume::{plane_cells, SlabPolicy, SLAB_BYTES_PER_CELL};

/// Encoder working memory and the decode's buffers per source pixel (V·H·W of the padded
/// images). Measured 94-156 at 320x256-800x800.
pub const ENCODER_BYTES_PER_PIXEL: u64 = 192;

/// `volume.onnx`'s working memory per cell of the volume (D·Hp·Wp): the warped features of every
/// plane, the 41-channel cost volume and G2's activations at once. Measured 674-699.
pub const WHOLE_VOLUME_BYTES_PER_CELL: u64 = 800;

/// `volume_net.onnx`'s working memory per cell: G2's activations over the 8-channel volume.
/// Measured 140-170 above the conv0 input and the volume output.
pub const VOLUME_NET_BYTES_PER_CELL: u64 = 208;

/// The sweep build's largest stage per cell: the run of `volume_net.onnx` whose preparation
/// computes G2's first convolution over the plane sweep (a band of rows per thread): that
/// convolution, G2's activations and the volume. Measured 138-144 above the process at rest at
/// 640x512-1024x1024 (the graph of the current exporter: one-pass norms need less than the old
/// ones' 208 of `VOLUME_NET_BYTES_PER_CELL`).
pub const SWEEP_BYTES_PER_CELL: u64 = 160;

/// What one request keeps for its lifetime per cell of the volume: the encoding volume (8
/// channels of f32).
const VOLUME_BYTES_PER_CELL: u64 = 32;

/// Bytes per target pixel: rays, the raw outputs and the encoded response.
const TARGET_BYTES_PER_PIXEL: u64 = 128;

/// Per request whatever its size: the request's own buffers (body, decoded PNGs in flight),
/// bookkeeping, allocator slack.
const PER_REQUEST_BYTES: u64 = 32 << 20;

/// How the server runs a bundle: what the estimate needs beyond the model's config.
#[derive(Debug, Clone, Copy)]
pub struct MemoryPlan {
    pub build: VolumeBuild,
    pub slabs: SlabPolicy,
    pub chunking: ChunkPolicy,
}

/// The sizes an estimate reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RequestSizes {
    /// Padded width and height of the sources to encode (`None`: a cached scene).
    pub sources: Option<(usize, usize)>,
    /// Pixels of the view to render (0: none).
    pub target_pixels: u64,
    /// What the view's sampling holds beside its pixels (guided sampling's weights and heads).
    pub sampling_bytes: u64,
}

/// The request's estimate split into what it holds and the largest working set of its stages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Estimate {
    /// Held from the decode to the last renderer run.
    pub held: u64,
    /// The largest of the encoder's and the volume stages' working memory.
    pub stage: u64,
    /// One renderer chunk.
    pub renderer: u64,
}

impl Estimate {
    pub fn total(&self) -> u64 {
        PER_REQUEST_BYTES + self.held + self.stage + self.renderer
    }
}

/// The estimate of one request: see the module doc.
pub fn estimate(config: &ModelConfig, plan: &MemoryPlan, sizes: &RequestSizes) -> u64 {
    parts(config, plan, sizes).total()
}

/// [`estimate`] by part.
pub fn parts(config: &ModelConfig, plan: &MemoryPlan, sizes: &RequestSizes) -> Estimate {
    let mut e = Estimate::default();
    if let Some((w, h)) = sizes.sources {
        let plane = plane_cells(config, w, h) as u64;
        let pixels = config.views as u64 * w as u64 * h as u64;
        let cells = config.depth_planes as u64 * plane;
        // Images (3 channels) and features (feature_channels at 1/16 of the pixels), f32.
        let images = pixels * 3 * 4 + pixels / 16 * config.feature_channels as u64 * 4;
        let encoder = pixels * ENCODER_BYTES_PER_PIXEL;
        let volume = match plan.build {
            VolumeBuild::Whole => cells * WHOLE_VOLUME_BYTES_PER_CELL,
            VolumeBuild::Slabs => {
                // G2's first convolution over the volume, assembled slab by slab: held while
                // the slabs run and during G2.
                let conv0 = cells * config.volume_channels as u64 * 4;
                let planes = plan.slabs.planes_per_slab(config.depth_planes, plane as usize) as u64 + 2;
                let slab = planes * plane * SLAB_BYTES_PER_CELL as u64;
                conv0 + slab.max(cells * VOLUME_NET_BYTES_PER_CELL)
            }
            VolumeBuild::Sweep => cells * SWEEP_BYTES_PER_CELL,
        };
        e.held = images + cells * VOLUME_BYTES_PER_CELL;
        e.stage = encoder.max(volume);
    }
    if sizes.target_pixels > 0 {
        let rays = (plan.chunking.rays_per_chunk(config.samples) as u64).min(sizes.target_pixels);
        e.renderer = rays * config.samples as u64 * BYTES_PER_SAMPLE as u64;
        e.held += sizes.target_pixels * TARGET_BYTES_PER_PIXEL + sizes.sampling_bytes;
    }
    e
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bundle::ModelConfig;

    /// The measured rows (tests/fixtures/memory/measured.json): each bundle's config and how it
    /// was run, and per source size the peak resident set above the process at rest.
    #[derive(serde::Deserialize)]
    struct Measured {
        bundles: std::collections::BTreeMap<String, MeasuredBundle>,
        rows: Vec<Row>,
    }

    #[derive(serde::Deserialize)]
    struct MeasuredBundle {
        config: ModelConfig,
    }

    #[derive(serde::Deserialize)]
    struct Row {
        bundle: String,
        build: String,
        sources: [usize; 2],
        target: [u64; 2],
        peak_above_rest_mib: f64,
    }

    fn measured() -> Measured {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/fixtures/memory/measured.json");
        serde_json::from_str(&std::fs::read_to_string(path).expect(path)).expect("measured.json")
    }

    fn plan(build: VolumeBuild) -> MemoryPlan {
        MemoryPlan { build, slabs: SlabPolicy::default(), chunking: ChunkPolicy::default() }
    }

    #[test]
    fn never_below_a_measured_peak_nor_far_above() {
        let m = measured();
        assert!(m.rows.len() >= 6, "the fixture holds the measured table");
        for row in &m.rows {
            let config = &m.bundles[&row.bundle].config;
            let build = match row.build.as_str() {
                "sweep" => VolumeBuild::Sweep,
                "slabs" => VolumeBuild::Slabs,
                _ => VolumeBuild::Whole,
            };
            let sizes = RequestSizes {
                sources: Some((row.sources[0], row.sources[1])),
                target_pixels: row.target[0] * row.target[1],
                sampling_bytes: 0,
            };
            let estimate = estimate(config, &plan(build), &sizes) as f64 / (1 << 20) as f64;
            let (w, h, measured) = (row.sources[0], row.sources[1], row.peak_above_rest_mib);
            eprintln!("{} {} {w}x{h}: measured {measured:.0} MiB, estimate {estimate:.0} MiB", row.bundle, row.build);
            assert!(
                estimate >= measured,
                "{} {} {w}x{h}: estimate {estimate:.0} < measured {measured:.0}",
                row.bundle,
                row.build
            );
            // An estimate far above the truth wastes the budget: at most 2.5x plus the renderer
            // chunk (sized for the heaviest renderer, the paper-size scnerf), and 256 MiB.
            let chunk = parts(config, &plan(build), &sizes).renderer as f64 / (1 << 20) as f64;
            assert!(
                estimate <= 2.5 * measured + chunk + 256.0,
                "{} {w}x{h}: estimate {estimate:.0} far above {measured:.0}",
                row.bundle
            );
        }
    }

    #[test]
    fn grows_with_the_sources_and_is_smaller_slab_by_slab() {
        let config = measured().bundles.into_values().next().unwrap().config;
        let at = |w, h, build| {
            estimate(
                &config,
                &plan(build),
                &RequestSizes { sources: Some((w, h)), target_pixels: 80 * 64, sampling_bytes: 0 },
            )
        };
        assert!(at(640, 512, VolumeBuild::Whole) > at(320, 256, VolumeBuild::Whole));
        assert!(at(1024, 1024, VolumeBuild::Slabs) > at(800, 800, VolumeBuild::Slabs));
        assert!(at(800, 800, VolumeBuild::Slabs) * 2 < at(800, 800, VolumeBuild::Whole));
        assert!(at(800, 800, VolumeBuild::Sweep) < at(800, 800, VolumeBuild::Slabs));
        // A cached scene's view: the renderer chunk and the target only.
        let view = estimate(
            &config,
            &plan(VolumeBuild::Whole),
            &RequestSizes { sources: None, target_pixels: 100, sampling_bytes: 0 },
        );
        assert!(view < at(320, 256, VolumeBuild::Whole) && view > PER_REQUEST_BYTES);
    }
}
