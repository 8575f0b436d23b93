//! The pipeline's own logic over the fake graph runner (`crate::testing`): the work and memory a
//! request is admitted with and what a refusal names, the choice of sampling, which views are
//! built when, the dispatch of a view to the full or the guided renderers, the depth-range
//! passes, and the assembly of the image.
//!
//! The fake bundle has three views, 16 samples, an image multiple of 32 and 4 x 8 float heads
//! on its one rectifier; its sources here are 8 x 6 (padded to 32 x 32).

use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use axum::http::StatusCode;
use bytes::Bytes;
use ndarray::{arr1, s, Array2};

use super::*;
use crate::backend::{ExecutorOptions, MemoryBudget, Work};
use crate::bundle::GuidedPolicy;
use crate::request::{OutputSet, ValidSource, ValidTarget};
use crate::testing::{self, FakeRunner};

type Calls = Arc<[AtomicUsize; GraphKind::ALL.len()]>;

const NEAR: f64 = 2.0;
const FAR: f64 = 6.0;

/// A pipeline over the fake runner with `memory` as its budget; renderer chunks of 100 rays.
fn pipeline_with(bundle: Bundle, memory: MemoryBudget) -> (Pipeline, Calls) {
    let runner = FakeRunner::new(&bundle);
    let calls = runner.calls.clone();
    let executor = ExecutorOptions { memory, ..ExecutorOptions::with_capacity(4) };
    let backend = BackendHandle::spawn(Box::new(runner), executor).expect("spawn the executor");
    let chunking = ChunkPolicy { max_rays: 100, memory_budget_bytes: usize::MAX };
    (Pipeline::new(backend, bundle, chunking, SlabPolicy::default(), Limits::default()), calls)
}

fn pipeline(bundle: Bundle) -> (Pipeline, Calls) {
    pipeline_with(bundle, MemoryBudget::UNLIMITED)
}

fn near_far() -> Bundle {
    testing::bundle("scnerf", "near_far")
}

fn runs(calls: &Calls, graph: GraphKind) -> usize {
    calls[graph.index()].load(Ordering::SeqCst)
}

fn units(work: Work, graph: GraphKind) -> f64 {
    work.0[graph.index()]
}

/// `testing::camera` (looking along +z) at another size.
fn camera(width: u32, height: u32) -> CanonicalCamera {
    CanonicalCamera { width, height, ..testing::camera() }
}

fn deadline() -> Due {
    (Instant::now() + Duration::from_secs(60)).into()
}

fn ticket(p: &Pipeline) -> Ticket {
    p.admit(deadline(), Work::default(), 0).expect("admitted")
}

/// `n` padded 32 x 32 sources, view i filled with i / 10 to tell them apart.
fn images(n: usize) -> ArcArray4<f32> {
    Array4::from_shape_fn((n, 3, 32, 32), |(i, ..)| i as f32 / 10.0).into_shared()
}

async fn scene(p: &Pipeline, ticket: &Ticket) -> Scene {
    let cameras = vec![camera(8, 6); 3];
    p.build_scene(ticket, &cameras, images(3), NEAR, FAR, &mut Timings::default()).await.expect("scene")
}

/// A validated scene of `n` 8 x 6 PNG sources.
fn valid_scene(n: usize) -> ValidScene {
    let png = Bytes::from(testing::png(8, 6, [200, 100, 50, 255]));
    let source =
        |i| ValidSource { camera: camera(8, 6), image: png.clone(), image_field: format!("sources[{i}].image") };
    ValidScene { sources: (0..n).map(source).collect(), near: NEAR, far: FAR, background: [1.0; 3] }
}

fn valid_request(target: CanonicalCamera) -> ValidRequest {
    let view = ValidTarget { target, outputs: OutputSet::RGB, sources: None, sampling: None };
    ValidRequest { scene: valid_scene(3), view }
}

fn stages(timings: &Timings) -> Vec<&'static str> {
    timings.0.iter().map(|(stage, _)| *stage).collect()
}

/// The 422 an error must be: its field and message.
fn invalid(e: ApiError) -> (String, String) {
    match e {
        ApiError::Invalid { field, message } => (field, message),
        other => panic!("expected a 422, got {other:?}"),
    }
}

/// The spread of a view's depth image.
fn depth_span(view: &View) -> f32 {
    let (lo, hi) = view.depth.iter().fold((f32::MAX, f32::MIN), |(lo, hi), &d| (lo.min(d), hi.max(d)));
    hi - lo
}

#[test]
fn timings_keep_the_stages_in_order_in_milliseconds() {
    let timings = Timings(vec![("decode", Duration::from_micros(1500)), ("encoder", Duration::from_secs(2))]);
    assert_eq!(timings.millis(), [("decode", 1.5), ("encoder", 2000.0)]);
}

/// Every target pixel is a renderer ray, once per pass: twice where `image_minmax` feeds the
/// renderer the view's own depth range, once where the renderer takes no range (mvsnerf).
#[test]
fn a_full_view_is_its_pixels_once_per_renderer_pass() {
    for (variant, norm, passes) in
        [("scnerf", "near_far", 1.0), ("scnerf", "image_minmax", 2.0), ("mvsnerf", "image_minmax", 1.0)]
    {
        let (p, _) = pipeline(testing::bundle(variant, norm));
        let work = p.view_work(&camera(8, 6), Sampling::Full);
        assert_eq!(work, Work::of(GraphKind::Renderer, passes * 48.0), "{variant} {norm}");
    }
}

/// Guided sampling plans its guide rays (the 2 x 2 grid of step 4 over 8 x 6) and fewer fine
/// samples than the full renderer's 16 a pixel, and no full renderer; asked of the same bundle,
/// full sampling plans the full renderer.
#[test]
fn a_guided_view_is_its_guide_rays_and_at_most_its_fine_samples() {
    let (p, _) = pipeline(testing::guided_bundle("scnerf"));
    let work = p.view_work(&camera(8, 6), Sampling::Guided);
    assert_eq!(units(work, GraphKind::RendererGuide), 4.0);
    assert_eq!(units(work, GraphKind::Renderer), 0.0);
    let fine = units(work, GraphKind::RendererFine);
    assert!(fine > 0.0 && fine < 16.0 * 48.0, "{fine}");
    assert_eq!(p.view_work(&camera(8, 6), Sampling::Full), Work::of(GraphKind::Renderer, 48.0));
}

/// A scene's work is its padded source pixels through the encoder and the volume graph: each
/// side rounded up to the image multiple of 32.
#[test]
fn a_scene_is_its_padded_source_pixels_through_encoder_and_volume() {
    let (p, _) = pipeline(near_far());
    let pixels = 3.0 * 32.0 * 32.0;
    let expected = Work::of(GraphKind::Encoder, pixels).plus(Work::of(GraphKind::Volume, pixels));
    assert_eq!(p.scene_work(&vec![camera(8, 6); 3]), expected);
    assert_eq!(units(p.scene_work(&vec![camera(40, 33); 3]), GraphKind::Encoder), 3.0 * 64.0 * 64.0);
    assert_eq!(p.scene_work(&[]), Work::default());
}

/// A cached scene's view costs the renderer alone, a scene upload no renderer, a render both.
#[test]
fn a_request_is_planned_as_the_scene_it_builds_plus_the_view_it_renders() {
    let (p, _) = pipeline(near_far());
    let (sources, target) = (vec![camera(8, 6); 3], camera(8, 6));
    let pixels = 3.0 * 32.0 * 32.0;
    let scene = Work::of(GraphKind::Encoder, pixels).plus(Work::of(GraphKind::Volume, pixels));
    let view = Work::of(GraphKind::Renderer, 48.0);
    assert_eq!(p.request_work(None, Some((&target, Sampling::Full))), view);
    assert_eq!(p.request_work(Some(&sources), None), scene);
    assert_eq!(p.request_work(Some(&sources), Some((&target, Sampling::Full))), scene.plus(view));
}

/// Beside the full renderer's memory, guided sampling holds the guidance of the spacing-2 grid
/// (4 x 3 pixels of 16 f32 weights: 768 bytes) and the guide rays' heads (2 x 2 rays of one
/// rectifier's 4 x 8 f32: 512 bytes).
#[test]
fn guided_sampling_holds_its_guidance_and_the_guide_rays_heads() {
    let target = camera(8, 6);
    let (guided, _) = pipeline(testing::guided_bundle("scnerf"));
    assert_eq!(guided.sampling_bytes(&target, Sampling::Guided), 768 + 512);
    assert_eq!(guided.sampling_bytes(&target, Sampling::Full), 0);
    let (plain, _) = pipeline(near_far());
    assert_eq!(plain.sampling_bytes(&target, Sampling::Guided), 0);
}

/// The estimate follows what a request does: building a volume adds to decoding the sources, a
/// view adds to its scene, a fresh scene's view costs more than a cached one's, and guided
/// sampling adds its 1280 bytes (above) to the view.
#[test]
fn the_memory_estimate_follows_what_the_request_runs() {
    let (p, _) = pipeline(testing::guided_bundle("scnerf"));
    let (sources, target) = (vec![camera(8, 6); 3], camera(8, 6));
    let (sources, full, guided) =
        (Some(&sources[..]), Some((&target, Sampling::Full)), Some((&target, Sampling::Guided)));
    let render = p.memory_estimate(sources, true, true, full);
    let scene = p.memory_estimate(sources, true, true, None);
    assert!(p.memory_estimate(sources, true, false, None) < scene);
    assert!(scene < render);
    assert!(p.memory_estimate(None, false, false, full) < render);
    assert_eq!(p.memory_estimate(sources, true, true, guided) - render, 1280);
}

/// Guided sampling only where the bundle has its graphs: there it is the default and either
/// mode can be asked for; elsewhere full is the only mode, `--sampling guided` falls back to it,
/// and a request for guided is a 422 naming `sampling`.
#[test]
fn guided_sampling_is_offered_only_by_a_bundle_with_its_graphs() {
    let (guided, _) = pipeline(testing::guided_bundle("scnerf"));
    assert_eq!(guided.default_sampling(), Sampling::Guided);
    assert_eq!(guided.samplings(), [Sampling::Full, Sampling::Guided]);
    assert_eq!(guided.sampling_of(Some(Sampling::Full)).unwrap(), Sampling::Full);
    assert_eq!(guided.with_default_sampling(Sampling::Full).sampling_of(None).unwrap(), Sampling::Full);

    let (plain, _) = pipeline(near_far());
    let plain = plain.with_default_sampling(Sampling::Guided);
    assert_eq!(plain.sampling_of(None).unwrap(), Sampling::Full);
    assert_eq!(plain.samplings(), [Sampling::Full]);
    assert_eq!(invalid(plain.sampling_of(Some(Sampling::Guided)).unwrap_err()).0, "sampling");
    assert_eq!(plain.view_work(&camera(8, 6), Sampling::Guided), Work::of(GraphKind::Renderer, 48.0));
}

/// A request larger than the whole memory budget is told which of its sizes: its sources and
/// target (a render), its sources (a scene upload) or its target (a cached scene's view).
/// Other refusals pass through.
#[test]
fn a_refusal_for_memory_names_the_request_s_sizes() {
    let e = BackendError::TooLarge { needed_mib: 900, budget_mib: 512 };
    let (sources, target) = (vec![camera(8, 6); 3], camera(16, 12));
    let cases = [
        (Some(&sources[..]), Some(&target), "sources", "3 source views of 8x6 with a 16x12 target need "),
        (Some(&sources[..]), None, "sources", "3 source views of 8x6 need "),
        (None, Some(&target), "target.width", "a 16x12 target needs "),
    ];
    for (s, t, field, start) in cases {
        let (named, message) = invalid(refusal(e.clone(), s, t));
        assert_eq!(named, field);
        assert_eq!(message, format!("{start}{e}"));
    }
    assert_eq!(invalid(refusal(e.clone(), None, None)), invalid(e.into()));
    assert_eq!(
        refusal(BackendError::QueueFull, Some(&sources), Some(&target)).status(),
        StatusCode::SERVICE_UNAVAILABLE
    );
}

/// Over the budget, a render and a capture's upload (held as a lease) are refused before any
/// decoding or graph run, naming their sizes.
#[tokio::test]
async fn a_request_over_the_memory_budget_is_refused_before_any_work() {
    let (p, calls) = pipeline_with(near_far(), MemoryBudget { total: 1, reserved: 0 });
    let mut timings = Timings::default();
    let e = p.render(&valid_request(camera(8, 6)), deadline(), &mut timings).await.unwrap_err();
    assert!(invalid(e).1.starts_with("3 source views of 8x6 with a 8x6 target need "));
    let e = p.encode_scene(&valid_scene(4), deadline(), &mut timings).await.unwrap_err();
    assert!(invalid(e).1.starts_with("4 source views of 8x6 need "));
    assert!(timings.0.is_empty(), "{:?}", stages(&timings));
    assert!(GraphKind::ALL.iter().all(|&g| runs(&calls, g) == 0));
}

/// A render times its stages in the order they run, and its view has the target's size.
#[tokio::test]
async fn a_render_runs_and_times_every_stage_in_order() {
    let (p, _) = pipeline(near_far());
    let mut timings = Timings::default();
    let view = p.render(&valid_request(camera(12, 5)), deadline(), &mut timings).await.expect("view");
    assert_eq!(stages(&timings), ["decode", "encoder", "volume", "renderer", "band", "assemble"]);
    assert_eq!((view.width(), view.height(), view.rgb.dim()), (12, 5, (5, 12, 3)));
}

/// `--band network` keeps the network's colours: the band stage does not run.
#[tokio::test]
async fn the_networks_band_skips_the_band_stage() {
    let (p, _) = pipeline(near_far());
    let mut timings = Timings::default();
    p.with_band(super::band::BandFill::Network)
        .render(&valid_request(camera(12, 5)), deadline(), &mut timings)
        .await
        .expect("view");
    assert_eq!(stages(&timings), ["decode", "encoder", "volume", "renderer", "assemble"]);
}

/// A scene of the model's view count is built on upload; a larger one (a capture) is only
/// decoded, its triples built when renders pick them. Either way the scene cache's estimate,
/// made before decoding, is what the scene then holds.
#[tokio::test]
async fn a_scene_of_the_model_s_view_count_is_built_on_upload_a_capture_is_not() {
    let (p, calls) = pipeline(near_far());
    let (req, mut timings) = (valid_scene(3), Timings::default());
    let (views, scene) = p.encode_scene(&req, deadline(), &mut timings).await.expect("three views");
    let scene = scene.expect("built on upload");
    assert_eq!(stages(&timings), ["decode", "encoder", "volume"]);
    assert_eq!(p.scene_bytes(&req), scene.bytes() as u64);
    assert_eq!(views.images.dim(), (3, 3, 32, 32));

    let (req, mut timings) = (valid_scene(4), Timings::default());
    let (views, scene) = p.encode_scene(&req, deadline(), &mut timings).await.expect("four views");
    assert!(scene.is_none());
    assert_eq!(stages(&timings), ["decode"]);
    assert_eq!(p.scene_bytes(&req), views.bytes() as u64);
    assert_eq!((runs(&calls, GraphKind::Encoder), runs(&calls, GraphKind::Volume)), (1, 1));
}

/// A view of a capture is rendered from the views picked, in that order; the triple built for it
/// is handed back for the cache, and a cached triple runs the renderer alone.
#[tokio::test]
async fn a_capture_s_triple_is_built_once_then_rendered_from_the_cache() {
    let (p, calls) = pipeline(near_far());
    let views = Views { images: images(4), cameras: vec![camera(8, 6); 4], near: NEAR, far: FAR };
    let (picked, target) = ([2, 0, 3], camera(8, 6));
    let mut timings = Timings::default();
    let (view, built) =
        p.render_sources(&views, &picked, None, &target, None, [1.0; 3], deadline(), &mut timings).await.expect("view");
    let built = built.expect("a triple built here goes to the cache");
    let firsts: Vec<f32> = (0..3).map(|i| built.images[[i, 0, 0, 0]]).collect();
    assert_eq!(firsts, [0.2, 0.0, 0.3]);
    assert_eq!((view.width(), view.height()), (8, 6));

    let (_, again) = p
        .render_sources(&views, &picked, Some(built), &target, None, [1.0; 3], deadline(), &mut timings)
        .await
        .unwrap();
    assert!(again.is_none());
    assert_eq!((runs(&calls, GraphKind::Encoder), runs(&calls, GraphKind::Volume)), (1, 1));
    // 48 rays in one chunk of up to 100, one pass: one renderer run a view.
    assert_eq!(runs(&calls, GraphKind::Renderer), 2);
}

/// Guided sampling runs the guide and fine renderers and never the full one, full sampling the
/// reverse; each view says how it was sampled.
#[tokio::test]
async fn a_view_goes_to_the_renderers_of_its_sampling() {
    let (p, calls) = pipeline(testing::guided_bundle("scnerf"));
    let ticket = ticket(&p);
    let scene = scene(&p, &ticket).await;
    let target = camera(8, 6);
    let mut timings = Timings::default();
    let full = p.render_view(&ticket, &scene, &target, [1.0; 3], Sampling::Full, None, &mut timings).await.unwrap();
    assert_eq!(full.sampling, SamplingReport { mode: Sampling::Full, samples_per_ray: 16.0 });
    let renderers =
        || [GraphKind::Renderer, GraphKind::RendererGuide, GraphKind::RendererFine].map(|g| runs(&calls, g));
    assert_eq!(renderers(), [1, 0, 0]);

    let guided = p.render_view(&ticket, &scene, &target, [1.0; 3], Sampling::Guided, None, &mut timings).await.unwrap();
    assert_eq!(guided.sampling.mode, Sampling::Guided);
    assert!(guided.sampling.samples_per_ray < 16.0, "{:?}", guided.sampling);
    let [full_runs, guide_runs, fine_runs] = renderers();
    assert_eq!(full_runs, 1, "guided sampling ran the full renderer");
    assert!(guide_runs > 0 && fine_runs > 0);
    assert_eq!((guided.width(), guided.height()), (8, 6));
    assert_eq!(stages(&timings), ["renderer", "band", "assemble", "renderer", "band", "assemble"]);
}

/// A 9 x 7 view rendered by guided sampling under `policy`: its samples per pixel, and the guide
/// and fine renderers' runs.
async fn guided_work(policy: GuidedPolicy) -> (f64, [usize; 2]) {
    let (p, calls) = pipeline(testing::guided_bundle_with("scnerf", policy));
    let ticket = ticket(&p);
    let scene = scene(&p, &ticket).await;
    let (target, mut timings) = (camera(9, 7), Timings::default());
    let view = p.render_view(&ticket, &scene, &target, [1.0; 3], Sampling::Guided, Some(10), &mut timings).await;
    let renderers = [GraphKind::RendererGuide, GraphKind::RendererFine].map(|g| runs(&calls, g));
    (view.unwrap().sampling.samples_per_ray, renderers)
}

/// Pixels that disagree with their neighbours are rendered again at all samples, through the
/// fine renderer (the guide renderer runs level 0 alone): none with verification off, none when
/// none disagrees by more than the tolerance or the share allows none; some when every
/// disagreement counts (the fake renderers' pixels fold where a ray's direction crosses the axis,
/// so some pixel lies outside its neighbours' range).
#[tokio::test]
async fn pixels_that_disagree_are_rendered_again_at_all_samples() {
    let plain = testing::guided_bundle("scnerf").guided().cloned().expect("a guided policy");
    let verifying = |tolerance, share| GuidedPolicy {
        verify_tolerance: Some(tolerance),
        verify_share: Some(share),
        smooth_max_step: 0,
        ..plain.clone()
    };
    let unverified = guided_work(GuidedPolicy { smooth_max_step: 0, ..plain.clone() }).await;
    assert_eq!(guided_work(verifying(1e9, 1.0)).await, unverified);
    assert_eq!(guided_work(verifying(0.0, 0.0)).await, unverified);
    let (verified, [guide_runs, fine_runs]) = guided_work(verifying(0.0, 1.0)).await;
    assert!(verified > unverified.0, "{verified} vs {unverified:?}");
    assert_eq!(guide_runs, unverified.1[0], "pixels rendered again through the guide renderer");
    assert!(fine_runs > unverified.1[1], "{fine_runs} fine runs vs {unverified:?}");
    // Each pixel rendered again adds all 16 samples to the view's 63 pixels.
    let again = (verified - unverified.0) * 63.0 / 16.0;
    assert!((again - again.round()).abs() < 1e-9 && again >= 1.0, "{again}");
    // With `verify_samples`, the same pixels at 4 samples each.
    let (fewer, _) = guided_work(GuidedPolicy { verify_samples: Some(4), ..verifying(0.0, 1.0) }).await;
    assert!(((fewer - unverified.0) * 63.0 / 4.0 - again).abs() < 1e-9, "{fewer} vs {verified}");
}

/// Pixels whose neighbours' colours span more than `edge_span` run at `edge_samples`: more samples
/// when every neighbourhood with any spread counts as an edge, the same when none does.
#[tokio::test]
async fn pixels_on_an_edge_run_at_their_samples() {
    let plain = testing::guided_bundle("scnerf").guided().cloned().expect("a guided policy");
    let edges =
        |span| GuidedPolicy { edge_span: Some(span), edge_samples: Some(16), smooth_max_step: 0, ..plain.clone() };
    let (without, _) = guided_work(GuidedPolicy { smooth_max_step: 0, ..plain.clone() }).await;
    assert_eq!(guided_work(edges(1e9)).await.0, without);
    assert!(guided_work(edges(0.0)).await.0 > without);
}

/// A full view runs the renderer once per chunk of rays and pass: 48 rays in chunks of 10 are
/// five runs, ten where `image_minmax` renders the depth first.
#[tokio::test]
async fn a_full_view_runs_each_chunk_once_per_depth_range_pass() {
    for (norm, expected) in [("near_far", 5), ("image_minmax", 10)] {
        let (p, calls) = pipeline(testing::bundle("scnerf", norm));
        let ticket = ticket(&p);
        let scene = scene(&p, &ticket).await;
        let mut timings = Timings::default();
        p.render_view(&ticket, &scene, &camera(8, 6), [1.0; 3], Sampling::Full, Some(10), &mut timings).await.unwrap();
        assert_eq!(runs(&calls, GraphKind::Renderer), expected, "{norm}");
    }
}

/// `image_minmax`'s second pass is fed the depth range of the first. The fake renderer's depth
/// is `near + |x|·range` (x: a component of the ray's unit direction), so one pass over the
/// request's [2, 6] spans 4·(b − a) for |x| in [a, b], and a second pass, fed that span as its
/// range, spans 4·(b − a)²: the first span squared over 4.
#[tokio::test]
async fn the_second_pass_renders_with_the_first_pass_s_depth_range() {
    let mut spans = vec![];
    for norm in ["near_far", "image_minmax"] {
        let (p, _) = pipeline(testing::bundle("scnerf", norm));
        let ticket = ticket(&p);
        let scene = scene(&p, &ticket).await;
        let mut timings = Timings::default();
        let view =
            p.render_view(&ticket, &scene, &camera(8, 6), [1.0; 3], Sampling::Full, None, &mut timings).await.unwrap();
        spans.push(depth_span(&view));
    }
    let (one, two) = (spans[0], spans[1]);
    assert!(one > 0.1, "the fake's depth must vary over the view: {one}");
    assert!((two - one * one / (FAR - NEAR) as f32).abs() < 1e-5, "one pass spans {one}, two {two}");
}

#[test]
fn the_depth_range_ignores_rays_without_a_finite_depth() {
    assert_eq!(min_max(&arr1(&[3.0, f32::NAN, -1.0, f32::INFINITY, 2.5])), Some([-1.0, 3.0]));
    assert_eq!(min_max(&arr1(&[f32::NAN, f32::NEG_INFINITY])), None);
    assert_eq!(min_max(&Array1::zeros(0)), None);
}

/// Rays are ordered row by row (ray r·W + c is pixel (r, c)), and a ray's colour is composited
/// on the background by its opacity.
#[test]
fn a_view_is_assembled_row_by_row_on_its_background() {
    let (w, h) = (4, 3);
    let raw = RawView {
        rgb: Array2::from_shape_fn((w * h, 3), |(_, channel)| if channel == 0 { 0.5 } else { 0.0 }),
        depth: Array1::from_shape_fn(w * h, |i| i as f32),
        opacity: Array1::from_shape_fn(w * h, |i| if i % 2 == 0 { 1.0 } else { 0.5 }),
    };
    let report = SamplingReport { mode: Sampling::Full, samples_per_ray: 16.0 };
    let view = assemble_view(&camera(w as u32, h as u32), raw, [0.0, 0.0, 1.0], report);
    assert_eq!((view.width(), view.height()), (4, 3));
    for (r, c) in (0..h).flat_map(|r| (0..w).map(move |c| (r, c))) {
        let ray = r * w + c;
        assert_eq!(view.depth[[r, c]], ray as f32);
        // A half-transparent ray shows half of the blue background.
        let blue = if ray % 2 == 0 { 0.0 } else { 0.5 };
        assert_eq!(view.rgb.slice(s![r, c, ..]).to_vec(), [0.5, 0.0, blue], "pixel ({r}, {c})");
        assert_eq!(view.opacity[[r, c]], 1.0 - blue);
    }
}
