//! Parity with the exporter's PyTorch reference: every case under tests/fixtures/parity/cases is
//! rendered through the Rust pipeline (request parsing, camera conversion, image decoding,
//! ONNX Runtime, chunking, assembly) and compared stage by stage with the committed tensors.
//!
//! The fixtures are committed, so a missing fixture directory is a failure, not a skip.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use axum::body::Body;
use axum::http::Request;
use base64::Engine;
use http_body_util::BodyExt;
use scnerf_e2e::{split_request, Case};
use scnerf_server::bundle::{BandRule, Bundle, DepthNorm, GraphKind};
use scnerf_server::http::{router, AppState, ServiceOptions};
use scnerf_server::pipeline::band::{self, BandFill};
use scnerf_server::pipeline::chunks::{self, ChunkPolicy, RawView};
use scnerf_server::pipeline::scene::Timings;
use scnerf_server::pipeline::volume::SlabPolicy;
use scnerf_server::pipeline::{assemble, rays, Pipeline};
use scnerf_server::request::Sampling;
use scnerf_server::request::{ImageMode, Limits, RenderRequest, ValidRequest};
use scnerf_server::testing::{ort_pipeline, ready_state};
use tower::ServiceExt;

/// tests/fixtures/parity, or SCNERF_PARITY_FIXTURES (to check a freshly generated set).
fn fixtures_dir() -> PathBuf {
    std::env::var_os("SCNERF_PARITY_FIXTURES")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("fixtures/parity"))
}

/// One ONNX Runtime pipeline for all tests of this binary (the runtime environment is
/// process-wide).
fn pipeline() -> Pipeline {
    static PIPELINE: OnceLock<Pipeline> = OnceLock::new();
    PIPELINE
        .get_or_init(|| {
            let dir = fixtures_dir().join("bundle");
            assert!(
                dir.is_dir(),
                "parity fixtures missing: {} (they are committed; run `scnerf-export fixtures`)",
                dir.display()
            );
            // The PyTorch reference renders the network's colour everywhere; the band's own
            // fixture is `band.json` (`band_fill_matches_python`).
            ort_pipeline(&dir, Limits::default(), 16).with_band(BandFill::Network)
        })
        .clone()
}

/// A place on the inference executor for one test's graph runs (no work declared: admission
/// by estimated finish time is not what these tests check).
fn admit(p: &Pipeline) -> scnerf_server::backend::Ticket {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(600);
    p.admit(deadline, scnerf_server::backend::Work::default(), 0).unwrap()
}

/// The real router's state over the ONNX Runtime pipeline, ready at once.
fn ready(p: Pipeline) -> AppState {
    ready_state(p, ServiceOptions { request_timeout: std::time::Duration::from_secs(600), ..Default::default() })
}

fn cases() -> Vec<PathBuf> {
    let dir = fixtures_dir().join("cases");
    let mut cases: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("parity fixtures missing: {}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .filter(|p| p.join("request.json").is_file())
        .collect();
    cases.sort();
    assert!(!cases.is_empty(), "no parity cases under {}", dir.display());
    cases
}

fn read_f32(path: &Path) -> Vec<f32> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
}

struct Expected {
    json: serde_json::Value,
    dir: PathBuf,
}

impl Expected {
    fn load(case: &Path) -> Expected {
        let text = std::fs::read_to_string(case.join("expected.json")).unwrap();
        Expected { json: serde_json::from_str(&text).unwrap(), dir: case.to_path_buf() }
    }

    fn tensor(&self, name: &str) -> (Vec<usize>, Vec<f32>) {
        let file = self.json["files"][name].as_str().unwrap_or_else(|| panic!("expected.json: no files.{name}"));
        let data = read_f32(&self.dir.join(file));
        let shape: Vec<usize> = self.json["shapes"][name]
            .as_array()
            .map(|a| a.iter().map(|d| d.as_u64().unwrap() as usize).collect())
            .unwrap_or_else(|| vec![data.len()]);
        assert_eq!(shape.iter().product::<usize>(), data.len(), "{name}: file size does not match its shape");
        (shape, data)
    }

    fn tolerance(&self, key: &str, default: f64) -> f64 {
        self.json["tolerances"][key].as_f64().unwrap_or(default)
    }
}

fn request(case: &Path) -> ValidRequest {
    let json = std::fs::read(case.join("request.json")).unwrap();
    let mut req = RenderRequest::from_json(&json, ImageMode::Parts, &Limits::default()).unwrap();
    for (i, s) in req.scene.sources.iter_mut().enumerate() {
        s.image = Some(std::fs::read(case.join(format!("source_{i}.png"))).unwrap().into());
    }
    req.validate(pipeline().config(), &Limits::default()).unwrap()
}

/// The largest `error` between the values of two equally long tensors of any shape, paired in
/// row-major order.
fn max_error<'a>(
    a: impl IntoIterator<Item = &'a f32, IntoIter: ExactSizeIterator>,
    b: impl IntoIterator<Item = &'a f32, IntoIter: ExactSizeIterator>,
    error: impl Fn(f32, f32) -> f64,
) -> f64 {
    error_sparing(a, b, 1, 0, error)
}

fn max_abs<'a>(
    a: impl IntoIterator<Item = &'a f32, IntoIter: ExactSizeIterator>,
    b: impl IntoIterator<Item = &'a f32, IntoIter: ExactSizeIterator>,
) -> f64 {
    max_error(a, b, abs_error)
}

fn abs_error(x: f32, y: f32) -> f64 {
    f64::from((x - y).abs())
}

/// |x - y| / max(|y|, 1e-3): relative to the magnitude of the reference.
fn rel_error(x: f32, y: f32) -> f64 {
    f64::from((x - y).abs()) / f64::from(y.abs()).max(1e-3)
}

/// The largest [`rel_error`].
fn max_rel<'a>(
    a: impl IntoIterator<Item = &'a f32, IntoIter: ExactSizeIterator>,
    b: impl IntoIterator<Item = &'a f32, IntoIter: ExactSizeIterator>,
) -> f64 {
    max_error(a, b, rel_error)
}

/// The largest per-pixel `error` (over a pixel's `channels` values) left once the `spared` worst
/// pixels are set aside.
fn error_sparing<'a>(
    a: impl IntoIterator<Item = &'a f32, IntoIter: ExactSizeIterator>,
    b: impl IntoIterator<Item = &'a f32, IntoIter: ExactSizeIterator>,
    channels: usize,
    spared: usize,
    error: impl Fn(f32, f32) -> f64,
) -> f64 {
    let (a, b) = (a.into_iter(), b.into_iter());
    assert_eq!(a.len(), b.len());
    let values: Vec<f64> = a.zip(b).map(|(x, y)| error(*x, *y)).collect();
    let mut pixels: Vec<f64> = values.chunks(channels).map(|c| c.iter().copied().fold(0.0, f64::max)).collect();
    pixels.sort_by(|x, y| y.total_cmp(x));
    pixels.get(spared).copied().unwrap_or(0.0)
}

/// Pixels of a guided view that may take other samples in ONNX Runtime than in PyTorch: where a
/// pixel's neighbours weigh two samples alike to within rounding, the two runtimes may rank them
/// apart. One in a thousand (rounded up); every other pixel is held to the tolerance.
fn guided_spared(pixels: usize) -> usize {
    pixels.div_ceil(1000)
}

fn check(case: &str, stage: &str, err: f64, tol: f64) {
    eprintln!("{case}: {stage} max error {err:.3e} (tolerance {tol:.0e})");
    assert!(err <= tol, "{case}: {stage} error {err:.3e} exceeds {tol:.0e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pipeline_matches_pytorch_stage_by_stage() {
    let p = pipeline();
    for case in cases() {
        let name = case.file_name().unwrap().to_string_lossy().to_string();
        let expected = Expected::load(&case);
        let req = request(&case);
        let mut timings = Timings::default();
        let ticket = admit(&p);
        let images = p.decode_sources(&req.scene).await.unwrap();
        let (near, far) = (req.scene.near, req.scene.far);
        let scene =
            p.build_scene(&ticket, &req.scene.cameras(), images.into_shared(), near, far, &mut timings).await.unwrap();

        let (shape, features) = expected.tensor("features");
        assert_eq!(scene.features.shape(), shape, "{name}: features shape");
        check(&name, "features", max_abs(&scene.features, &features), expected.tolerance("features_max_abs", 1e-4));
        let (shape, volume) = expected.tensor("volume");
        assert_eq!(scene.volume.shape(), shape, "{name}: volume shape");
        check(&name, "volume", max_abs(&scene.volume, &volume), expected.tolerance("volume_max_abs", 1e-4));

        let view = p
            .render_view(&ticket, &scene, &req.view.target, req.scene.background, Sampling::Full, None, &mut timings)
            .await
            .unwrap();
        assert_eq!(
            (u64::from(view.width()), u64::from(view.height())),
            (expected.json["width"].as_u64().unwrap(), expected.json["height"].as_u64().unwrap())
        );
        check(&name, "rgb", max_abs(&view.rgb, &expected.tensor("rgb").1), expected.tolerance("rgb_max_abs", 1e-3));
        check(
            &name,
            "depth (relative)",
            max_rel(&view.depth, &expected.tensor("depth").1),
            expected.tolerance("depth_max_rel", 1e-3),
        );
        check(
            &name,
            "opacity",
            max_abs(&view.opacity, &expected.tensor("opacity").1),
            expected.tolerance("opacity_max_abs", 1e-3),
        );
        eprintln!("{name}: timings {:?}", timings.millis());
    }
}

/// Guided sampling through the server's pipeline and ONNX Runtime against the PyTorch reference
/// (exporter runtime/guided.py): the same samples per pixel, the same pixels (but for near-ties,
/// [`guided_spared`]).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn guided_sampling_matches_pytorch() {
    let p = pipeline();
    for case in cases() {
        let name = case.file_name().unwrap().to_string_lossy().to_string();
        let expected = Expected::load(&case);
        let req = request(&case);
        let mut timings = Timings::default();
        let ticket = admit(&p);
        let scene = p.prepare_scene(&ticket, &req.scene, &mut timings).await.unwrap();
        let view = p
            .render_view(&ticket, &scene, &req.view.target, req.scene.background, Sampling::Guided, None, &mut timings)
            .await
            .unwrap();
        let samples = expected.json["guided_samples_per_ray"].as_f64().unwrap();
        assert_eq!(view.sampling.samples_per_ray, samples, "{name}: network samples per pixel");
        assert!(samples < p.config().samples as f64, "{name}: guided ran {samples} samples per pixel");
        let spared = guided_spared(view.depth.len());
        let rgb = error_sparing(&view.rgb, &expected.tensor("rgb_guided").1, 3, spared, abs_error);
        check(&name, "guided rgb", rgb, expected.tolerance("rgb_max_abs", 1e-3));
        let depth = error_sparing(&view.depth, &expected.tensor("depth_guided").1, 1, spared, rel_error);
        check(&name, "guided depth (relative)", depth, expected.tolerance("depth_max_rel", 1e-3));
        let opacity = error_sparing(&view.opacity, &expected.tensor("opacity_guided").1, 1, spared, abs_error);
        check(&name, "guided opacity", opacity, expected.tolerance("opacity_max_abs", 1e-3));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn output_does_not_depend_on_chunk_size() {
    let p = pipeline();
    let case = &cases()[0];
    let req = request(case);
    let mut timings = Timings::default();
    let ticket = admit(&p);
    let scene = p.prepare_scene(&ticket, &req.scene, &mut timings).await.unwrap();
    let (target, background) = (&req.view.target, req.scene.background);
    let small =
        p.render_view(&ticket, &scene, target, background, Sampling::Full, Some(37), &mut timings).await.unwrap();
    let large =
        p.render_view(&ticket, &scene, target, background, Sampling::Full, Some(5000), &mut timings).await.unwrap();
    let err = max_abs(&small.rgb, &large.rgb)
        .max(max_abs(&small.depth, &large.depth))
        .max(max_abs(&small.opacity, &large.opacity));
    eprintln!("chunk 37 vs 5000: max abs difference {err:.3e}");
    assert!(err <= 1e-6, "output depends on the chunk size: max difference {err:.3e}");
}

/// The fixture bundle declaring `depth_norm: image_minmax`, over the same executor and graphs:
/// the setting only changes what the renderer's `depth_range` input is fed.
fn image_minmax_pipeline() -> Pipeline {
    let mut bundle = Bundle::load(&fixtures_dir().join("bundle")).unwrap_or_else(|e| panic!("{e}"));
    bundle.config.depth_norm = DepthNorm::ImageMinmax;
    Pipeline::new(
        pipeline().executor().clone(),
        bundle,
        ChunkPolicy::default(),
        SlabPolicy::default(),
        Limits::default(),
    )
    .with_band(BandFill::Network)
}

/// The two-pass `image_minmax` render through the real graphs. The committed fixtures hold no
/// image_minmax case (the exporter writes near_far ones), so this checks the rule rather than
/// PyTorch's numbers: the view equals a renderer pass fed the [min, max] of the one-pass depth
/// image (which does not depend on the range), and does not depend on the chunk size.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn image_minmax_feeds_the_depth_images_range_to_a_second_pass() {
    let (near_far, minmax) = (pipeline(), image_minmax_pipeline());
    let req = request(&cases()[0]);
    let (target, background) = (&req.view.target, req.scene.background);
    let mut timings = Timings::default();
    let ticket = admit(&near_far);
    let scene = near_far.prepare_scene(&ticket, &req.scene, &mut timings).await.unwrap();
    let one_pass =
        near_far.render_view(&ticket, &scene, target, background, Sampling::Full, None, &mut timings).await.unwrap();
    let small =
        minmax.render_view(&ticket, &scene, target, background, Sampling::Full, Some(37), &mut timings).await.unwrap();
    let large = minmax
        .render_view(&ticket, &scene, target, background, Sampling::Full, Some(5000), &mut timings)
        .await
        .unwrap();

    let finite = one_pass.depth.iter().copied().filter(|d| d.is_finite());
    let range = [finite.clone().fold(f32::INFINITY, f32::min), finite.fold(f32::NEG_INFINITY, f32::max)];
    let inputs = &Bundle::load(&fixtures_dir().join("bundle")).unwrap().graph(GraphKind::Renderer).inputs.clone();
    let raw = chunks::render_rays(&ticket, &scene, inputs, &rays::generate(target), range, 512, true).await.unwrap();
    let expected_rgb = assemble::composite(&raw, background);

    check("image_minmax", "rgb against a pass fed the depth range", max_abs(&large.rgb, &expected_rgb), 1e-6);
    check("image_minmax", "depth against one pass", max_abs(&large.depth, &one_pass.depth), 1e-6);
    let chunking = max_abs(&small.rgb, &large.rgb).max(max_abs(&small.depth, &large.depth));
    check("image_minmax", "chunk 37 against 5000", chunking.max(max_abs(&small.opacity, &large.opacity)), 1e-6);
    let fed = max_abs(&large.rgb, &one_pass.rgb);
    eprintln!("image_minmax: rgb differs from near_far by up to {fed:.3e} (range {range:?})");
    assert!(fed > 1e-6, "the depth range made no difference: this case cannot tell the two rules apart");
}

/// The same cases through the real HTTP router: multipart in, JSON out (PNG rgb, float32 depth).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn http_multipart_render_matches_pytorch() {
    let p = pipeline();
    let app = router(ready(p));
    for case in cases() {
        let name = case.file_name().unwrap().to_string_lossy().to_string();
        let expected = Expected::load(&case);
        let mut files = Case::load(&case).unwrap();
        for (sampling, suffix) in [("full", ""), ("guided", "_guided")] {
            files.request["sampling"] = serde_json::json!(sampling);
            let (ctype, body) = files.multipart(&files.request);
            let req = Request::post("/v1/render")
                .header("content-type", ctype)
                .header("accept", "application/json")
                .body(Body::from(body))
                .unwrap();
            let resp = app.clone().oneshot(req).await.unwrap();
            let status = resp.status();
            let bytes = resp.into_body().collect().await.unwrap().to_bytes();
            assert_eq!(status, 200, "{name}: {}", String::from_utf8_lossy(&bytes));
            let json: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
            assert_eq!(json["sampling"], sampling, "{name}");
            let b64 =
                |v: &serde_json::Value| base64::engine::general_purpose::STANDARD.decode(v.as_str().unwrap()).unwrap();
            let png = image::load_from_memory(&b64(&json["rgb"]["data"])).unwrap().into_rgb8();
            let rgb: Vec<f32> = png.as_raw().iter().map(|&b| f32::from(b) / 255.0).collect();
            let want = |output: &str| expected.tensor(&format!("{output}{suffix}")).1;
            let stage = |output: &str| format!("http {sampling} {output}");
            let depth: Vec<f32> = b64(&json["depth"]["data"])
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            let spared = if sampling == "guided" { guided_spared(depth.len()) } else { 0 };
            // Quantisation to 8 bits adds at most half a level.
            let rgb_error = error_sparing(&rgb, &want("rgb"), 3, spared, abs_error);
            check(&name, &stage("rgb (8-bit)"), rgb_error, 0.5 / 255.0 + 1e-3);
            let tolerance = expected.tolerance("depth_max_rel", 1e-3);
            check(
                &name,
                &stage("depth (relative)"),
                error_sparing(&depth, &want("depth"), 1, spared, rel_error),
                tolerance,
            );
        }
    }
}

/// A view of a cached scene (`POST /v1/scenes` then `POST /v1/scenes/{id}/render`) is
/// bit-identical to the one-shot `POST /v1/render` of the same request, through the real graphs.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cached_scene_render_is_bit_identical_to_one_shot() {
    let app = router(ready(pipeline()));
    let case = Case::load(&cases()[0]).unwrap();
    let post = |path: &str, ctype: &str, body: Vec<u8>| {
        Request::post(path)
            .header("content-type", ctype)
            .header("accept", "application/json")
            .body(Body::from(body))
            .unwrap()
    };
    let call = |req: Request<Body>| {
        let app = app.clone();
        async move {
            let resp = app.oneshot(req).await.unwrap();
            let status = resp.status().as_u16();
            let bytes = resp.into_body().collect().await.unwrap().to_bytes();
            assert!(status < 300, "{status}: {}", String::from_utf8_lossy(&bytes));
            serde_json::from_slice::<serde_json::Value>(&bytes).unwrap()
        }
    };

    let (ctype, body) = case.multipart(&case.request);
    let one_shot = call(post("/v1/render", &ctype, body)).await;

    let (scene, view) = split_request(&case.request);
    let (ctype, body) = case.multipart(&scene);
    let created = call(post("/v1/scenes", &ctype, body)).await;
    let id = created["scene_id"].as_str().unwrap();
    let path = format!("/v1/scenes/{id}/render");
    let cached = call(post(&path, "application/json", serde_json::to_vec(&view).unwrap())).await;

    for key in ["width", "height", "model_id", "rgb", "depth", "opacity"] {
        assert!(!one_shot[key].is_null(), "{key} missing");
        assert_eq!(cached[key], one_shot[key], "{key} differs between the cached and the one-shot render");
    }
    eprintln!("one-shot timings {}; cached timings {}", one_shot["timings_ms"], cached["timings_ms"]);
}

/// A capture scene renders exactly what `/v1/render` renders from the same triple in the same
/// order, whether the server chose the triple or the request pinned it: the parity case's three
/// sources among two far-away extra views (indices 1, 2, 4 of five), through the real graphs.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn capture_scene_render_is_bit_identical_to_one_shot_of_its_triple() {
    let app = router(ready(pipeline()));
    let case = Case::load(&cases()[0]).unwrap();
    let call = |path: String, ctype: String, body: Vec<u8>| {
        let app = app.clone();
        async move {
            let req = Request::post(path)
                .header("content-type", ctype)
                .header("accept", "application/json")
                .body(Body::from(body))
                .unwrap();
            let resp = app.oneshot(req).await.unwrap();
            let status = resp.status().as_u16();
            let bytes = resp.into_body().collect().await.unwrap().to_bytes();
            assert!(status < 300, "{status}: {}", String::from_utf8_lossy(&bytes));
            serde_json::from_slice::<serde_json::Value>(&bytes).unwrap()
        }
    };
    let (scene, view) = split_request(&case.request);
    // Views: [extra, source 0, source 1, extra, source 2]; an extra is source 0's camera moved
    // 20 units back along its axis, far from the target.
    let mut extra = scene["sources"][0].clone();
    extra["camera"]["pose"]["matrix"][2][3] = serde_json::json!(23.0);
    let order = [None, Some(0), Some(1), None, Some(2)];
    let mut capture = scene.clone();
    capture["sources"] = order.iter().map(|o| o.map_or(extra.clone(), |i| scene["sources"][i].clone())).collect();
    let images: Vec<&[u8]> = order.iter().map(|o| case.images[o.unwrap_or(0)].as_slice()).collect();
    let json = serde_json::to_vec(&capture).unwrap();
    let names: Vec<String> = (0..5).map(|i| format!("source_{i}")).collect();
    let mut parts: Vec<(&str, Option<&str>, &str, &[u8])> = vec![("request", None, "application/json", &json)];
    parts.extend(names.iter().zip(&images).map(|(n, img)| (n.as_str(), Some("view.png"), "image/png", *img)));
    let (ctype, body) = scnerf_e2e::multipart(&parts);
    let created = call("/v1/scenes".into(), ctype, body).await;
    let path = format!("/v1/scenes/{}/render", created["scene_id"].as_str().unwrap());

    let mut pinned = view.clone();
    pinned["sources"] = serde_json::json!([4, 1, 2]);
    for body in [view, pinned] {
        let rendered = call(path.clone(), "application/json".into(), serde_json::to_vec(&body).unwrap()).await;
        let chosen: Vec<usize> =
            rendered["sources"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap() as usize).collect();
        let triple: Vec<usize> = chosen.iter().map(|&i| order[i].expect("one of the case's sources")).collect();
        let mut request = case.request.clone();
        request["sources"] = triple.iter().map(|&i| case.request["sources"][i].clone()).collect();
        let reordered =
            Case { request: request.clone(), images: triple.iter().map(|&i| case.images[i].clone()).collect() };
        let (ctype, body) = reordered.multipart(&request);
        let one_shot = call("/v1/render".into(), ctype, body).await;
        for key in ["width", "height", "model_id", "rgb", "depth", "opacity"] {
            assert!(!one_shot[key].is_null(), "{key} missing");
            assert_eq!(rendered[key], one_shot[key], "{key} differs from /v1/render of sources {triple:?}");
        }
        eprintln!("capture scene rendered from views {chosen:?} = case sources {triple:?}");
    }
}

/// A (possibly nested) JSON list of numbers as an array of its shape.
fn json_array(value: &serde_json::Value) -> ndarray::ArrayD<f32> {
    fn walk(value: &serde_json::Value, depth: usize, shape: &mut Vec<usize>, flat: &mut Vec<f32>) {
        match value.as_array() {
            Some(items) => {
                if shape.len() == depth {
                    shape.push(items.len());
                }
                items.iter().for_each(|item| walk(item, depth + 1, shape, flat));
            }
            None => flat.push(value.as_f64().expect("a number") as f32),
        }
    }
    let (mut shape, mut flat) = (Vec::new(), Vec::new());
    walk(value, 0, &mut shape, &mut flat);
    ndarray::ArrayD::from_shape_vec(shape, flat).expect("a rectangular list")
}

/// The band's recolouring (pipeline::band) against its Python twin (runtime/band.py) on
/// `band.json`: the rig's target rays from the server's own camera conversion, random depths
/// and opacities, three sources padded below their images.
#[test]
fn band_fill_matches_python() {
    let case: serde_json::Value =
        serde_json::from_slice(&std::fs::read(fixtures_dir().join("band.json")).expect("band.json is committed"))
            .unwrap();
    let wire: scnerf_capture::wire::WireCamera = serde_json::from_value(case["target"].clone()).unwrap();
    let target = scnerf_server::request::cameras::CameraSpec::from_wire(&wire, "target")
        .unwrap()
        .canonicalize("target")
        .unwrap();
    let images = json_array(&case["images"]).into_dimensionality::<ndarray::Ix4>().unwrap();
    let intrinsics = json_array(&case["intrinsics"]).into_dimensionality::<ndarray::Ix3>().unwrap();
    let extrinsics = json_array(&case["extrinsics"]).into_dimensionality::<ndarray::Ix3>().unwrap();
    let sizes: Vec<(usize, usize)> = serde_json::from_value(case["source_sizes"].clone()).unwrap();
    let sources = band::Sources {
        images: images.view(),
        sizes: &sizes,
        intrinsics: intrinsics.view(),
        extrinsics: extrinsics.view(),
    };
    let raw = &case["raw"];
    let mut view = RawView {
        rgb: json_array(&raw["rgb"]).into_dimensionality().unwrap(),
        depth: json_array(&raw["depth"]).into_dimensionality().unwrap(),
        opacity: json_array(&raw["opacity"]).into_dimensionality().unwrap(),
    };
    let filled = band::fill_from_sources(&mut view, &rays::generate(&target), &sources, BandRule::WhenDark);
    assert_eq!(filled as u64, case["band_pixels"].as_u64().unwrap(), "pixels in the band");
    assert!(filled > 0 && filled < view.depth.len(), "the case has pixels in and out of the band");
    let expected = json_array(&case["expected_rgb"]);
    check("band", "rgb", max_abs(view.rgb.iter(), expected.iter()), 1e-6);
}
