//! What the stages hand on: a scene's encoding, a rendered view, the time each stage took.

use std::time::{Duration, Instant};

use ndarray::{ArcArray3, ArcArray4, ArcArray5, Array2, Array3};

use crate::request::Sampling;

/// Wall time per stage, in the order the stages ran.
#[derive(Debug, Clone, Default)]
pub struct Timings(pub Vec<(&'static str, Duration)>);

impl Timings {
    pub fn add(&mut self, stage: &'static str, d: Duration) {
        self.0.push((stage, d));
    }

    /// Times one async stage.
    pub async fn time<T, F: std::future::Future<Output = T>>(&mut self, stage: &'static str, f: F) -> T {
        let start = Instant::now();
        let out = f.await;
        self.add(stage, start.elapsed());
        out
    }

    pub fn millis(&self) -> Vec<(&'static str, f64)> {
        self.0.iter().map(|(s, d)| (*s, d.as_secs_f64() * 1e3)).collect()
    }
}

/// Everything the renderer needs about the sources it renders from (the model's view count:
/// three); reusable for any number of target views. The arrays are shared: every renderer run
/// of every view reads them without a copy.
#[derive(Debug, Clone)]
pub struct Scene {
    /// (V, 3, H, W) padded source images in [0, 1].
    pub images: ArcArray4<f32>,
    /// (V, C, H/4, W/4) encoder output.
    pub features: ArcArray4<f32>,
    /// (1, Cv, D, H/4 + 2·pad, W/4 + 2·pad) encoding volume.
    pub volume: ArcArray5<f32>,
    /// (V, 3, 3) full-resolution K per view.
    pub intrinsics: ArcArray3<f32>,
    /// (V, 4, 4) OpenCV world-to-camera per view.
    pub extrinsics: ArcArray3<f32>,
    /// Each view's (width, height) before padding.
    pub source_sizes: Vec<(usize, usize)>,
    pub near: f64,
    pub far: f64,
}

impl Scene {
    /// Approximate memory held by the scene (for cache accounting).
    pub fn bytes(&self) -> usize {
        4 * (self.images.len() + self.features.len() + self.volume.len())
    }
}

/// A rendered view: composited RGB (H, W, 3) in [0, 1], depth and opacity (H, W), and how its
/// rays were sampled.
#[derive(Debug, Clone)]
pub struct View {
    pub rgb: Array3<f32>,
    pub depth: Array2<f32>,
    pub opacity: Array2<f32>,
    pub sampling: SamplingReport,
}

impl View {
    pub fn width(&self) -> u32 {
        self.depth.ncols() as u32
    }

    pub fn height(&self) -> u32 {
        self.depth.nrows() as u32
    }
}

/// How a view was sampled, for the response and the metrics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SamplingReport {
    pub mode: Sampling,
    /// Network samples per pixel, on average over the view.
    pub samples_per_ray: f64,
}
