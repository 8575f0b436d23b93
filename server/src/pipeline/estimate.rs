//! The most memory a request adds to the process, estimated from its sizes and the bundle's
//! config before anything is decoded (admission by memory, `backend`'s module doc).
//!
//! A request holds, from its decode to its last renderer run: the padded source images (decoded
//! one at a time into their stack: the stack and one image being decoded), their
//! features and the encoding volume (and, while a slab-built volume is assembled, G2's first
//! convolution over it), then the target's rays and outputs and guided sampling's guidance. On
//! top of that, one stage at a time adds its working memory: the encoder's activations, the cost
//! volume (all of it with `volume.onnx`, one slab of planes with `cost_slab.onnx`, a band of rows
//! with the plane sweep) or G2; the stages run one after another, so the largest of them counts.
//!
//! A renderer run's working memory is not counted per request: renderer runs, every request's and
//! every model's, take turns on the one executor thread and share one ONNX Runtime arena, so the
//! process sets aside one run, the largest model's at the chunk policy's size, once
//! ([`renderer_run_bytes`], `Models::largest_renderer_run`). Nor is the request's body: it is
//! held against the budget by a lease as it arrives (`backend`'s module doc).
//!
//! Every term follows the request's sizes: the sources' pixels, the volume's cells, the planes
//! of one cost slab (as many as `--volume-slab-mb` gives the sources' size), the target's pixels.
//!
//! The per-unit figures are calibrated on measured peaks over a grid of source and target sizes
//! (`bench/memory.py`, the table in docs/results.md, "The estimate (admission by memory)"; the
//! rows are the fixture `tests/fixtures/memory/measured.json`, and a test checks that the
//! estimate never falls below any of them nor far above).

use crate::bundle::{ModelConfig, VolumeBuild};
use crate::pipeline::chunks::ChunkPolicy;
use crate::pipeline::volume::{plane_cells, SlabPolicy};

/// Encoder working memory per source pixel (V·H·W of the padded images). Measured 94-156 at
/// 320x256-800x800.
pub const ENCODER_BYTES_PER_PIXEL: u64 = 192;

/// Decoding one source image, per pixel, beside the stack it is decoded into: the decoder's
/// 8-bit buffer, its row buffers and a capture's file being read. Measured at 800x800 and
/// 1024x1024, less the stack and the body: 6-13 for a scene's upload, 30-45 for a capture's.
pub const DECODE_BYTES_PER_PIXEL: u64 = 56;

/// Reading one image's header, or decoding it, beside its pixels: the decoder's buffers and the
/// metadata it keeps, whatever the file holds (`scnerf_capture::images`).
const IMAGE_HEADER_BYTES: u64 = scnerf_capture::images::HEADER_BYTES as u64;

/// `volume.onnx`'s working memory per cell of the volume (D·Hp·Wp): the warped features of every
/// plane, the 41-channel cost volume and G2's activations at once. Measured 674-699.
pub const WHOLE_VOLUME_BYTES_PER_CELL: u64 = 800;

/// `volume_net.onnx`'s working memory per cell: G2's activations over the 8-channel volume.
/// Measured 140-170 above the conv0 input and the volume output (213-226 with them, 80x64 to
/// 640x512).
pub const VOLUME_NET_BYTES_PER_CELL: u64 = 208;

/// The sweep build's largest stage per cell beside the volume it makes: the run of
/// `volume_net.onnx` whose preparation computes G2's first convolution over the plane sweep (a
/// band of rows per thread), that convolution and G2's activations. The whole request measured
/// 98-102 above the process at rest per cell at 80x64-1024x1024, of which 32 are the volume and
/// 1-3 the images and features (the graph of the current exporter: one-pass norms need less than
/// the old ones' 208 of `VOLUME_NET_BYTES_PER_CELL`).
pub const SWEEP_BYTES_PER_CELL: u64 = 72;

/// One `cost_slab.onnx` run's working memory per cell of its planes (halo included): the warped
/// features and the 41-channel cost of those planes. Measured 600-730 (80x64 to 640x512).
pub const COST_SLAB_BYTES_PER_CELL: u64 = 800;

/// One renderer run's working memory per sample point (rays x samples): every point's features
/// through the MLP and the rectifiers. Measured 5.4-6.1 KiB with the paper-size `scnerf`
/// renderer at chunks of 455 rays (the default policy at 128 samples); guided sampling's runs,
/// sized to the same chunk policy, grew a fresh arena by at most 172 MiB of the 370 MiB this
/// gives (bench/memory.py, docs/results.md).
pub const RENDERER_BYTES_PER_SAMPLE: u64 = 6656;

/// What one request keeps for its lifetime per cell of the volume: the encoding volume (8
/// channels of f32).
const VOLUME_BYTES_PER_CELL: u64 = 32;

/// Bytes per target pixel: rays, the raw outputs and the encoded response. The band stage's
/// sightings of the sources (32 bytes, `band.rs`) are held after the renderer's runs and before
/// the response is encoded.
const TARGET_BYTES_PER_PIXEL: u64 = 128;

/// Per request whatever its size: bookkeeping, the response being encoded, allocator slack.
const PER_REQUEST_BYTES: u64 = 2 << 20;

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
    /// Padded width and height of the sources (`None`: a cached scene's view).
    pub sources: Option<(usize, usize)>,
    /// Source views the request decodes (0: its scene is decoded already).
    pub decoded_views: usize,
    /// Whether it builds a volume (encoder, cost volume, G2) from the model's view count of them.
    pub builds_volume: bool,
    /// Pixels of the view to render (0: none).
    pub target_pixels: u64,
    /// What the view's sampling holds beside its pixels (guided sampling's weights and heads).
    pub sampling_bytes: u64,
}

impl RequestSizes {
    /// A `/v1/render`: three sources decoded, their volume built, a view rendered.
    pub fn render(config: &ModelConfig, sources: (usize, usize), target_pixels: u64) -> RequestSizes {
        RequestSizes {
            sources: Some(sources),
            decoded_views: config.views,
            builds_volume: true,
            target_pixels,
            sampling_bytes: 0,
        }
    }
}

/// The request's estimate split into what it holds and the largest working set of its stages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
struct Estimate {
    /// Held from the decode to the last renderer run.
    held: u64,
    /// The largest of the decode's, the encoder's and the volume stages' working memory.
    stage: u64,
}

impl Estimate {
    fn total(&self) -> u64 {
        PER_REQUEST_BYTES + self.held + self.stage
    }
}

/// The estimate of one request: see the module doc.
pub fn estimate(config: &ModelConfig, plan: &MemoryPlan, sizes: &RequestSizes) -> u64 {
    parts(config, plan, sizes).total()
}

/// [`estimate`] by part.
fn parts(config: &ModelConfig, plan: &MemoryPlan, sizes: &RequestSizes) -> Estimate {
    let mut e = Estimate::default();
    let Some((w, h)) = sizes.sources else { return with_target(sizes, e) };
    let image_pixels = w as u64 * h as u64;
    if sizes.decoded_views > 0 {
        e.held += sizes.decoded_views as u64 * image_pixels * 3 * 4;
        e.stage = image_pixels * DECODE_BYTES_PER_PIXEL + IMAGE_HEADER_BYTES;
    }
    if sizes.builds_volume {
        let plane = plane_cells(config, w, h) as u64;
        let pixels = config.views as u64 * image_pixels;
        let cells = config.depth_planes as u64 * plane;
        // The images, unless decoded here (a triple taken from a scene's views is a copy), and
        // the features (feature_channels at 1/16 of the pixels), f32.
        let images = if sizes.decoded_views > 0 { 0 } else { pixels * 3 * 4 };
        let features = pixels / 16 * config.feature_channels as u64 * 4;
        let encoder = pixels * ENCODER_BYTES_PER_PIXEL;
        let volume = match plan.build {
            VolumeBuild::Whole => cells * WHOLE_VOLUME_BYTES_PER_CELL,
            VolumeBuild::Slabs => {
                // G2's first convolution over the volume, assembled slab by slab: held while
                // the slabs run and during G2.
                let conv0 = cells * config.volume_channels as u64 * 4;
                let planes = plan.slabs.planes_per_slab(config.depth_planes, plane as usize) as u64 + 2;
                let slab = planes * plane * COST_SLAB_BYTES_PER_CELL;
                conv0 + slab.max(cells * VOLUME_NET_BYTES_PER_CELL)
            }
            VolumeBuild::Sweep => cells * SWEEP_BYTES_PER_CELL,
        };
        e.held += images + features + cells * VOLUME_BYTES_PER_CELL;
        e.stage = e.stage.max(encoder).max(volume);
    }
    with_target(sizes, e)
}

/// `e` with the target's buffers.
fn with_target(sizes: &RequestSizes, mut e: Estimate) -> Estimate {
    e.held += sizes.target_pixels * TARGET_BYTES_PER_PIXEL + sizes.sampling_bytes;
    e
}

/// One renderer run's working memory for this model: a full chunk's (every renderer run, full,
/// guide or fine, is sized to the chunk policy's). Set aside once for the process (module doc),
/// whether ONNX Runtime's arena keeps it between requests or gives it back.
pub fn renderer_run_bytes(config: &ModelConfig, chunking: &ChunkPolicy) -> u64 {
    chunking.rays_per_chunk(config.samples) as u64 * config.samples as u64 * RENDERER_BYTES_PER_SAMPLE
}

/// What a scene of `views` padded `width` x `height` views keeps in the scene cache: the views'
/// images, and when its volume is built with them (the model's view count), the features and
/// the volume. The cache's own accounting (`Scene::bytes`, `Views::bytes`), before anything is
/// decoded.
pub fn scene_bytes(config: &ModelConfig, (w, h): (usize, usize), views: usize, builds_volume: bool) -> u64 {
    let images = (views * 3 * w * h) as u64;
    let built = builds_volume.then(|| {
        let features = views * config.feature_channels * (w / 4) * (h / 4);
        let volume = config.volume_channels * config.depth_planes * plane_cells(config, w, h);
        (features + volume) as u64
    });
    4 * (images + built.unwrap_or(0))
}

/// Reading a capture's text and metadata files (`metadata_bytes` of them): the text's copy and
/// what the readers build from it, per byte of it (measured on hostile files, docs/results.md);
/// a JSON file's values (~64 bytes each in `serde_json::Value`, at most one per byte and
/// `MAX_JSON_VALUES`); the depths ranked for a COLMAP model's near/far (at most `MAX_DEPTHS`, and
/// points x images: a record takes at least 16 bytes); and the image header being read (one at a
/// time).
pub fn capture_parse_bytes(metadata_bytes: u64) -> u64 {
    use scnerf_capture::readers::{colmap::MAX_DEPTHS, MAX_JSON_VALUES};
    const PER_BYTE: u64 = 8;
    let values = metadata_bytes.min(MAX_JSON_VALUES as u64);
    let records = metadata_bytes / 16;
    let depths = records.saturating_mul(records).min(MAX_DEPTHS as u64);
    PER_REQUEST_BYTES + metadata_bytes * PER_BYTE + values * 64 + depths * 8 + IMAGE_HEADER_BYTES
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bundle::ModelConfig;
    use crate::pipeline::sources::padded_size;

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
        /// A render's three, or a scene's upload (with no target).
        #[serde(default = "three")]
        views: usize,
        /// [0, 0]: a scene's upload.
        target: [u64; 2],
        /// A capture's upload (`POST /v1/captures`) rather than a scene's, with its metadata's
        /// bytes.
        #[serde(default)]
        capture: bool,
        #[serde(default)]
        metadata_bytes: u64,
        /// The request's body: its images (a capture's files), leased apart from the estimate.
        #[serde(default)]
        body_bytes: u64,
        peak_above_rest_mib: f64,
        /// A render's peak before its first renderer run (its decode, encoder and volume).
        before_renderer_peak_above_rest_mib: Option<f64>,
    }

    fn three() -> usize {
        3
    }

    fn measured() -> Measured {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/fixtures/memory/measured.json");
        serde_json::from_str(&std::fs::read_to_string(path).expect(path)).expect("measured.json")
    }

    fn plan(build: VolumeBuild) -> MemoryPlan {
        MemoryPlan { build, slabs: SlabPolicy::default(), chunking: ChunkPolicy::default() }
    }

    fn mib(bytes: u64) -> f64 {
        bytes as f64 / (1 << 20) as f64
    }

    /// What the budget holds for a measured row, MiB: its body's lease and its estimate: a
    /// render's (guided sampling, the server's default: its guidance, not its guide rays' heads,
    /// which need the bundle's policy and are at most ~12 MiB at these targets), a scene's
    /// upload, or a capture's (the larger of parsing its metadata and decoding its views as a
    /// scene's).
    fn held_for(row: &Row, config: &ModelConfig, build: VolumeBuild) -> f64 {
        let padded = padded_size(row.sources[0], row.sources[1], config.image_multiple);
        let (tw, th) = (row.target[0], row.target[1]);
        let estimate = match tw * th {
            0 => {
                let upload = RequestSizes {
                    sources: Some(padded),
                    decoded_views: row.views,
                    builds_volume: row.views == config.views,
                    target_pixels: 0,
                    sampling_bytes: 0,
                };
                let scene = estimate(config, &plan(build), &upload);
                if row.capture {
                    scene.max(capture_parse_bytes(row.metadata_bytes))
                } else {
                    scene
                }
            }
            pixels => {
                let guidance = crate::pipeline::guided::Guidance::bytes(tw as usize, th as usize, config.samples);
                let sizes = RequestSizes { sampling_bytes: guidance, ..RequestSizes::render(config, padded, pixels) };
                estimate(config, &plan(build), &sizes)
            }
        };
        mib(row.body_bytes + estimate)
    }

    #[test]
    fn never_below_a_measured_peak_nor_far_above() {
        let m = measured();
        assert!(m.rows.len() >= 6, "the fixture holds the measured table");
        let renders = m.rows.iter().filter(|r| r.target != [0, 0]).count();
        let own = m.rows.iter().filter(|r| r.before_renderer_peak_above_rest_mib.is_some()).count();
        assert!(own * 2 > renders, "most renders say their peak before the renderer");
        for row in &m.rows {
            let config = &m.bundles[&row.bundle].config;
            let build = match row.build.as_str() {
                "sweep" => VolumeBuild::Sweep,
                "slabs" => VolumeBuild::Slabs,
                _ => VolumeBuild::Whole,
            };
            let held = held_for(row, config, build);
            let measured = row.peak_above_rest_mib;
            // A fresh server's first render grows the renderers' arena: what the budget sets
            // aside once for one renderer run.
            let renderer = match row.target {
                [0, 0] => 0.0,
                _ => mib(renderer_run_bytes(config, &ChunkPolicy::default())),
            };
            let (w, h) = (row.sources[0], row.sources[1]);
            let kind = if row.capture { "capture" } else { "views" };
            let what = format!("{} {} {w}x{h} {kind} x{} -> {:?}", row.bundle, row.build, row.views, row.target);
            eprintln!("{what}: measured {measured:.0} MiB, held for it {held:.0} MiB (+ {renderer:.0} renderer)");
            assert!(held + renderer >= measured, "{what}: {held:.0} + {renderer:.0} < measured {measured:.0}");
            if let Some(before) = row.before_renderer_peak_above_rest_mib {
                assert!(held >= before, "{what}: {held:.0} < {before:.0} measured before the renderer");
            }
            // An estimate far above the truth wastes the budget. The plane sweep's rows (the
            // default bundle's build, measured with the current server): within 1.3x, or 12 MiB
            // for the smallest uploads, where the bounds for one image (its header's 4 MiB, its
            // decode) outweigh them. The other builds', measured with older servers: at most 2.5x
            // and 256 MiB.
            let most = match build {
                VolumeBuild::Sweep => (1.3 * measured).max(measured + 12.0),
                _ => 2.5 * measured + 256.0,
            };
            assert!(held <= most, "{what}: {held:.0} MiB held for {measured:.0} measured");
        }
    }

    #[test]
    fn grows_with_the_sources_and_is_smaller_slab_by_slab() {
        let config = measured().bundles.into_values().next().unwrap().config;
        let at = |w, h, build| estimate(&config, &plan(build), &RequestSizes::render(&config, (w, h), 80 * 64));
        assert!(at(640, 512, VolumeBuild::Whole) > at(320, 256, VolumeBuild::Whole));
        assert!(at(1024, 1024, VolumeBuild::Slabs) > at(800, 800, VolumeBuild::Slabs));
        assert!(at(800, 800, VolumeBuild::Slabs) * 2 < at(800, 800, VolumeBuild::Whole));
        assert!(at(800, 800, VolumeBuild::Sweep) < at(800, 800, VolumeBuild::Slabs));
        // A cached scene's view: the target's buffers only.
        let cached = RequestSizes {
            sources: None,
            decoded_views: 0,
            builds_volume: false,
            target_pixels: 100,
            sampling_bytes: 0,
        };
        let view = estimate(&config, &plan(VolumeBuild::Whole), &cached);
        assert!(view < at(320, 256, VolumeBuild::Whole) && view > PER_REQUEST_BYTES);
    }
}
