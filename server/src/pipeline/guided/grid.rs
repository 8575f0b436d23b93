//! The nested grids of guided sampling: which pixels each level renders, and their neighbours.

use crate::bundle::GuidedPolicy;

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

/// The level-0 ray nearest a pixel (half-way: the later), as a row of the level-0 grid: its
/// rectifier heads stand for the pixel's.
pub fn nearest_guide((v, u): Pixel, grid_width: usize, grid_height: usize, step: usize) -> usize {
    let v = ((v + step / 2) / step).min(grid_height - 1);
    let u = ((u + step / 2) / step).min(grid_width - 1);
    v * grid_width + u
}

/// Guided sampling's work, from the policy and the view's size alone.
impl GuidedPolicy {
    /// The level-0 rays of a `width` x `height` view.
    pub fn guide_rays(&self, width: usize, height: usize) -> usize {
        grid_len(width, self.step) * grid_len(height, self.step)
    }

    /// The guide rays of a `width` x `height` view, and its fine rays' samples at most (when no
    /// pixel takes its neighbours' mean, every pixel lies on an edge and the most pixels are
    /// rendered again, at all `samples`): for admission, before the view is rendered.
    pub fn most_work(&self, width: usize, height: usize, samples: usize) -> (usize, usize) {
        let fine = self
            .levels()
            .map(|(spacing, k)| {
                let n = level_pixels(width, height, spacing).len();
                n * self.samples_at(k, f32::INFINITY, usize::MAX) + self.most_reruns(n) * self.rerun_samples(samples)
            })
            .sum();
        (self.guide_rays(width, height), fine)
    }
}
