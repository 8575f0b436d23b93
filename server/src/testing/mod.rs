//! Test support (not part of the API, and compiled only for tests: the unit tests, or the `testing`
//! feature the test crates turn on): a fake graph runner with the bundle contract's shapes, a
//! manifest for it, and request builders. Lets the HTTP layer be tested without ONNX Runtime.
//! `models.rs`: servers of several models over fakes, and bundle folders on disk; `interrupt.rs`:
//! the fake runner's terminate flag.

mod interrupt;
mod models;

pub use interrupt::FakeInterrupt;
pub use models::{models_state, models_state_with, named_bundle, reload_state, write_bundle, FakeModel};

use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use crate::backend::ort::{OrtOptions, OrtRunner};
use ndarray::{Array2, ArrayD, Axis, Ix2, IxDyn};
use scnerf_capture::camera::{Axes, Intrinsics, PoseKind};
use scnerf_capture::wire::{WireCamera, WireIntrinsics, WirePose};

use crate::backend::device::GraphOptLevel;
use crate::backend::{BackendError, BackendHandle, ExecutorOptions, GraphRunner, Interrupt, NamedTensors, Tensor};
use crate::bundle::GuidedPolicy;
use crate::bundle::{validate_manifest, Bundle, GraphKind, Manifest};
use crate::http::{AppState, ServiceOptions};
use crate::pipeline::chunks::ChunkPolicy;
use crate::pipeline::volume::SlabPolicy;
use crate::pipeline::Pipeline;
use crate::request::Limits;

/// A manifest that satisfies the contract, with a small config (fast fake volumes).
pub fn manifest(variant: &str, depth_norm: &str) -> Manifest {
    let sha = "cd".repeat(32);
    let (v, c, cv, d) = (3, 32, 8, 8);
    let t =
        |name: &str, shape: serde_json::Value| serde_json::json!({"name": name, "shape": shape, "dtype": "float32"});
    let mut renderer_inputs = vec![
        t("ray_origins", serde_json::json!(["R", 3])),
        t("ray_directions", serde_json::json!(["R", 3])),
        t("near_far", serde_json::json!([2])),
        t("volume", serde_json::json!([1, cv, d, "Hp", "Wp"])),
        t("images", serde_json::json!([v, 3, "H", "W"])),
        t("intrinsics", serde_json::json!([v, 3, 3])),
        t("extrinsics", serde_json::json!([v, 4, 4])),
    ];
    if variant != "mvsnerf" {
        renderer_inputs.push(t("depth_range", serde_json::json!([2])));
        renderer_inputs.push(t("features", serde_json::json!([v, c, "h", "w"])));
    }
    let json = serde_json::json!({
        "format_version": 1,
        "model_id": "set below",
        "variant": variant,
        "config": {"views": v, "feature_channels": c, "volume_channels": cv, "depth_planes": d,
                   "samples": 16, "pad": 2, "image_multiple": 32, "depth_norm": depth_norm,
                   "mlp_width": 128},
        "graphs": {
            "encoder": {"file": "encoder.onnx", "sha256": "00",
                "inputs": [t("images", serde_json::json!([v, 3, "H", "W"]))],
                "outputs": [t("features", serde_json::json!([v, c, "h", "w"]))]},
            "volume": {"file": "volume.onnx", "sha256": "00",
                "inputs": [t("features", serde_json::json!([v, c, "h", "w"])),
                           t("images", serde_json::json!([v, 3, "H", "W"])),
                           t("projections", serde_json::json!([v, 4, 4])),
                           t("depth_planes", serde_json::json!([d]))],
                "outputs": [t("volume", serde_json::json!([1, cv, d, "Hp", "Wp"]))]},
            "renderer": {"file": "renderer.onnx", "sha256": sha,
                "inputs": renderer_inputs,
                "outputs": [t("rgb", serde_json::json!(["R", 3])), t("depth", serde_json::json!(["R"])),
                            t("opacity", serde_json::json!(["R"]))]}
        },
        "provenance": {"source_checkpoint": "fake", "source_sha256": "00", "exporter_version": "0.0.0",
                       "training": null, "metrics": null, "created": "2026-01-01T00:00:00Z"}
    });
    let mut manifest: Manifest = serde_json::from_value(json).expect("test manifest");
    manifest.model_id = manifest.expected_model_id();
    manifest
}

pub fn bundle(variant: &str, depth_norm: &str) -> Bundle {
    bundle_of(manifest(variant, depth_norm))
}

/// [`manifest`] with guided sampling's graphs and policy (one rectifier's heads, 4 x 8 floats).
pub fn guided_manifest(variant: &str) -> Manifest {
    let mut m = manifest(variant, "near_far");
    let mut value = serde_json::to_value(&m).expect("manifest serialises");
    value["config"]["heads"] = 2.into();
    value["config"]["head_dim"] = 2.into();
    value["config"]["width"] = 8.into();
    let renderer = value["graphs"]["renderer"].clone();
    let heads = |rays: &str| serde_json::json!({"name": "geometry_heads", "shape": [rays, 4, 8], "dtype": "float32"});
    let t =
        |name: &str, shape: serde_json::Value| serde_json::json!({"name": name, "shape": shape, "dtype": "float32"});
    let mut guide = renderer.clone();
    guide["file"] = "renderer_guide.onnx".into();
    guide["outputs"]
        .as_array_mut()
        .expect("outputs")
        .extend([t("sample_weights", serde_json::json!(["R", 16])), heads("R")]);
    let mut fine = renderer;
    fine["file"] = "renderer_fine.onnx".into();
    fine["inputs"].as_array_mut().expect("inputs").extend([
        t("sample_index", serde_json::json!(["R", "K"])),
        t("sample_multiplicity", serde_json::json!(["R", "K"])),
        heads("G"),
        t("head_index", serde_json::json!(["R"])),
    ]);
    fine["outputs"].as_array_mut().expect("outputs").push(t("sample_weights", serde_json::json!(["R", "K"])));
    value["graphs"]["renderer_guide"] = guide;
    value["graphs"]["renderer_fine"] = fine;
    value["guided"] = serde_json::json!({"step": 4, "samples": [8, 4], "support_threshold": 0.001,
                                         "smooth_tolerance": 0.03, "smooth_max_step": 1});
    m = serde_json::from_value(value).expect("guided test manifest");
    m.model_id = m.expected_model_id();
    m
}

/// A bundle of [`guided_manifest`]'s.
pub fn guided_bundle(variant: &str) -> Bundle {
    bundle_of(guided_manifest(variant))
}

/// [`guided_bundle`] with another policy.
pub fn guided_bundle_with(variant: &str, policy: GuidedPolicy) -> Bundle {
    let mut manifest = guided_manifest(variant);
    manifest.guided = Some(policy);
    bundle_of(manifest)
}

pub(crate) fn bundle_of(manifest: Manifest) -> Bundle {
    let config = validate_manifest(&manifest).expect("test manifest is valid");
    Bundle { dir: "/nonexistent/fake".into(), manifest, config }
}

/// Deterministic stand-in for the three graphs. The renderer is a per-ray function of the inputs
/// (so, like the real graph, independent of chunking); it depends on depth_range so that
/// two-pass depth normalisation is exercised.
pub struct FakeRunner {
    pub config: crate::bundle::ModelConfig,
    /// Every call fails with this message (to test error paths).
    pub fail_with: Option<String>,
    /// Sleep per call (to test deadlines and scheduling); the watchdog's interrupt ends it, as
    /// ONNX Runtime's terminate flag ends a run.
    pub delay: Duration,
    pub interrupt: Arc<FakeInterrupt>,
    /// Graph runs so far, by kind (`GraphKind::index`), to see which work was dropped.
    pub calls: Arc<[AtomicUsize; GraphKind::ALL.len()]>,
    /// The cameras each renderer run was fed, in order: to check them against a request's.
    pub renderer_cameras: Arc<Mutex<Vec<RendererCameras>>>,
    /// Scales the rendered colours: two models' fakes that differ in it render different views.
    pub tint: f32,
}

/// The camera inputs of one renderer run: the sources' (what the volume was built from) and the
/// target's rays.
#[derive(Debug, Clone)]
pub struct RendererCameras {
    pub graph: GraphKind,
    /// (V, 3, 3) K per source view.
    pub intrinsics: ArrayD<f32>,
    /// (V, 4, 4) world-to-camera per source view.
    pub extrinsics: ArrayD<f32>,
    /// (R, 3) each ray's origin and direction (`R_c2w [(u - cx) / fx, (v - cy) / fy, 1]`).
    pub ray_origins: Array2<f32>,
    pub ray_directions: Array2<f32>,
}

impl FakeRunner {
    pub fn new(bundle: &Bundle) -> FakeRunner {
        FakeRunner {
            config: bundle.config.clone(),
            fail_with: None,
            delay: Duration::ZERO,
            interrupt: Arc::default(),
            calls: Arc::default(),
            renderer_cameras: Arc::default(),
            tint: 1.0,
        }
    }
}

fn input<'a>(inputs: &'a NamedTensors, name: &str) -> &'a Tensor {
    &inputs.iter().find(|(n, _)| n == name).unwrap_or_else(|| panic!("fake runner: no input {name}")).1
}

impl GraphRunner for FakeRunner {
    fn interrupter(&self) -> Option<Arc<dyn Interrupt>> {
        Some(self.interrupt.clone())
    }

    fn run(&mut self, graph: GraphKind, inputs: &NamedTensors) -> Result<NamedTensors, BackendError> {
        self.calls[graph.index()].fetch_add(1, Ordering::SeqCst);
        if self.interrupt.sleep(self.delay) {
            return Err(BackendError::Run {
                graph,
                message: "Exiting due to terminate flag being set to true.".into(),
            });
        }
        if let Some(message) = &self.fail_with {
            return Err(BackendError::Run { graph, message: message.clone() });
        }
        if matches!(graph, GraphKind::Renderer | GraphKind::RendererGuide | GraphKind::RendererFine) {
            let rays = |name| input(inputs, name).view().into_dimensionality::<Ix2>().expect("(R, 3) rays").to_owned();
            self.renderer_cameras.lock().unwrap().push(RendererCameras {
                graph,
                intrinsics: input(inputs, "intrinsics").to_owned(),
                extrinsics: input(inputs, "extrinsics").to_owned(),
                ray_origins: rays("ray_origins"),
                ray_directions: rays("ray_directions"),
            });
        }
        let c = &self.config;
        let filled = |shape: &[usize], value: f32| ArrayD::from_elem(IxDyn(shape), value).into_shared();
        Ok(match graph {
            GraphKind::Encoder => {
                let images = input(inputs, "images");
                let (v, h, w) = (images.shape()[0], images.shape()[2] / 4, images.shape()[3] / 4);
                let mean = images.iter().sum::<f32>() / images.len() as f32;
                vec![("features".into(), filled(&[v, c.feature_channels, h, w], mean))]
            }
            GraphKind::Volume | GraphKind::CostSlab => {
                let f = input(inputs, "features");
                let (hp, wp) = (f.shape()[2] + 2 * c.pad, f.shape()[3] + 2 * c.pad);
                let (name, planes) = match graph {
                    GraphKind::Volume => ("volume", c.depth_planes),
                    _ => ("conv0", input(inputs, "depth_planes").len() - 2),
                };
                vec![(name.into(), filled(&[1, c.volume_channels, planes, hp, wp], f[[0, 0, 0, 0]]))]
            }
            GraphKind::CostConv => {
                let cost = input(inputs, "cost");
                let (planes, hp, wp) = (cost.shape()[2] - 2, cost.shape()[3], cost.shape()[4]);
                let mean = cost.iter().sum::<f32>() / cost.len() as f32;
                vec![("conv0".into(), filled(&[1, c.volume_channels, planes, hp, wp], mean))]
            }
            GraphKind::VolumeNet => {
                let conv0 = input(inputs, "conv0");
                vec![("volume".into(), filled(conv0.shape(), conv0[[0, 0, 0, 0, 0]]))]
            }
            GraphKind::Renderer => fake_pixels(inputs, self.tint),
            GraphKind::RendererGuide => {
                let rays = input(inputs, "ray_origins").shape()[0];
                let mut out = fake_pixels(inputs, self.tint);
                // All weight on the middle sample; heads of zeros (4 x 8 per ray).
                let mut weights = ArrayD::zeros(IxDyn(&[rays, c.samples]));
                weights.index_axis_mut(Axis(1), c.samples / 2).fill(1.0);
                out.push(("sample_weights".into(), weights.into_shared()));
                out.push(("geometry_heads".into(), filled(&[rays, 4, 8], 0.0)));
                out
            }
            GraphKind::RendererFine => {
                let index = input(inputs, "sample_index");
                let (rays, k) = (index.shape()[0], index.shape()[1]);
                let mut out = fake_pixels(inputs, self.tint);
                out.push(("sample_weights".into(), filled(&[rays, k], 1.0 / k as f32)));
                out
            }
        })
    }
}

/// The fake renderers' pixels: per ray, functions of its unit direction.
fn fake_pixels(inputs: &NamedTensors, tint: f32) -> NamedTensors {
    let dirs = input(inputs, "ray_directions").view().into_dimensionality::<Ix2>().expect("(R, 3) rays");
    let near = input(inputs, "near_far")[0];
    let range = inputs.iter().find(|(n, _)| n == "depth_range").map_or(1.0, |(_, t)| t[1] - t[0]);
    let norm = dirs.map_axis(Axis(1), |d| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt());
    let unit = &dirs / &norm.insert_axis(Axis(1));
    vec![
        ("rgb".into(), unit.mapv(|x| (0.5 * tint * x.abs()).min(1.0)).into_shared().into_dyn()),
        ("depth".into(), unit.column(0).mapv(|x| near + x.abs() * range).into_shared().into_dyn()),
        ("opacity".into(), unit.column(1).mapv(|x| 0.5 + 0.5 * x.abs()).into_shared().into_dyn()),
    ]
}

/// An AppState over the fake runner, ready at once.
pub fn state_with(bundle: Bundle, runner: FakeRunner, limits: Limits, timeout: Duration) -> AppState {
    state_with_queue(bundle, runner, limits, timeout, 8)
}

pub fn state_with_queue(
    bundle: Bundle,
    runner: FakeRunner,
    limits: Limits,
    timeout: Duration,
    queue: usize,
) -> AppState {
    state_with_options(bundle, runner, limits, ServiceOptions { request_timeout: timeout, ..Default::default() }, queue)
}

/// The general form: any service options (cache size and TTL, deadline, auth...).
pub fn state_with_options(
    bundle: Bundle,
    runner: FakeRunner,
    limits: Limits,
    options: ServiceOptions,
    queue: usize,
) -> AppState {
    state_with_executor(bundle, runner, limits, options, ExecutorOptions::with_capacity(queue))
}

/// [`state_with_options`] with any executor settings (a memory budget).
pub fn state_with_executor(
    bundle: Bundle,
    runner: FakeRunner,
    limits: Limits,
    options: ServiceOptions,
    executor: ExecutorOptions,
) -> AppState {
    let backend = BackendHandle::spawn(Box::new(runner), executor).expect("spawn backend");
    let chunking = ChunkPolicy { max_rays: 100, memory_budget_bytes: usize::MAX };
    let pipeline = Pipeline::new(backend, bundle, chunking, SlabPolicy::default(), limits);
    ready_state(pipeline, options)
}

/// The router's state over `pipeline`, ready at once (no warm-up render).
pub fn ready_state(pipeline: Pipeline, options: ServiceOptions) -> AppState {
    let state = AppState::new(pipeline, options);
    state.set_ready();
    state
}

/// A pipeline over the real graphs of the bundle in `dir` with ONNX Runtime (all CPUs, default
/// chunking), `queue` requests admitted at once. ONNX Runtime's environment is process-wide:
/// one such pipeline per test process, shared by its tests.
pub fn ort_pipeline(dir: &Path, limits: Limits, queue: usize) -> Pipeline {
    ort_pipeline_with(dir, limits, ExecutorOptions::with_capacity(queue))
}

/// [`ort_pipeline`] with any executor settings (a memory budget).
pub fn ort_pipeline_with(dir: &Path, limits: Limits, executor: ExecutorOptions) -> Pipeline {
    let bundle = Bundle::load(dir).unwrap_or_else(|e| panic!("{e}"));
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let opts = OrtOptions { dylib: None, intra_threads: threads, opt_level: GraphOptLevel::All, spin: false };
    let runner = OrtRunner::load(&bundle, &opts).unwrap_or_else(|e| panic!("{e}"));
    let backend = BackendHandle::spawn(Box::new(runner), executor).expect("spawn backend");
    Pipeline::new(backend, bundle, ChunkPolicy::default(), SlabPolicy::default(), limits)
}

pub fn fake_state() -> AppState {
    let bundle = bundle("scnerf", "near_far");
    let runner = FakeRunner::new(&bundle);
    state_with(bundle, runner, Limits::default(), Duration::from_secs(60))
}

/// A canonical camera: 8x6, at the origin looking along +z.
pub fn camera() -> crate::camera::CanonicalCamera {
    crate::camera::CanonicalCamera {
        width: 8,
        height: 6,
        k: nalgebra::Matrix3::new(8.0, 0.0, 4.0, 0.0, 8.0, 3.0, 0.0, 0.0, 1.0),
        w2c: nalgebra::Matrix4::identity(),
    }
}

/// A PNG of the given size and colour.
pub fn png(width: u32, height: u32, rgba: [u8; 4]) -> Vec<u8> {
    let img = image::RgbaImage::from_pixel(width, height, image::Rgba(rgba));
    let mut out = Vec::new();
    image::DynamicImage::ImageRgba8(img)
        .write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)
        .expect("png");
    out
}

/// A camera in docs/design.md's JSON form: Blender-style camera-to-world, OpenGL axes, on a circle of
/// radius 4 around the origin at angle `angle`, looking at the origin. A JSON value, for tests to
/// edit into what a client might send.
pub fn camera_json(width: u32, height: u32, angle: f64) -> serde_json::Value {
    let (s, c) = angle.sin_cos();
    let (w, h) = (f64::from(width), f64::from(height));
    let camera = WireCamera {
        width,
        height,
        intrinsics: Some(WireIntrinsics::Focal(Intrinsics { fx: w, fy: w, cx: w / 2.0, cy: h / 2.0 })),
        k: None,
        // OpenGL camera looks down its -z: put z_cam = (s, 0, c) pointing away from the origin.
        pose: WirePose {
            matrix: [[c, 0.0, s, 4.0 * s], [0.0, 1.0, 0.0, 0.0], [-s, 0.0, c, 4.0 * c], [0.0, 0.0, 0.0, 1.0]],
            kind: PoseKind::CameraToWorld,
            axes: Axes::Opengl,
        },
    };
    serde_json::to_value(camera).expect("a camera is JSON")
}

/// A valid request JSON without images: 3 sources of `size`, an 8x6 target.
pub fn request_json(size: u32) -> serde_json::Value {
    serde_json::json!({
        "sources": [{"camera": camera_json(size, size, -0.2)}, {"camera": camera_json(size, size, 0.0)},
                    {"camera": camera_json(size, size, 0.2)}],
        "target": camera_json(8, 6, 0.1),
        "near": 2.0, "far": 6.0,
        "background": [1.0, 1.0, 1.0],
        "outputs": ["rgb"]
    })
}

/// A well-formed PNG that claims `width` x `height` RGB pixels but carries almost no data: what a
/// decompression bomb looks like to a header reader (e.g. 100000 x 100000 = 30 GB decoded).
pub fn png_header(width: u32, height: u32) -> Vec<u8> {
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&width.to_be_bytes());
    ihdr.extend_from_slice(&height.to_be_bytes());
    ihdr.extend_from_slice(&[8, 2, 0, 0, 0]); // 8-bit, RGB, deflate, no filter, no interlace
    png_chunk(&mut out, b"IHDR", &ihdr);
    // A zlib stream of a few zero bytes: far fewer rows than the header promises.
    png_chunk(&mut out, b"IDAT", &[0x78, 0x9c, 0x63, 0x00, 0x00, 0x00, 0x01, 0x00, 0x01]);
    png_chunk(&mut out, b"IEND", &[]);
    out
}

/// `png` with `chunks` (type, data) between its header and its image data, where metadata goes:
/// colour-profile and text bombs, chunk floods.
pub fn png_with_chunks<'a>(png: &[u8], chunks: impl IntoIterator<Item = (&'a [u8; 4], &'a [u8])>) -> Vec<u8> {
    // The signature (8 bytes) and the IHDR chunk (25) come first.
    let (head, rest) = png.split_at(33);
    let mut out = head.to_vec();
    for (kind, data) in chunks {
        png_chunk(&mut out, kind, data);
    }
    out.extend_from_slice(rest);
    out
}

fn png_chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    out.extend_from_slice(&(data.len() as u32).to_be_bytes());
    let start = out.len();
    out.extend_from_slice(kind);
    out.extend_from_slice(data);
    let crc = crc32(&out[start..]);
    out.extend_from_slice(&crc.to_be_bytes());
}

/// CRC-32 (IEEE), bitwise: PNG chunk checksums for the test images above.
fn crc32(data: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in data {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
        }
    }
    !crc
}
