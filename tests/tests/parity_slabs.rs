//! Parity of the slab-by-slab volume build: the parity fixture bundle with its `volume.onnx`
//! split into `cost_slab.onnx` and `volume_net.onnx` (`scnerf-export split-volume`, committed
//! under tests/fixtures/parity-slabs: the two graphs and the manifest; the encoder and renderer
//! are the parity bundle's own, checked against the manifest's hashes when the bundle loads)
//! renders every parity case within the PyTorch tolerances, and its volume does not depend on
//! how many planes a slab run takes. A test binary of its own: ONNX Runtime's environment is
//! process-wide, one bundle per process.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use scnerf_server::bundle::VolumeBuild;
use scnerf_server::pipeline::chunks::ChunkPolicy;
use scnerf_server::pipeline::guided::Sampling;
use scnerf_server::pipeline::sources::padded_size;
use scnerf_server::pipeline::volume::{SlabPolicy, SLAB_BYTES_PER_CELL};
use scnerf_server::pipeline::{Pipeline, Timings};
use scnerf_server::request::{ImageMode, Limits, RenderRequest, ValidRequest};
use scnerf_server::testing::ort_pipeline;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures")
}

/// The split bundle assembled in a temporary folder (the encoder and renderer copied from the
/// parity bundle), loaded once per process.
fn pipeline() -> Pipeline {
    static PIPELINE: OnceLock<Pipeline> = OnceLock::new();
    PIPELINE
        .get_or_init(|| {
            let dir = std::env::temp_dir().join(format!("scnerf-parity-slabs-{}", std::process::id()));
            std::fs::create_dir_all(&dir).unwrap();
            for (from, file) in [
                ("parity/bundle", "encoder.onnx"),
                ("parity/bundle", "renderer.onnx"),
                ("parity-slabs", "cost_slab.onnx"),
                ("parity-slabs", "volume_net.onnx"),
                ("parity-slabs", "manifest.json"),
            ] {
                std::fs::copy(fixtures().join(from).join(file), dir.join(file)).unwrap();
            }
            let p = ort_pipeline(&dir, Limits::default(), 16);
            let _ = std::fs::remove_dir_all(&dir); // the sessions hold what they need
            p
        })
        .clone()
}

/// The same graphs and executor, `planes` depth planes per cost slab run.
fn with_slabs(p: &Pipeline, planes: usize, cells: usize) -> Pipeline {
    let policy = SlabPolicy { memory_budget_bytes: (planes + 2) * SLAB_BYTES_PER_CELL * cells };
    Pipeline::new(p.executor().clone(), p.bundle().clone(), ChunkPolicy::default(), policy, Limits::default())
}

fn cases() -> Vec<PathBuf> {
    let mut cases: Vec<PathBuf> = std::fs::read_dir(fixtures().join("parity/cases"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.join("request.json").is_file())
        .collect();
    cases.sort();
    assert!(!cases.is_empty());
    cases
}

fn request(p: &Pipeline, case: &Path) -> ValidRequest {
    let json = std::fs::read(case.join("request.json")).unwrap();
    let mut req = RenderRequest::from_json(&json, ImageMode::Parts, &Limits::default()).unwrap();
    for (i, s) in req.scene.sources.iter_mut().enumerate() {
        s.image = Some(std::fs::read(case.join(format!("source_{i}.png"))).unwrap().into());
    }
    req.validate(p.config(), &Limits::default()).unwrap()
}

fn expected(case: &Path, name: &str) -> Vec<f32> {
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(case.join("expected.json")).unwrap()).unwrap();
    let bytes = std::fs::read(case.join(json["files"][name].as_str().unwrap())).unwrap();
    bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
}

fn max_abs<'a>(a: impl IntoIterator<Item = &'a f32>, b: impl IntoIterator<Item = &'a f32>) -> f64 {
    a.into_iter().zip(b).map(|(x, y)| f64::from((x - y).abs())).fold(0.0, f64::max)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slab_built_volume_matches_pytorch_whatever_the_slab_size() {
    let p = pipeline();
    assert_eq!(p.bundle().volume_build(), VolumeBuild::Slabs);
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(600);
    for case in cases() {
        let name = case.file_name().unwrap().to_string_lossy().to_string();
        let req = request(&p, &case);
        let cameras = req.scene.cameras();
        let (c, pad) = (&cameras[0], p.config().pad);
        let (w, h) = padded_size(c.width as usize, c.height as usize, p.config().image_multiple);
        let cells = (h / 4 + 2 * pad) * (w / 4 + 2 * pad);
        let mut volumes = Vec::new();
        // One plane per run, five (the last slab shorter), and all planes in one run.
        for planes in [1, 5, p.config().depth_planes] {
            let pipeline = with_slabs(&p, planes, cells);
            let ticket = pipeline.admit(deadline, Default::default(), 0).unwrap();
            let mut timings = Timings::default();
            let scene = pipeline.prepare_scene(&ticket, &req.scene, &mut timings).await.unwrap();
            let err = max_abs(&scene.volume, &expected(&case, "volume"));
            eprintln!("{name}: {planes} planes per slab: volume max error {err:.3e}");
            assert!(err <= 1e-4, "{name}: volume error {err:.3e} with {planes} planes per slab");
            let view = pipeline
                .render_view(
                    &ticket,
                    &scene,
                    &req.view.target,
                    req.scene.background,
                    Sampling::Full,
                    None,
                    &mut timings,
                )
                .await
                .unwrap();
            let err = max_abs(&view.rgb, &expected(&case, "rgb"));
            assert!(err <= 1e-3, "{name}: rgb error {err:.3e} with {planes} planes per slab");
            volumes.push(scene.volume);
        }
        for v in &volumes[1..] {
            assert_eq!(max_abs(v, &volumes[0]), 0.0, "{name}: the volume depends on the slab size");
        }
    }
}
