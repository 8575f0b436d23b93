//! Start-up: load and verify the bundle, create the ONNX Runtime sessions, bind, warm up, serve.

use std::io::Write;
use std::sync::Arc;
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Matrix3, Vector3};
use ndarray::Array4;
use tokio::net::TcpListener;

use crate::backend::ort::OrtRunner;
use crate::backend::{BackendHandle, MemoryBudget};
use crate::bundle::Bundle;
use crate::camera::CanonicalCamera;
use crate::config::Config;
use crate::http::serve::{ensure_file_limit, serve};
use crate::http::{router, AppState};
use crate::pipeline::scene::Timings;
use crate::pipeline::Pipeline;
use crate::sysmem;

pub async fn run(config: Config) -> Result<(), String> {
    let signals = shutdown_signals()?;
    let serve_options = config.serve_options();
    ensure_file_limit(serve_options.max_connections)?;
    // Before the slow part (loading the graphs): a bad token file fails the start at once.
    let options = config.service_options()?;
    if options.auth.enabled() {
        tracing::info!(tokens = options.auth.token_count(), "bearer-token authentication on");
    }
    let bundle_dir = config.bundle_dir();
    let bundle = Bundle::load(&bundle_dir).map_err(|e| e.to_string())?;
    tracing::info!(model_id = %bundle.manifest.model_id, dir = %bundle_dir.display(), "bundle verified");
    let ort = config.ort_options();
    let runner = {
        let bundle = bundle.clone();
        let exec = config.exec_options();
        tokio::task::spawn_blocking(move || OrtRunner::load_with(&bundle, &ort, &exec))
            .await
            .map_err(|e| e.to_string())?
            .map_err(|e| format!("bundle {}: {e}", bundle_dir.display()))?
    };
    let (budget, budget_source) = config.memory_budget();
    tracing::info!(budget_mib = budget >> 20, source = %budget_source, "memory budget");
    let backend = BackendHandle::spawn(Box::new(runner), config.executor_options()).map_err(|e| e.to_string())?;
    let pipeline = Pipeline::new(backend, bundle, config.chunking(), config.slabs(), config.limits())
        .with_default_sampling(config.sampling);
    if pipeline.default_sampling() != config.sampling {
        tracing::info!(asked = %config.sampling, "the bundle has no guided-sampling graphs: views are sampled in full");
    }
    let state = AppState::new(pipeline, options);
    spawn_cache_sweeper(&state);

    let listener =
        TcpListener::bind(config.addr).await.map_err(|e| format!("cannot listen on {}: {e}", config.addr))?;
    let local = listener.local_addr().map_err(|e| e.to_string())?;
    // Scripts and the end-to-end tests read this line to find an ephemeral port.
    println!("listening on http://{local}");
    let _ = std::io::stdout().flush();
    tracing::info!(%local, "listening");

    let (failed_tx, failed_rx) = tokio::sync::oneshot::channel::<String>();
    if config.skip_warmup {
        reserve_memory(&state)?;
        state.set_ready();
    } else {
        let state = state.clone();
        tokio::spawn(async move {
            let warmed = warm_up(state.pipeline()).await.map_err(|e| format!("warm-up render failed: {e}"));
            match warmed.and_then(|elapsed| Ok((elapsed, reserve_memory(&state)?))) {
                Ok((elapsed, memory)) => {
                    tracing::info!(
                        ms = elapsed.as_millis() as u64,
                        reserved_mib = memory.reserved >> 20,
                        for_requests_mib = memory.for_requests() >> 20,
                        "warm-up render done; ready"
                    );
                    state.set_ready();
                }
                Err(e) => {
                    let _ = failed_tx.send(e);
                }
            }
        });
    }

    let warmup_error = Arc::new(std::sync::Mutex::new(None));
    let grace_secs = serve_options.shutdown_grace.as_secs();
    let shutdown = {
        let (warmup_error, state) = (warmup_error.clone(), state.clone());
        async move {
            tokio::select! {
                _ = signals => {
                    tracing::info!(grace_secs, "shutting down");
                    state.set_draining();
                }
                Ok(e) = failed_rx => {
                    *warmup_error.lock().unwrap_or_else(|p| p.into_inner()) = Some(e);
                }
            }
        }
    };
    let app = crate::http::viewer::mount(router(state), &config);
    let stopped = serve(listener, app, &serve_options, shutdown).await;
    let failure = warmup_error.lock().unwrap_or_else(|p| p.into_inner()).take();
    if let Some(e) = failure {
        return Err(e);
    }
    if stopped.cut > 0 {
        return Err(format!("the shutdown grace period ran out: {} requests in flight were answered 503", stopped.cut));
    }
    tracing::info!("shut down");
    Ok(())
}

/// Sets aside the memory held apart from requests: the process at rest after the warm-up (the
/// sessions, their weights, the renderer's arena) and the scene cache at its limit.
fn reserve_memory(state: &AppState) -> Result<MemoryBudget, String> {
    let at_rest = sysmem::resident().map_or(0, |r| r.now);
    let cache = state.scenes().config().max_bytes as u64;
    state.pipeline().executor().reserve(at_rest + cache)
}

/// Expired scenes are also dropped on every cache access; this frees their memory when the
/// server is idle.
fn spawn_cache_sweeper(state: &AppState) {
    let scenes = Arc::downgrade(state.scenes());
    let period = (state.scenes().config().ttl / 4).clamp(Duration::from_secs(1), Duration::from_secs(60));
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(period);
        loop {
            tick.tick().await;
            let Some(scenes) = scenes.upgrade() else { break };
            scenes.purge_expired(Instant::now());
        }
    });
}

/// Resolves on SIGTERM or SIGINT. The handlers are installed when this is called (before the
/// server announces itself), so a signal arriving during start-up is not lost or fatal.
fn shutdown_signals() -> Result<impl std::future::Future<Output = ()>, String> {
    use tokio::signal::unix::{signal, SignalKind};
    let mut term = signal(SignalKind::terminate()).map_err(|e| format!("cannot handle SIGTERM: {e}"))?;
    let mut int = signal(SignalKind::interrupt()).map_err(|e| format!("cannot handle SIGINT: {e}"))?;
    Ok(async move {
        tokio::select! { _ = term.recv() => {}, _ = int.recv() => {} }
    })
}

/// Renders a tiny synthetic view through all three graphs: checks that the bundle really runs
/// before /readyz says so, and lets ONNX Runtime allocate its kernels.
pub async fn warm_up(pipeline: &Pipeline) -> Result<Duration, String> {
    let start = Instant::now();
    let config = pipeline.config();
    let size = config.image_multiple;
    let cameras = warmup_cameras(config.views, size as u32);
    let images = Array4::from_elem((config.views, 3, size, size), 0.5);
    let mut timings = Timings::default();
    let mut target = cameras[0].clone();
    target.width = 4;
    target.height = 4;
    // Warm-up runs before readiness, alone on the executor; the deadline only bounds a hang.
    let samplings = pipeline.samplings();
    let work = samplings.iter().fold(pipeline.scene_work(&cameras), |w, &s| w.plus(pipeline.view_work(&target, s)));
    let ticket = pipeline.admit(Instant::now() + Duration::from_secs(3600), work, 0).map_err(|e| e.to_string())?;
    let scene = pipeline
        .build_scene(&ticket, &cameras, images.into_shared(), 2.0, 6.0, &mut timings)
        .await
        .map_err(|e| e.to_string())?;
    // Every way of sampling the bundle has, so that each of its graphs has run once.
    for sampling in samplings {
        let view = pipeline
            .render_view(&ticket, &scene, &target, [0.0; 3], sampling, None, &mut timings)
            .await
            .map_err(|e| e.to_string())?;
        if view.rgb.iter().chain(&view.depth).chain(&view.opacity).any(|v| !v.is_finite()) {
            return Err(format!("the warm-up render ({sampling} sampling) produced non-finite values"));
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
