//! Start-up: load and verify the bundles, create each model's ONNX Runtime sessions, bind, warm
//! up every model, serve.

use std::io::Write;
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::net::TcpListener;

use crate::backend::ort::OrtRunner;
use crate::backend::{BackendHandle, GraphRunner, MemoryBudget};
use crate::bundle::Bundle;
use crate::config::Config;
use crate::http::connections::ensure_file_limit;
use crate::http::serve::serve;
use crate::http::{router, AppState};
use crate::models::{
    duplicate_name, model_name, names, one_line, report, same_folder, Loader, MakeRunner, Model, Models, Refusals,
    Search, Skipped, Snapshot,
};
pub use crate::models::{warm_up, warm_up_within};
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
    let (budget, budget_source) = config.memory_budget();
    tracing::info!(budget_mib = budget >> 20, source = %budget_source, "memory budget");
    let state = AppState::with_models(load_models(&config).await?, options);
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
        let (state, within) = (state.clone(), config.model_deadlines().warm_up);
        tokio::spawn(async move {
            let warmed = warm_up_all(state.models(), within).await;
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

/// The bundles of `--bundle` (any that fails fails the start) and below `--models` (one that
/// fails is skipped with a warning), each model's runner in a slot of the one executor.
async fn load_models(config: &Config) -> Result<Models, String> {
    let refusals = Arc::new(Refusals::default());
    let bundles = find_bundles(config, &refusals).await?;
    let make_runner = ort_runners(config);
    let settings = config.model_settings();
    let (mut executor, mut models): (Option<BackendHandle>, Vec<Model>) = (None, Vec::new());
    for (bundle, required) in bundles {
        let dir = bundle.dir.clone();
        let (model_id, shown) = (one_line(&bundle.manifest.model_id), one_line(&dir.display().to_string()));
        tracing::info!(%model_id, dir = %shown, "bundle verified");
        let (make, for_runner, before) = (make_runner.clone(), bundle.clone(), Snapshot::of(&dir));
        let runner = tokio::task::spawn_blocking(move || make(&for_runner)).await.map_err(|e| e.to_string())?;
        let runner = match runner {
            Ok(runner) => runner,
            Err(e) if required => return Err(format!("bundle {}: {e}", dir.display())),
            Err(reason) => {
                refusals.remember(before, &reason);
                report(vec![Skipped::new(&dir, &reason)]);
                continue;
            }
        };
        let backend = match &executor {
            Some(executor) => executor.add_runner(runner),
            None => BackendHandle::spawn(runner, config.executor_options()).map_err(|e| e.to_string())?,
        };
        executor.get_or_insert_with(|| backend.clone());
        let model = Model::new(settings.pipeline(backend, bundle));
        if model.pipeline.default_sampling() != config.sampling {
            tracing::info!(model = %model.name, asked = %config.sampling,
                           "the bundle has no guided-sampling graphs: views are sampled in full");
        }
        models.push(model);
    }
    let executor = executor.ok_or("no model to serve: every bundle below --models was skipped")?;
    let loader = config.models.clone().map(|dir| Loader {
        dir,
        make_runner,
        settings,
        executor,
        warm_up: !config.skip_warmup,
        deadlines: config.model_deadlines(),
        refusals,
    });
    Models::new(models, config.default_model.as_deref(), loader)
}

/// The verified bundles to serve, each with whether it must load (`--bundle`) or may be skipped
/// (found below `--models`, by the rules of a reload: `models::Search`); two of one name fail
/// the start, naming both folders.
async fn find_bundles(config: &Config, refusals: &Arc<Refusals>) -> Result<Vec<(Bundle, bool)>, String> {
    let mut bundles = Vec::new();
    for dir in config.bundle_dirs() {
        names::check_folder(&dir).map_err(|e| format!("--bundle {dir:?}: {e}"))?;
        bundles.push((Bundle::load(&dir).map_err(|e| e.to_string())?, true));
    }
    let mut names: Vec<(String, std::path::PathBuf)> = Vec::new();
    let mut unique = Vec::new();
    for (bundle, required) in bundles {
        let name = model_name(&bundle.dir);
        match names.iter().find(|(n, _)| *n == name) {
            // The same folder twice: one model.
            Some((_, first)) if same_folder(first, &bundle.dir) => continue,
            Some((_, first)) => return Err(duplicate_name(&name, first, &bundle.dir)),
            None => names.push((name, bundle.dir.clone())),
        }
        unique.push((bundle, required));
    }
    if let Some(dir) = &config.models {
        // A --bundle inside --models is passed over there (one model); another of its name skipped.
        let served = names.iter().map(|(n, d)| (Arc::from(n.as_str()), d.clone())).collect();
        let timeout = config.model_deadlines().search;
        let found = Search { dir: dir.clone(), served, memory: None, refusals: refusals.clone(), timeout }.run().await;
        report(found.skipped);
        unique.extend(found.bundles.into_iter().map(|bundle| (bundle, false)));
    }
    Ok(unique)
}

/// Each model's runner: its graphs' ONNX Runtime sessions, on the configured device.
fn ort_runners(config: &Config) -> MakeRunner {
    let (ort, exec) = (config.ort_options(), config.exec_options());
    Arc::new(move |bundle: &Bundle| {
        OrtRunner::load_with(bundle, &ort, &exec).map(|runner| Box::new(runner) as Box<dyn GraphRunner>)
    })
}

/// Every model's warm-up render, in turn, each within its deadline.
async fn warm_up_all(models: &Models, within: Duration) -> Result<Duration, String> {
    let mut elapsed = Duration::ZERO;
    for model in models.all() {
        let took = warm_up_within(&model.pipeline, within)
            .await
            .map_err(|e| format!("model {}: warm-up render failed: {e}", model.name))?;
        elapsed += took;
    }
    Ok(elapsed)
}

/// Sets aside the memory held apart from requests: the process at rest after the warm-up (every
/// model's sessions, their weights) and one renderer run (runs take turns on the executor; the
/// renderers' shared arena may keep it between requests). The scene cache is not set aside: it
/// counts as it fills, and its idle scenes are evicted to admit a request (`backend/reclaim.rs`).
fn reserve_memory(state: &AppState) -> Result<MemoryBudget, String> {
    let at_rest = sysmem::resident().map_or(0, |r| r.now);
    let renderer = state.models().largest_renderer_run();
    state.pipeline().executor().reserve(at_rest + renderer)
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
