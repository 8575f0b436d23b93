//! Shared by the parity tests of the bundles whose volume is built slab by slab (parity_slabs.rs)
//! or from the server's plane sweep (parity_sweep.rs): the parity fixture bundle with its
//! `volume.onnx` split (`scnerf-export fixtures` writes them beside it, under tests/fixtures: the
//! new volume graphs and the manifest; the other graphs are the parity bundle's own, checked
//! against the manifest's hashes when the bundle loads), and the check that every parity case's
//! volume and view are PyTorch's however the pipeline is configured.

use std::path::{Path, PathBuf};

use scnerf_server::pipeline::scene::Timings;
use scnerf_server::pipeline::sources::padded_size;
use scnerf_server::pipeline::Pipeline;
use scnerf_server::request::Sampling;
use scnerf_server::request::{ImageMode, Limits, RenderRequest, ValidRequest};
use scnerf_server::testing::ort_pipeline;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures")
}

/// The split bundle of `fixtures/<split>` assembled in a temporary folder: its manifest, and each
/// graph the manifest names from `<split>` or else from the parity bundle; loaded (one per test
/// process: ONNX Runtime's environment is process-wide).
pub fn split_pipeline(split: &str) -> Pipeline {
    let dir = std::env::temp_dir().join(format!("scnerf-{split}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let manifest = fixtures().join(split).join("manifest.json");
    std::fs::copy(&manifest, dir.join("manifest.json")).unwrap();
    let manifest: serde_json::Value = serde_json::from_slice(&std::fs::read(&manifest).unwrap()).unwrap();
    for graph in manifest["graphs"].as_object().unwrap().values() {
        let file = graph["file"].as_str().unwrap();
        let own = fixtures().join(split).join(file);
        let from = if own.is_file() { own } else { fixtures().join("parity/bundle").join(file) };
        std::fs::copy(from, dir.join(file)).unwrap();
    }
    let p = ort_pipeline(&dir, Limits::default(), 16);
    let _ = std::fs::remove_dir_all(&dir); // the sessions hold what they need
    p
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

/// Cells of one plane of the volume of a case's sources.
pub fn plane_cells(p: &Pipeline, req: &ValidRequest) -> usize {
    let cameras = req.scene.cameras();
    let (c, pad) = (&cameras[0], p.config().pad);
    let (w, h) = padded_size(c.width as usize, c.height as usize, p.config().image_multiple);
    (h / 4 + 2 * pad) * (w / 4 + 2 * pad)
}

/// Every parity case's volume, built by each of `variants` (a name and the pipeline for a case's
/// plane cells), is PyTorch's within its tolerance and renders PyTorch's view; all variants give
/// the same volume, bit for bit.
pub async fn volumes_match_pytorch(p: &Pipeline, variants: &[(&str, &dyn Fn(usize) -> Pipeline)]) {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(600);
    for case in cases() {
        let name = case.file_name().unwrap().to_string_lossy().to_string();
        let req = request(p, &case);
        let mut volumes = Vec::new();
        for (variant, pipeline_for) in variants {
            let pipeline = pipeline_for(plane_cells(p, &req));
            let ticket = pipeline.admit(deadline, Default::default(), 0).unwrap();
            let mut timings = Timings::default();
            let scene = pipeline.prepare_scene(&ticket, &req.scene, &mut timings).await.unwrap();
            let err = max_abs(&scene.volume, &expected(&case, "volume"));
            eprintln!("{name}, {variant}: volume max error {err:.3e}");
            assert!(err <= 1e-4, "{name}: volume error {err:.3e} with {variant}");
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
            assert!(err <= 1e-3, "{name}: rgb error {err:.3e} with {variant}");
            volumes.push(scene.volume);
        }
        for (v, (variant, _)) in volumes[1..].iter().zip(&variants[1..]) {
            assert_eq!(max_abs(v, &volumes[0]), 0.0, "{name}: {variant} gives another volume than {}", variants[0].0);
        }
    }
}
