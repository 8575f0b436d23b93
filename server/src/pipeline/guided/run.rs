//! Rendering a view by guided sampling: the levels' graph runs, in order.

use std::ops::Range;

use ndarray::{s, Array2, Array3, Ix2, Ix3};

use super::grid::{first_level_pixels, Pixel};
use super::plan::{again_samples, disagreeing, plan_level, put_fine, Canvas, FineRays, Frame, Guidance};
use crate::backend::{BackendError, Tensor, Ticket};
use crate::bundle::{Bundle, GraphKind, GuidedPolicy};
use crate::camera::CanonicalCamera;
use crate::pipeline::chunks::{chunk_inputs, run_chunks, take_pixels, ChunkPolicy, RawView};
use crate::pipeline::rays::Rays;
use crate::pipeline::scene::{SamplingReport, Scene};
use crate::request::Sampling;

/// The rectifiers' heads of the guide rays, by graph name (`geometry_heads`, ...): (G, h·d_k, C).
type Heads = Vec<(String, Tensor)>;

/// Renders every pixel of `target` (its `rays`) by guided sampling: see the module doc.
#[allow(clippy::too_many_arguments)]
pub async fn render(
    ticket: &Ticket,
    bundle: &Bundle,
    policy: &GuidedPolicy,
    chunking: &ChunkPolicy,
    scene: &Scene,
    target: &CanonicalCamera,
    rays: &Rays,
    background: [f32; 3],
) -> Result<(RawView, SamplingReport), BackendError> {
    let (width, height) = (target.width as usize, target.height as usize);
    let samples = bundle.config.samples;
    let mut frame = Frame {
        canvas: Canvas::new(width, height),
        guidance: Guidance::new(width, height, samples),
        height,
        background,
    };
    let levels: Vec<(usize, usize)> = policy.levels().collect();
    let first = first_level_pixels(width, height, policy.step);
    let heads = run_guide(ticket, bundle, chunking, scene, rays, &first, &mut frame).await?;
    let mut network_samples = first.len() * samples;
    // The fine renderer's last run of the request may release its arena, where its session keeps
    // one (`Ticket::run_last`): the last level's pixels rendered again where the policy verifies
    // (none: its arena stays held), else the last level's last run.
    let verifies = policy.verify_tolerance.is_some();
    for (level, &(spacing, count)) in levels.iter().enumerate() {
        let runs;
        (frame, runs) = plan_level_blocking(policy.clone(), frame, spacing, count).await?;
        let last = level + 1 == levels.len();
        for (i, fine) in runs.iter().enumerate() {
            let last_run = last && !verifies && i + 1 == runs.len();
            network_samples +=
                run_fine(ticket, bundle, chunking, scene, rays, &heads, fine, &mut frame, spacing, last_run).await?;
        }
        let fine_pixels: Vec<Pixel> = runs.into_iter().flat_map(|fine| fine.pixels).collect();
        let again = again_samples(policy, &frame, spacing, disagreeing(policy, &frame, &fine_pixels, spacing));
        network_samples +=
            run_fine(ticket, bundle, chunking, scene, rays, &heads, &again, &mut frame, spacing, last).await?;
    }
    let Canvas { rgb, depth, opacity, .. } = frame.canvas;
    let samples_per_ray = network_samples as f64 / (width * height) as f64;
    Ok((RawView { rgb, depth, opacity }, SamplingReport { mode: Sampling::Guided, samples_per_ray }))
}

/// A level's fine rays through `renderer_fine.onnx`; returns the samples they ran.
#[allow(clippy::too_many_arguments)]
async fn run_fine(
    ticket: &Ticket,
    bundle: &Bundle,
    chunking: &ChunkPolicy,
    scene: &Scene,
    rays: &Rays,
    heads: &Heads,
    fine: &FineRays,
    frame: &mut Frame,
    spacing: usize,
    last: bool,
) -> Result<usize, BackendError> {
    let n = fine.pixels.len();
    if n == 0 {
        return Ok(0);
    }
    let inputs = &bundle.graph(GraphKind::RendererFine).inputs;
    let near_far = [scene.near as f32, scene.far as f32];
    let fine_rays = rays.select(&fine.pixels.iter().map(|&p| frame.canvas.index(p)).collect::<Vec<_>>());
    let k = fine.index.ncols();
    let extra = |name: &str, range: Range<usize>| -> Option<Tensor> {
        let rows = |a: &Array2<f32>| a.slice(s![range.clone(), ..]).to_owned().into_shared().into_dyn();
        match name {
            "sample_index" => Some(rows(&fine.index)),
            "sample_multiplicity" => Some(rows(&fine.multiplicity)),
            "head_index" => Some(fine.guide.slice(s![range.clone()]).to_owned().into_shared().into_dyn()),
            _ => heads.iter().find(|(n, _)| n == name).map(|(_, t)| t.clone()),
        }
    };
    let build = |range: Range<usize>| chunk_inputs(scene, inputs, &fine_rays, range, near_far, &extra);
    let chunk = chunking.fine_rays_per_chunk(k, bundle.config.samples);
    run_chunks(ticket, GraphKind::RendererFine, n, chunk, k as f64, last, build, |range, mut outputs| {
        let (rgb, depth, opacity) = take_pixels(&mut outputs, range.len())?;
        let weights = outputs.take::<Ix2>("sample_weights", &[Some(range.len()), Some(k)])?;
        put_fine(frame, fine, range, spacing, &(rgb, depth, opacity, weights));
        Ok(())
    })
    .await?;
    Ok(n * k)
}

/// Level 0 through the full network (`renderer_guide.onnx`) at all S samples: its outputs into
/// the canvas, its weights into the guidance; returns its rectifiers' heads, which every fine ray
/// reads.
async fn run_guide(
    ticket: &Ticket,
    bundle: &Bundle,
    chunking: &ChunkPolicy,
    scene: &Scene,
    all_rays: &Rays,
    pixels: &[Pixel],
    frame: &mut Frame,
) -> Result<Heads, BackendError> {
    let n = pixels.len();
    let spec = bundle.graph(GraphKind::RendererGuide);
    let rays = &all_rays.select(&pixels.iter().map(|&p| frame.canvas.index(p)).collect::<Vec<_>>());
    let samples = bundle.config.samples;
    let near_far = [scene.near as f32, scene.far as f32];
    let mut kept: Vec<(String, Array3<f32>)> = spec
        .outputs
        .iter()
        .filter(|t| t.name.ends_with("_heads"))
        .map(|t| {
            (t.name.clone(), Array3::zeros((n, bundle.config.heads * bundle.config.head_dim, bundle.config.width)))
        })
        .collect();
    let build = |range: Range<usize>| chunk_inputs(scene, &spec.inputs, rays, range, near_far, &|_, _| None);
    let chunk = chunking.rays_per_chunk(samples);
    run_chunks(ticket, GraphKind::RendererGuide, n, chunk, 1.0, true, build, |range, mut outputs| {
        let (rgb, depth, opacity) = take_pixels(&mut outputs, range.len())?;
        frame.canvas.put(&pixels[range.clone()], &rgb, &depth, &opacity);
        let weights = outputs.take::<Ix2>("sample_weights", &[Some(range.len()), Some(samples)])?;
        for (r, &p) in pixels[range.clone()].iter().enumerate() {
            if p.0 % 2 == 0 && p.1 % 2 == 0 {
                frame.guidance.set(p, weights.row(r));
            }
        }
        for (name, all) in &mut kept {
            let (h, c) = (all.shape()[1], all.shape()[2]);
            let got = outputs.take::<Ix3>(name, &[Some(range.len()), Some(h), Some(c)])?;
            all.slice_mut(s![range.clone(), .., ..]).assign(&got);
        }
        Ok(())
    })
    .await?;
    Ok(kept.into_iter().map(|(name, a)| (name, a.into_shared().into_dyn())).collect())
}

/// [`plan_level`] off the async runtime (it sorts samples for every pixel of the level).
async fn plan_level_blocking(
    policy: GuidedPolicy,
    mut frame: Frame,
    spacing: usize,
    count: usize,
) -> Result<(Frame, Vec<FineRays>), BackendError> {
    tokio::task::spawn_blocking(move || {
        let fine = plan_level(&policy, &mut frame, spacing, count);
        (frame, fine)
    })
    .await
    .map_err(|e| BackendError::Run { graph: GraphKind::RendererFine, message: format!("planning a level failed: {e}") })
}
