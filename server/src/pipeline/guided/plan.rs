//! A view being rendered level by level: its canvas, the weights later levels read, and what each
//! level runs.

use std::collections::BTreeMap;
use std::ops::Range;

use ndarray::{ArcArray1, ArcArray2, Array1, Array2, ArrayView1};

use super::grid::{grid_len, level_pixels, nearest_guide, neighbours, Pixel};
use super::samples::{select_samples, spread_samples, spread_weights, Score, Selection};
use crate::bundle::GuidedPolicy;

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

    /// The lowest and highest of the neighbours' composited colours, per channel.
    fn colour_range(&self, near: &[Pixel], background: [f32; 3]) -> [(f32, f32); 3] {
        let colours: Vec<[f32; 3]> = near.iter().map(|&p| self.composited(p, background)).collect();
        std::array::from_fn(|c| {
            colours.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), x| (lo.min(x[c]), hi.max(x[c])))
        })
    }

    /// The largest spread of the neighbours' composited colours in a channel (0 for fewer than
    /// two).
    pub fn colour_span(&self, near: &[Pixel], background: [f32; 3]) -> f32 {
        self.colour_range(near, background).iter().fold(0f32, |span, (lo, hi)| span.max(hi - lo))
    }

    /// How far the pixel's outputs lie outside its neighbours': the largest distance of its
    /// composited colour outside their range in a channel, or of its opacity below their lowest.
    pub fn disagreement(&self, p: Pixel, near: &[Pixel], background: [f32; 3]) -> f32 {
        let own = self.composited(p, background);
        let range = self.colour_range(near, background);
        let colour = own.iter().zip(range).fold(0f32, |gap, (&x, (lo, hi))| gap.max(lo - x).max(x - hi));
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

impl FineRays {
    /// The rays of `pixels`, each with its `selection` of `k` samples.
    fn new(
        policy: &GuidedPolicy,
        grid: (usize, usize),
        k: usize,
        pixels: Vec<Pixel>,
        selections: Vec<Selection>,
    ) -> Self {
        let rows = pixels.len();
        let mut index = Array2::zeros((rows, k));
        let mut multiplicity = Array2::zeros((rows, k));
        for (r, sel) in selections.iter().enumerate() {
            index.row_mut(r).assign(&Array1::from_iter(sel.index.iter().map(|&i| i as f32)));
            multiplicity.row_mut(r).assign(&ArrayView1::from(&sel.multiplicity));
        }
        let guide = pixels.iter().map(|&p| nearest_guide(p, grid.0, grid.1, policy.step) as f32).collect();
        FineRays { pixels, selections, index, multiplicity, guide }
    }
}

/// One level: pixels whose neighbours agree take their mean (in the frame); the others get their
/// samples, returned in runs of one sample count each: the level's `count`, then edge pixels'
/// (where the policy gives them more).
pub fn plan_level(policy: &GuidedPolicy, frame: &mut Frame, spacing: usize, count: usize) -> Vec<FineRays> {
    let Frame { canvas, guidance, height, background } = frame;
    let (width, height, background) = (canvas.width, *height, *background);
    let samples = guidance.weights.ncols();
    let keeps_guidance = spacing > 1;
    let grid = (grid_len(width, policy.step), grid_len(height, policy.step));
    // Sample count -> (pixels, selections), in increasing count.
    let mut runs: BTreeMap<usize, (Vec<Pixel>, Vec<Selection>)> = BTreeMap::new();
    for p in level_pixels(width, height, spacing) {
        let near = neighbours(p, width, height, spacing);
        let span = canvas.colour_span(&near, background);
        if spacing <= policy.smooth_max_step && near.len() >= 2 && span <= policy.smooth_tolerance {
            canvas.take_mean(p, &near);
            if keeps_guidance {
                let score = neighbour_score(guidance, &near, samples);
                guidance.set(p, score.view());
            }
            continue;
        }
        let score = Score::of(neighbour_score(guidance, &near, samples).view());
        let k = policy.samples_at(count, span, score.support(policy.support_threshold)).min(samples);
        let (pixels, selections) = runs.entry(k).or_default();
        selections.push(select_samples(&score, k, policy.support_threshold));
        pixels.push(p);
    }
    runs.into_iter().map(|(k, (pixels, selections))| FineRays::new(policy, grid, k, pixels, selections)).collect()
}

/// The pixels of a level rendered at K samples (`fine`, row by row) whose outputs disagree with
/// their neighbours' by more than the policy's `verify_tolerance` ([`Canvas::disagreement`]): the
/// worst, at most [`GuidedPolicy::most_reruns`] of them (ties: the earlier pixel), row by row.
/// Where their K samples missed matter the neighbours found, or found matter that is not there,
/// they are rendered again at the policy's `verify_samples` ([`again_samples`]).
pub fn disagreeing(policy: &GuidedPolicy, frame: &Frame, fine: &[Pixel], spacing: usize) -> Vec<Pixel> {
    let Some(tolerance) = policy.verify_tolerance else { return Vec::new() };
    let (width, height) = (frame.canvas.width, frame.height);
    let mut worst: Vec<(f32, Pixel)> = fine
        .iter()
        .map(|&p| (frame.canvas.disagreement(p, &neighbours(p, width, height, spacing), frame.background), p))
        .filter(|&(gap, _)| gap > tolerance)
        .collect();
    worst.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    worst.truncate(policy.most_reruns(fine.len()));
    let mut pixels: Vec<Pixel> = worst.into_iter().map(|(_, p)| p).collect();
    pixels.sort_unstable();
    pixels
}

/// The pixels rendered again: fine rays at the policy's [`GuidedPolicy::rerun_samples`] samples,
/// their neighbours' support and the rest spread over the ray ([`spread_samples`]), with the
/// nearest guide ray's heads like every fine ray (rendering them through the guide renderer, with
/// their own heads, runs the rectifiers' attention again and scored the same).
pub fn again_samples(policy: &GuidedPolicy, frame: &Frame, spacing: usize, pixels: Vec<Pixel>) -> FineRays {
    let (width, height) = (frame.canvas.width, frame.height);
    let samples = frame.guidance.weights.ncols();
    let count = policy.rerun_samples(samples);
    let selections = pixels
        .iter()
        .map(|&p| {
            let weights = neighbour_score(&frame.guidance, &neighbours(p, width, height, spacing), samples);
            spread_samples(&Score::of(weights.view()), count, policy.support_threshold)
        })
        .collect();
    let grid = (grid_len(width, policy.step), grid_len(height, policy.step));
    FineRays::new(policy, grid, count, pixels, selections)
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
