//! Guided sampling: a view rendered coarse to fine, the network run only where the surface is.
//!
//! The policy's one home on the server (its Python twin is exporter/scnerf_export/runtime/guided.py;
//! the parity fixtures hold the two together). A view is rendered in levels of pixels on nested
//! grids:
//!
//! * level 0, every `step`-th pixel in both axes: the full network at the S uniform samples
//!   (`renderer_guide.onnx`), which also returns each ray's compositing weights and its
//!   rectifiers' heads. These pixels are exactly what full sampling renders;
//! * then grids of half the spacing each, down to every pixel. A pixel of a level has 2 or 4
//!   neighbours rendered before it, one spacing away. Where their composited colours agree
//!   within `smooth_tolerance` (on grids no coarser than `smooth_max_step`), the pixel takes their
//!   mean and the network does not run. Otherwise its samples come from the neighbours' weights
//!   ([`select_samples`]): the K (the level's `samples`) uniform samples where the neighbours
//!   composite most, each standing for the nearby samples where a neighbour saw matter, run
//!   through `renderer_fine.onnx` with the rectifier heads of the nearest level-0 ray;
//! * after each level, its K-sample pixels whose colour or opacity their neighbours disagree
//!   with by more than `verify_tolerance` ([`disagreeing`]) are rendered again at all S samples
//!   (`renderer_guide.onnx`), at most `verify_share` of them, before the next level reads them.
//!
//! A pixel is rendered once, or twice where it disagrees. The counts and thresholds are the
//! bundle's (`guided` in the manifest), so the exporter that measured them and the server agree.

use std::cmp::Ordering;
use std::ops::Range;

use ndarray::{s, ArcArray1, ArcArray2, Array1, Array2, Array3, ArrayView1, Ix2, Ix3};
use serde::{Deserialize, Serialize};

use super::chunks::{chunk_inputs, run_chunks, take_pixels, ChunkPolicy, RawView};
use super::rays::{self, Rays};
use super::Scene;
use crate::backend::{BackendError, Tensor, Ticket};
use crate::bundle::{Bundle, GraphKind};
use crate::camera::Camera;

/// How a view's rays are sampled.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, utoipa::ToSchema, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Sampling {
    /// The paper's S uniform samples on every ray.
    Full,
    /// Coarse to fine: the network near the surface only (this module).
    Guided,
}

impl Sampling {
    pub const ALL: [Sampling; 2] = [Sampling::Full, Sampling::Guided];

    pub fn name(self) -> &'static str {
        match self {
            Sampling::Full => "full",
            Sampling::Guided => "guided",
        }
    }

    pub fn parse(s: &str) -> Option<Sampling> {
        Sampling::ALL.into_iter().find(|m| m.name() == s)
    }
}

impl std::fmt::Display for Sampling {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The manifest's `guided` object (docs/bundle.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct GuidedPolicy {
    /// Spacing of the level-0 grid (a power of two).
    pub step: usize,
    /// Samples per pixel of each later level, coarse to fine (one per halving of the spacing).
    pub samples: Vec<usize>,
    /// A neighbour's (dilated) weight from which a sample counts as matter.
    pub support_threshold: f32,
    /// Largest spread of the neighbours' colours, per channel, for a pixel to take their mean.
    pub smooth_tolerance: f32,
    /// Coarsest grid spacing at which pixels may take their neighbours' mean.
    pub smooth_max_step: usize,
    /// A pixel rendered at K samples whose composited colour lies further than this outside its
    /// neighbours' range in a channel, or whose opacity lies this far below theirs, is rendered
    /// again at all S samples ([`disagreeing`]). Absent: no pixel is rendered again.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verify_tolerance: Option<f32>,
    /// The largest share of a level's K-sample pixels rendered again, the worst first: bounds a
    /// view's work when most of its pixels disagree.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verify_share: Option<f64>,
}

impl GuidedPolicy {
    /// Checks the policy against a model of `samples` samples per ray.
    pub fn validate(&self, samples: usize) -> Result<(), String> {
        if self.step == 0 || !self.step.is_power_of_two() {
            return Err(format!("guided.step must be a power of two, got {}", self.step));
        }
        if self.samples.len() != self.step.trailing_zeros() as usize {
            return Err(format!("guided.samples needs one count per level below step {}", self.step));
        }
        if let Some(k) = self.samples.iter().find(|&&k| k == 0 || k > samples) {
            return Err(format!("guided.samples: {k} is not within 1..={samples}"));
        }
        let finite = [self.support_threshold, self.smooth_tolerance].iter().all(|v| v.is_finite() && *v >= 0.0);
        if !finite {
            return Err("guided.support_threshold and guided.smooth_tolerance must be finite and >= 0".into());
        }
        match (self.verify_tolerance, self.verify_share) {
            (None, None) => Ok(()),
            (Some(t), Some(share)) if t.is_finite() && t >= 0.0 && (0.0..=1.0).contains(&share) => Ok(()),
            _ => Err("guided.verify_tolerance (finite, >= 0) and guided.verify_share (0 to 1) come together".into()),
        }
    }

    /// The most pixels of a level of `fine` K-sample pixels that are rendered again.
    pub fn most_reruns(&self, fine: usize) -> usize {
        self.verify_share.map_or(0, |share| (share * fine as f64).floor() as usize)
    }

    /// (grid spacing, samples per pixel) of every level after the first, coarse to fine.
    pub fn levels(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        self.samples.iter().enumerate().map(|(i, &k)| (self.step >> (i + 1), k))
    }

    /// The level-0 rays of a `width` x `height` view.
    pub fn guide_rays(&self, width: usize, height: usize) -> usize {
        grid_len(width, self.step) * grid_len(height, self.step)
    }

    /// The rays of a `width` x `height` view run at all S samples (the guide rays and, at most,
    /// the pixels rendered again), and its fine rays' samples at most (when no pixel takes its
    /// neighbours' mean): for admission, before the view is rendered.
    pub fn most_work(&self, width: usize, height: usize) -> (usize, usize) {
        let guide_rays = self.guide_rays(width, height);
        let levels = self.levels().map(|(spacing, k)| (level_pixels(width, height, spacing).len(), k));
        let (reruns, fine) = levels.fold((0, 0), |(r, f), (n, k)| (r + self.most_reruns(n), f + n * k));
        (guide_rays + reruns, fine)
    }
}

/// Points 0, n, 2n, ... below `len`.
pub fn grid_len(len: usize, spacing: usize) -> usize {
    (len.saturating_sub(1)) / spacing + 1
}

/// A pixel as (v, u): row, column.
pub type Pixel = (usize, usize);

/// The level-0 pixels: every `step`-th row and column, row by row.
pub fn first_level_pixels(width: usize, height: usize, step: usize) -> Vec<Pixel> {
    (0..height).step_by(step).flat_map(|v| (0..width).step_by(step).map(move |u| (v, u))).collect()
}

/// The pixels of the grid of `spacing` that are not on the grid of twice it, row by row: the
/// pixels of the level of that spacing.
pub fn level_pixels(width: usize, height: usize, spacing: usize) -> Vec<Pixel> {
    let coarse = 2 * spacing;
    (0..height)
        .step_by(spacing)
        .flat_map(|v| (0..width).step_by(spacing).map(move |u| (v, u)))
        .filter(|&(v, u)| v % coarse != 0 || u % coarse != 0)
        .collect()
}

/// The neighbours of a level's pixel rendered before it: one spacing away along each axis in
/// which it is off the coarser grid, inside the image; 1, 2 or 4 of them, in the order of the
/// offsets (-,-), (-,+), (+,-), (+,+).
pub fn neighbours((v, u): Pixel, width: usize, height: usize, spacing: usize) -> Vec<Pixel> {
    let coarse = 2 * spacing;
    let along = |x: usize, len: usize| -> Vec<usize> {
        if x.is_multiple_of(coarse) {
            vec![x]
        } else {
            [Some(x - spacing), (x + spacing < len).then_some(x + spacing)].into_iter().flatten().collect()
        }
    };
    let vs = along(v, height);
    let us = along(u, width);
    vs.iter().flat_map(|&nv| us.iter().map(move |&nu| (nv, nu))).collect()
}

/// The samples a fine ray runs, chosen from its neighbours' weights.
#[derive(Debug, Clone, PartialEq)]
pub struct Selection {
    /// K uniform-sample indices, increasing.
    pub index: Vec<u32>,
    /// How many uniform samples each stands for (>= 1).
    pub multiplicity: Vec<f32>,
    /// Per uniform sample, the position in `index` of the taken sample that stands for it, or -1.
    pub owner: Vec<i32>,
}

/// The `count` samples of a ray from its neighbours' weights `score` (S): see the Python twin,
/// `select_samples`. The score is dilated by one sample (half a neighbour's score); the samples
/// with the highest dilated scores are taken (ties: the nearer to the best sample, then the
/// lower index); every sample whose dilated score reaches `threshold` and is not taken is stood
/// for by the nearest taken one (ties: the lower).
pub fn select_samples(score: ArrayView1<f32>, count: usize, threshold: f32) -> Selection {
    let s = score.len();
    let at = |k: isize| if k < 0 || k as usize >= s { 0.0 } else { score[k as usize] };
    let dilated: Vec<f32> = (0..s as isize).map(|k| at(k).max(0.5 * at(k - 1).max(at(k + 1)))).collect();
    let best = dilated.iter().enumerate().fold(0, |b, (k, &d)| if d > dilated[b] { k } else { b });
    let rank = |a: &usize, b: &usize| {
        dilated[*b]
            .partial_cmp(&dilated[*a])
            .unwrap_or(Ordering::Equal)
            .then(a.abs_diff(best).cmp(&b.abs_diff(best)))
            .then(a.cmp(b))
    };
    let mut order: Vec<usize> = (0..s).collect();
    let count = count.min(s);
    if count < s {
        order.select_nth_unstable_by(count, rank);
    }
    let mut index: Vec<usize> = order[..count].to_vec();
    index.sort_unstable();
    let mut owner = vec![-1i32; s];
    let mut multiplicity = vec![0f32; count];
    let mut next = 0; // first taken index >= k
    for k in 0..s {
        while next < count && index[next] < k {
            next += 1;
        }
        let taken = next < count && index[next] == k;
        if !taken && dilated[k] < threshold {
            continue;
        }
        let lower = next.checked_sub(1);
        let nearest = match (lower, (next < count).then_some(next)) {
            (Some(l), Some(h)) if k - index[l] <= index[h] - k => l,
            (_, Some(h)) => h,
            (Some(l), None) => l,
            (None, None) => continue,
        };
        owner[k] = nearest as i32;
        multiplicity[nearest] += 1.0;
    }
    Selection { index: index.into_iter().map(|k| k as u32).collect(), multiplicity, owner }
}

/// A fine ray's weights over all S samples, for the levels after it: each taken sample's weight
/// shared among the samples it stands for.
pub fn spread_weights(weights: ArrayView1<f32>, selection: &Selection, out: &mut [f32]) {
    for (k, &o) in selection.owner.iter().enumerate() {
        out[k] = if o < 0 { 0.0 } else { weights[o as usize] / selection.multiplicity[o as usize] };
    }
}

/// The level-0 ray nearest a pixel (half-way: the later), as a row of the level-0 grid: its
/// rectifier heads stand for the pixel's.
pub fn nearest_guide((v, u): Pixel, grid_width: usize, grid_height: usize, step: usize) -> usize {
    let v = ((v + step / 2) / step).min(grid_height - 1);
    let u = ((u + step / 2) / step).min(grid_width - 1);
    v * grid_width + u
}

/// The weights over all S samples of the pixels later levels read: those on the grid of every
/// second row and column (every level's neighbours are), stored compactly.
pub struct Guidance {
    width: usize,
    weights: Array2<f32>,
}

impl Guidance {
    pub fn new(width: usize, height: usize, samples: usize) -> Guidance {
        Guidance {
            width: grid_len(width, 2),
            weights: Array2::zeros((grid_len(width, 2) * grid_len(height, 2), samples)),
        }
    }

    fn row((v, u): Pixel, width: usize) -> usize {
        debug_assert!(v % 2 == 0 && u % 2 == 0, "guidance is kept on the grid of 2");
        (v / 2) * width + u / 2
    }

    pub fn of(&self, p: Pixel) -> ArrayView1<'_, f32> {
        self.weights.row(Self::row(p, self.width))
    }

    pub fn set(&mut self, p: Pixel, weights: ArrayView1<f32>) {
        self.weights.row_mut(Self::row(p, self.width)).assign(&weights);
    }

    pub fn set_with(&mut self, p: Pixel, fill: impl FnOnce(&mut [f32])) {
        let row = Self::row(p, self.width);
        fill(self.weights.row_mut(row).as_slice_mut().expect("rows of a standard array are contiguous"));
    }

    /// Bytes of a view's guidance: for the memory estimate.
    pub fn bytes(width: usize, height: usize, samples: usize) -> u64 {
        (grid_len(width, 2) * grid_len(height, 2) * samples * 4) as u64
    }
}

/// Elementwise maximum of the neighbours' guidance: a fine ray's score.
pub fn neighbour_score(guidance: &Guidance, near: &[Pixel], samples: usize) -> Array1<f32> {
    let mut score = Array1::zeros(samples);
    for &p in near {
        score.zip_mut_with(&guidance.of(p), |s: &mut f32, &w| *s = s.max(w));
    }
    score
}

/// The raw outputs (before the background) of a view being rendered, row by row.
pub struct Canvas {
    pub width: usize,
    pub rgb: Array2<f32>,
    pub depth: Array1<f32>,
    pub opacity: Array1<f32>,
}

impl Canvas {
    pub fn new(width: usize, height: usize) -> Canvas {
        let n = width * height;
        Canvas { width, rgb: Array2::zeros((n, 3)), depth: Array1::zeros(n), opacity: Array1::zeros(n) }
    }

    pub fn index(&self, (v, u): Pixel) -> usize {
        v * self.width + u
    }

    fn composited(&self, p: Pixel, background: [f32; 3]) -> [f32; 3] {
        let i = self.index(p);
        let clear = 1.0 - self.opacity[i];
        std::array::from_fn(|c| self.rgb[[i, c]] + clear * background[c])
    }

    /// Whether at least two neighbours' composited colours agree within `tolerance` per channel.
    pub fn neighbours_agree(&self, near: &[Pixel], background: [f32; 3], tolerance: f32) -> bool {
        if near.len() < 2 {
            return false;
        }
        let colours: Vec<[f32; 3]> = near.iter().map(|&p| self.composited(p, background)).collect();
        (0..3).all(|c| {
            let (lo, hi) =
                colours.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), x| (lo.min(x[c]), hi.max(x[c])));
            hi - lo <= tolerance
        })
    }

    /// How far the pixel's outputs lie outside its neighbours': the largest distance of its
    /// composited colour outside their range in a channel, or of its opacity below their lowest.
    pub fn disagreement(&self, p: Pixel, near: &[Pixel], background: [f32; 3]) -> f32 {
        let own = self.composited(p, background);
        let colours: Vec<[f32; 3]> = near.iter().map(|&q| self.composited(q, background)).collect();
        let colour = (0..3).fold(0f32, |gap, c| {
            let (lo, hi) =
                colours.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), x| (lo.min(x[c]), hi.max(x[c])));
            gap.max(lo - own[c]).max(own[c] - hi)
        });
        let lowest = near.iter().map(|&q| self.opacity[self.index(q)]).fold(f32::INFINITY, f32::min);
        colour.max(lowest - self.opacity[self.index(p)])
    }

    /// The pixel takes the mean of its neighbours' outputs.
    pub fn take_mean(&mut self, p: Pixel, near: &[Pixel]) {
        let n = near.len() as f32;
        let rows: Vec<usize> = near.iter().map(|&q| self.index(q)).collect();
        let i = self.index(p);
        for c in 0..3 {
            self.rgb[[i, c]] = rows.iter().map(|&r| self.rgb[[r, c]]).sum::<f32>() / n;
        }
        self.depth[i] = rows.iter().map(|&r| self.depth[r]).sum::<f32>() / n;
        self.opacity[i] = rows.iter().map(|&r| self.opacity[r]).sum::<f32>() / n;
    }

    /// Outputs of rays `rows` of a run (rgb (R,3), depth (R), opacity (R)) into their pixels.
    pub fn put(&mut self, pixels: &[Pixel], rgb: &ArcArray2<f32>, depth: &ArcArray1<f32>, opacity: &ArcArray1<f32>) {
        for (r, &p) in pixels.iter().enumerate() {
            let i = self.index(p);
            self.rgb.row_mut(i).assign(&rgb.row(r));
            self.depth[i] = depth[r];
            self.opacity[i] = opacity[r];
        }
    }
}

/// A level's pixels that run the network, with what they run.
pub struct FineRays {
    pub pixels: Vec<Pixel>,
    pub selections: Vec<Selection>,
    /// (R, K) sample indices and multiplicities, (R) each ray's guide ray: graph inputs.
    pub index: Array2<f32>,
    pub multiplicity: Array2<f32>,
    pub guide: Array1<f32>,
}

/// A view being rendered: its outputs so far and the weights later levels read.
pub struct Frame {
    pub canvas: Canvas,
    pub guidance: Guidance,
    pub height: usize,
    pub background: [f32; 3],
}

/// One level: pixels whose neighbours agree take their mean (in the frame); the others get their
/// samples, returned.
pub fn plan_level(policy: &GuidedPolicy, frame: &mut Frame, spacing: usize, count: usize) -> FineRays {
    let Frame { canvas, guidance, height, background } = frame;
    let (width, height, background) = (canvas.width, *height, *background);
    let samples = guidance.weights.ncols();
    let keeps_guidance = spacing > 1;
    let (grid_w, grid_h) = (grid_len(width, policy.step), grid_len(height, policy.step));
    let mut run = Vec::new();
    let mut selections = Vec::new();
    for p in level_pixels(width, height, spacing) {
        let near = neighbours(p, width, height, spacing);
        if spacing <= policy.smooth_max_step && canvas.neighbours_agree(&near, background, policy.smooth_tolerance) {
            canvas.take_mean(p, &near);
            if keeps_guidance {
                let score = neighbour_score(guidance, &near, samples);
                guidance.set(p, score.view());
            }
            continue;
        }
        let score = neighbour_score(guidance, &near, samples);
        selections.push(select_samples(score.view(), count, policy.support_threshold));
        run.push(p);
    }
    let k = count.min(samples);
    let rows = run.len();
    let mut index = Array2::zeros((rows, k));
    let mut multiplicity = Array2::zeros((rows, k));
    for (r, sel) in selections.iter().enumerate() {
        index.row_mut(r).assign(&Array1::from_iter(sel.index.iter().map(|&i| i as f32)));
        multiplicity.row_mut(r).assign(&ArrayView1::from(&sel.multiplicity));
    }
    let guide = run.iter().map(|&p| nearest_guide(p, grid_w, grid_h, policy.step) as f32).collect();
    FineRays { pixels: run, selections, index, multiplicity, guide }
}

/// The pixels of a level rendered at K samples (`fine`) whose outputs disagree with their
/// neighbours' by more than the policy's `verify_tolerance` ([`Canvas::disagreement`]): the
/// worst, at most [`GuidedPolicy::most_reruns`] of them (ties: the earlier pixel), row by row.
/// Where their K samples missed matter the neighbours found, or found matter that is not there,
/// they are rendered again at all S samples.
pub fn disagreeing(policy: &GuidedPolicy, frame: &Frame, fine: &FineRays, spacing: usize) -> Vec<Pixel> {
    let Some(tolerance) = policy.verify_tolerance else { return Vec::new() };
    let (width, height) = (frame.canvas.width, frame.height);
    let mut worst: Vec<(f32, Pixel)> = fine
        .pixels
        .iter()
        .map(|&p| (frame.canvas.disagreement(p, &neighbours(p, width, height, spacing), frame.background), p))
        .filter(|&(gap, _)| gap > tolerance)
        .collect();
    worst.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    worst.truncate(policy.most_reruns(fine.pixels.len()));
    let mut pixels: Vec<Pixel> = worst.into_iter().map(|(_, p)| p).collect();
    pixels.sort_unstable();
    pixels
}

/// A fine run's outputs (rays `range` of the level) into the canvas, and its rays' weights into
/// the guidance when later levels read them.
pub fn put_fine(frame: &mut Frame, fine: &FineRays, range: Range<usize>, spacing: usize, outputs: &FineOutputs) {
    let (rgb, depth, opacity, weights) = outputs;
    frame.canvas.put(&fine.pixels[range.clone()], rgb, depth, opacity);
    if spacing > 1 {
        for (r, i) in range.enumerate() {
            let selection = &fine.selections[i];
            frame.guidance.set_with(fine.pixels[i], |row| spread_weights(weights.row(r), selection, row));
        }
    }
}

/// rgb (R,3), depth (R), opacity (R) and the samples' weights (R,K) of a fine run.
pub type FineOutputs = (ArcArray2<f32>, ArcArray1<f32>, ArcArray1<f32>, ArcArray2<f32>);

/// How a view was sampled, for the response and the metrics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SamplingReport {
    pub mode: Sampling,
    /// Network samples per pixel, on average over the view.
    pub samples_per_ray: f64,
}

/// The rectifiers' heads of the guide rays, by graph name (`geometry_heads`, ...): (G, h·d_k, C).
type Heads = Vec<(String, Tensor)>;

/// Renders every pixel of `target` by guided sampling: see the module doc.
#[allow(clippy::too_many_arguments)]
pub async fn render(
    ticket: &Ticket,
    bundle: &Bundle,
    policy: &GuidedPolicy,
    chunking: &ChunkPolicy,
    scene: &Scene,
    target: &Camera,
    background: [f32; 3],
) -> Result<(RawView, SamplingReport), BackendError> {
    let (width, height) = (target.width as usize, target.height as usize);
    let samples = bundle.config.samples;
    let rays = rays::generate(target);
    let mut frame = Frame {
        canvas: Canvas::new(width, height),
        guidance: Guidance::new(width, height, samples),
        height,
        background,
    };
    let levels: Vec<(usize, usize)> = policy.levels().collect();
    let first = first_level_pixels(width, height, policy.step);
    let mut heads = Heads::new();
    let all = AllSamples { pixels: &first, heads: Some(&mut heads) };
    // Each renderer's last run of the request may release its arena, where its session keeps
    // one (`Ticket::run_last`): the guide renderer's is level 0's unless pixels may be rendered
    // again, then the last level's pixels rendered again (none: its arena stays held).
    let guide_runs_again = policy.verify_tolerance.is_some() && !levels.is_empty();
    run_all_samples(ticket, bundle, chunking, scene, &rays, all, &mut frame, !guide_runs_again).await?;
    let mut network_samples = first.len() * samples;
    for (level, &(spacing, count)) in levels.iter().enumerate() {
        let fine;
        (frame, fine) = plan_level_blocking(policy.clone(), frame, spacing, count).await?;
        let last = level + 1 == levels.len();
        network_samples +=
            run_fine(ticket, bundle, chunking, scene, &rays, &heads, &fine, &mut frame, spacing, last).await?;
        let again = disagreeing(policy, &frame, &fine, spacing);
        let all = AllSamples { pixels: &again, heads: None };
        run_all_samples(ticket, bundle, chunking, scene, &rays, all, &mut frame, last).await?;
        network_samples += again.len() * samples;
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

/// Pixels run through the full network (`renderer_guide.onnx`) at all S samples, and where
/// their rectifier heads go: level 0's are kept for the fine rays, a pixel rendered again needs
/// none.
struct AllSamples<'a> {
    pixels: &'a [Pixel],
    heads: Option<&'a mut Heads>,
}

/// Level 0, or the pixels of a level rendered again: their outputs into the canvas, their weights
/// into the guidance (for the pixels later levels read), their heads where asked.
#[allow(clippy::too_many_arguments)]
async fn run_all_samples(
    ticket: &Ticket,
    bundle: &Bundle,
    chunking: &ChunkPolicy,
    scene: &Scene,
    all_rays: &Rays,
    AllSamples { pixels, heads }: AllSamples<'_>,
    frame: &mut Frame,
    last: bool,
) -> Result<(), BackendError> {
    let n = pixels.len();
    if n == 0 {
        return Ok(());
    }
    let spec = bundle.graph(GraphKind::RendererGuide);
    let rays = &all_rays.select(&pixels.iter().map(|&p| frame.canvas.index(p)).collect::<Vec<_>>());
    let samples = bundle.config.samples;
    let near_far = [scene.near as f32, scene.far as f32];
    let keeps_heads = heads.is_some();
    let mut kept: Vec<(String, Array3<f32>)> = spec
        .outputs
        .iter()
        .filter(|t| keeps_heads && t.name.ends_with("_heads"))
        .map(|t| {
            (t.name.clone(), Array3::zeros((n, bundle.config.heads * bundle.config.head_dim, bundle.config.width)))
        })
        .collect();
    let build = |range: Range<usize>| chunk_inputs(scene, &spec.inputs, rays, range, near_far, &|_, _| None);
    let chunk = chunking.rays_per_chunk(samples);
    run_chunks(ticket, GraphKind::RendererGuide, n, chunk, 1.0, last, build, |range, mut outputs| {
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
    if let Some(heads) = heads {
        *heads = kept.into_iter().map(|(name, a)| (name, a.into_shared().into_dyn())).collect();
    }
    Ok(())
}

/// [`plan_level`] off the async runtime (it sorts samples for every pixel of the level).
async fn plan_level_blocking(
    policy: GuidedPolicy,
    mut frame: Frame,
    spacing: usize,
    count: usize,
) -> Result<(Frame, FineRays), BackendError> {
    tokio::task::spawn_blocking(move || {
        let fine = plan_level(&policy, &mut frame, spacing, count);
        (frame, fine)
    })
    .await
    .map_err(|e| BackendError::Run { graph: GraphKind::RendererFine, message: format!("planning a level failed: {e}") })
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::arr1;

    #[test]
    fn levels_cover_every_pixel_once() {
        let (w, h, step) = (21, 13, 8);
        let mut seen = vec![0; w * h];
        for (v, u) in first_level_pixels(w, h, step) {
            seen[v * w + u] += 1;
        }
        let mut spacing = step / 2;
        while spacing >= 1 {
            for (v, u) in level_pixels(w, h, spacing) {
                seen[v * w + u] += 1;
                let near = neighbours((v, u), w, h, spacing);
                assert!(!near.is_empty() && near.len() <= 4);
                // Every neighbour lies on the coarser grid, rendered by an earlier level.
                assert!(near.iter().all(|&(nv, nu)| nv % (2 * spacing) == 0 && nu % (2 * spacing) == 0));
            }
            spacing /= 2;
        }
        assert!(seen.iter().all(|&n| n == 1), "{seen:?}");
    }

    #[test]
    fn neighbours_are_one_spacing_away() {
        assert_eq!(neighbours((0, 4), 16, 16, 4), vec![(0, 0), (0, 8)]);
        assert_eq!(neighbours((4, 4), 16, 16, 4), vec![(0, 0), (0, 8), (8, 0), (8, 8)]);
        // The last column has no neighbour beyond the image.
        assert_eq!(neighbours((2, 15), 16, 16, 1), vec![(2, 14)]);
    }

    #[test]
    fn a_narrow_surface_is_sampled_exactly() {
        let mut score = Array1::<f32>::zeros(16);
        score[7] = 0.6;
        score[8] = 0.3;
        let sel = select_samples(score.view(), 4, 1e-3);
        // The two samples with weight, their dilation (6 and 9), nothing else stands for more.
        assert_eq!(sel.index, vec![6, 7, 8, 9]);
        assert_eq!(sel.multiplicity, vec![1.0; 4]);
        assert_eq!(sel.owner.iter().filter(|&&o| o >= 0).count(), 4);
    }

    #[test]
    fn a_wide_surface_is_stood_for_by_its_samples() {
        let score = arr1(&[0.0, 0.1, 0.1, 0.1, 0.1, 0.5, 0.1, 0.1, 0.1, 0.0, 0.0, 0.0]);
        let sel = select_samples(score.view(), 3, 1e-3);
        assert_eq!(sel.index, vec![4, 5, 6]);
        // Support: samples 0..=9 (0 and 9 by dilation); 0..=4 go to 4, 6..=9 to 6.
        assert_eq!(sel.multiplicity, vec![5.0, 1.0, 4.0]);
        assert_eq!(sel.multiplicity.iter().sum::<f32>(), 10.0);
        let mut spread = vec![0.0; 12];
        spread_weights(arr1(&[0.5, 0.2, 0.4]).view(), &sel, &mut spread);
        assert_eq!(spread[0], 0.1);
        assert_eq!(spread[5], 0.2);
        assert_eq!(spread[9], 0.1);
        assert_eq!(spread[10], 0.0);
    }

    #[test]
    fn ties_go_to_the_samples_nearest_the_best() {
        let sel = select_samples(Array1::<f32>::zeros(10).view(), 3, 1e-3);
        assert_eq!(sel.index, vec![0, 1, 2]);
        let mut score = Array1::<f32>::zeros(10);
        score[5] = 1.0;
        let sel = select_samples(score.view(), 5, 0.6);
        assert_eq!(sel.index, vec![3, 4, 5, 6, 7]);
    }

    #[test]
    fn the_nearest_guide_ray_rounds_half_way_up() {
        // A 3 x 3 level-0 grid at step 8 (pixels 0, 8, 16).
        assert_eq!(nearest_guide((4, 2), 3, 3, 8), 3);
        assert_eq!(nearest_guide((3, 12), 3, 3, 8), 2);
        // Beyond the last grid column: the last column.
        assert_eq!(nearest_guide((0, 23), 3, 3, 8), 2);
    }

    /// A 5 x 5 frame whose every pixel is grey and opaque.
    fn grey_frame() -> Frame {
        let mut canvas = Canvas::new(5, 5);
        canvas.rgb.fill(0.5);
        canvas.opacity.fill(1.0);
        Frame { canvas, guidance: Guidance::new(5, 5, 4), height: 5, background: [0.0; 3] }
    }

    fn verifying(tolerance: f32, share: f64) -> GuidedPolicy {
        GuidedPolicy {
            step: 4,
            samples: vec![4, 4],
            support_threshold: 1e-3,
            smooth_tolerance: 0.0,
            smooth_max_step: 1,
            verify_tolerance: Some(tolerance),
            verify_share: Some(share),
        }
    }

    fn fine_at(pixels: Vec<Pixel>) -> FineRays {
        FineRays {
            pixels,
            selections: Vec::new(),
            index: Array2::zeros((0, 0)),
            multiplicity: Array2::zeros((0, 0)),
            guide: Array1::zeros(0),
        }
    }

    #[test]
    fn pixels_that_disagree_with_their_neighbours_are_rendered_again_worst_first() {
        let mut frame = grey_frame();
        // On the grid of spacing 1: (1, 1) missed its neighbours' matter (dark: the background
        // shows), (1, 3) is brighter than any neighbour, (3, 1) a little off, (3, 3) agrees.
        let i = |p| frame.canvas.index(p);
        let (dark, bright, slight) = (i((1, 1)), i((1, 3)), i((3, 1)));
        frame.canvas.opacity[dark] = 0.3;
        frame.canvas.rgb.row_mut(dark).fill(0.15);
        frame.canvas.rgb.row_mut(bright).fill(0.9);
        frame.canvas.rgb.row_mut(slight).fill(0.55);
        let fine = fine_at(vec![(1, 1), (1, 3), (3, 1), (3, 3)]);
        let near = neighbours((1, 1), 5, 5, 1);
        assert!((frame.canvas.disagreement((1, 1), &near, [0.0; 3]) - 0.7).abs() < 1e-6);
        assert_eq!(disagreeing(&verifying(0.1, 1.0), &frame, &fine, 1), vec![(1, 1), (1, 3)]);
        // The share bounds how many: the worst (the dark pixel, 0.7 off) first.
        assert_eq!(disagreeing(&verifying(0.01, 0.25), &frame, &fine, 1), vec![(1, 1)]);
        assert_eq!(disagreeing(&verifying(0.01, 0.75), &frame, &fine, 1), vec![(1, 1), (1, 3), (3, 1)]);
        // A policy without verification renders no pixel again.
        let plain = GuidedPolicy { verify_tolerance: None, verify_share: None, ..verifying(0.0, 1.0) };
        assert!(disagreeing(&plain, &frame, &fine, 1).is_empty());
    }

    #[test]
    fn reruns_count_in_the_most_work() {
        let policy = verifying(0.1, 0.5);
        let plain = GuidedPolicy { verify_tolerance: None, verify_share: None, ..policy.clone() };
        let (w, h) = (9, 9);
        let fine: Vec<usize> = policy.levels().map(|(spacing, _)| level_pixels(w, h, spacing).len()).collect();
        let reruns: usize = fine.iter().map(|&n| n / 2).sum();
        assert_eq!(policy.most_work(w, h).0, plain.most_work(w, h).0 + reruns);
        assert_eq!(policy.most_work(w, h).1, plain.most_work(w, h).1);
        assert!(GuidedPolicy { verify_share: None, ..policy.clone() }.validate(128).is_err());
        assert!(GuidedPolicy { verify_share: Some(1.5), ..policy }.validate(128).is_err());
    }

    #[test]
    fn policy_checks() {
        let policy = GuidedPolicy {
            step: 8,
            samples: vec![32, 16, 8],
            support_threshold: 1e-3,
            smooth_tolerance: 0.03,
            smooth_max_step: 2,
            verify_tolerance: None,
            verify_share: None,
        };
        assert!(policy.validate(128).is_ok());
        assert!(policy.validate(16).unwrap_err().contains("32"));
        assert!(GuidedPolicy { step: 6, ..policy.clone() }.validate(128).is_err());
        assert!(GuidedPolicy { samples: vec![8], ..policy.clone() }.validate(128).is_err());
        assert_eq!(policy.levels().collect::<Vec<_>>(), vec![(4, 32), (2, 16), (1, 8)]);
    }
}
