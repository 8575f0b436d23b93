//! The warm-up render: every model renders a tiny synthetic view before it serves.

use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Matrix3, Vector3};
use ndarray::Array4;

use crate::backend::BackendError;
use crate::camera::CanonicalCamera;
use crate::pipeline::scene::Timings;
use crate::pipeline::Pipeline;

/// Renders a tiny synthetic view through all three graphs: checks that the bundle really runs
/// before /readyz says so, and lets ONNX Runtime allocate its kernels.
pub async fn warm_up(pipeline: &Pipeline) -> Result<Duration, String> {
    warm_up_within(pipeline, Duration::from_secs(3600)).await
}

/// [`warm_up`] that fails once `within` has passed: a graph crafted to run for minutes (a long
/// `Loop`) is not served. The runs it queued are dropped with it; the one in progress is ended
/// at the deadline (`backend/watchdog.rs`), then the executor takes the next request's.
pub async fn warm_up_within(pipeline: &Pipeline, within: Duration) -> Result<Duration, String> {
    try_warm_up(pipeline, within).await.map_err(|e| e.to_string())
}

/// Why a warm-up did not pass: the model's fault, or the server's load at the time.
#[derive(Debug, thiserror::Error)]
pub enum WarmUpError {
    /// Not admitted (the budget or the queue has no room now): may pass later, unchanged.
    #[error("not admitted now: {0}")]
    Busy(String),
    /// It failed, or it was admitted and missed its deadline.
    #[error("{0}")]
    Failed(String),
}

/// [`warm_up_within`], saying whose fault a failure is.
pub async fn try_warm_up(pipeline: &Pipeline, within: Duration) -> Result<Duration, WarmUpError> {
    match tokio::time::timeout(within, render(pipeline, within)).await {
        Ok(done) => done,
        Err(_) => Err(missed(within)),
    }
}

fn missed(within: Duration) -> WarmUpError {
    WarmUpError::Failed(format!("it did not finish within {} s (--warmup-timeout-secs)", within.as_secs_f64()))
}

/// A graph run's failure; one ended at the deadline (`backend/watchdog.rs`) is the deadline missed.
fn failed(error: BackendError, within: Duration) -> WarmUpError {
    match error {
        BackendError::DeadlineExceeded => missed(within),
        error => WarmUpError::Failed(error.to_string()),
    }
}

async fn render(pipeline: &Pipeline, within: Duration) -> Result<Duration, WarmUpError> {
    let (start, deadline) = (Instant::now(), Instant::now() + within);
    let config = pipeline.config();
    let size = config.image_multiple;
    let cameras = warmup_cameras(config.views, size as u32);
    let images = Array4::from_elem((config.views, 3, size, size), 0.5);
    let mut timings = Timings::default();
    let mut target = cameras[0].clone();
    target.width = 4;
    target.height = 4;
    // Admitted as a request is, with its memory estimate: it waits its turn, is refused when the
    // budget lacks room, and its graphs' runs stop at the deadline.
    let samplings = pipeline.samplings();
    let work = samplings.iter().fold(pipeline.scene_work(&cameras), |w, &s| w.plus(pipeline.view_work(&target, s)));
    let memory = samplings.iter().map(|&s| pipeline.memory_estimate(Some(&cameras), false, true, Some((&target, s))));
    let ticket =
        pipeline.admit(deadline, work, memory.max().unwrap_or(0)).map_err(|e| WarmUpError::Busy(e.message()))?;
    let scene = pipeline
        .build_scene(&ticket, &cameras, images.into_shared(), 2.0, 6.0, &mut timings)
        .await
        .map_err(|e| failed(e, within))?;
    // Every way of sampling the bundle has, so that each of its graphs has run once.
    for sampling in samplings {
        let view = pipeline
            .render_view(&ticket, &scene, &target, [0.0; 3], sampling, None, &mut timings)
            .await
            .map_err(|e| failed(e, within))?;
        if view.rgb.iter().chain(&view.depth).chain(&view.opacity).any(|v| !v.is_finite()) {
            return Err(WarmUpError::Failed(format!(
                "the warm-up render ({sampling} sampling) produced non-finite values"
            )));
        }
    }
    pipeline.executor().forget_rates();
    Ok(start.elapsed())
}

/// Cameras on a small arc 4 units from the origin, looking at it (OpenCV, world-to-camera).
fn warmup_cameras(views: usize, size: u32) -> Vec<CanonicalCamera> {
    let (f, c) = (f64::from(size), f64::from(size) / 2.0);
    (0..views)
        .map(|i| {
            // Rotation about y by -0.1·i; the origin lies 4 units ahead on the optical axis.
            let w2c = Isometry3::new(Vector3::new(0.0, 0.0, 4.0), Vector3::y() * (-0.1 * i as f64));
            CanonicalCamera {
                width: size,
                height: size,
                k: Matrix3::new(f, 0.0, c, 0.0, f, c, 0.0, 0.0, 1.0),
                w2c: w2c.to_homogeneous(),
            }
        })
        .collect()
}
