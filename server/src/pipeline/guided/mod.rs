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
//!   through `renderer_fine.onnx` with the rectifier heads of the nearest level-0 ray. Where the
//!   neighbours' colours span more than `edge_span`, the pixel lies on an edge, where K samples
//!   miss what one side saw, and runs at `edge_samples` samples instead. With `min_samples`, a
//!   pixel whose neighbours saw matter on fewer samples runs at fewer ([`Score::support`],
//!   [`GuidedPolicy::samples_at`](crate::bundle::GuidedPolicy::samples_at));
//! * after each level, its K-sample pixels whose colour or opacity their neighbours disagree
//!   with by more than `verify_tolerance` ([`disagreeing`]) are rendered again at
//!   `verify_samples` spread over the whole ray (all S without it; `renderer_fine.onnx`,
//!   [`again_samples`]), at most `verify_share` of them, before the next level reads them.
//!
//! A pixel is rendered once, or twice where it disagrees. The counts and thresholds are the
//! bundle's (`guided` in the manifest), so the exporter that measured them and the server agree.

mod grid;
mod plan;
mod run;
mod samples;
#[cfg(test)]
mod tests;

pub use grid::{first_level_pixels, grid_len, level_pixels, nearest_guide, neighbours, Pixel};
pub use plan::{
    again_samples, disagreeing, neighbour_score, plan_level, put_fine, Canvas, FineOutputs, FineRays, Frame, Guidance,
};
pub use run::render;
pub use samples::{select_samples, spread_samples, spread_weights, Score, Selection};
