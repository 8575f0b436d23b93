//! Servers of several models over fake runners, and bundle folders written to disk (what
//! `--models DIR` finds and a reload loads).

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use super::{bundle, FakeRunner};
use crate::backend::{BackendHandle, ExecutorOptions, GraphRunner};
use crate::bundle::{sha256_file, Bundle, Manifest};
use crate::http::{AppState, ServiceOptions};
use crate::models::{Deadlines, Loader, Model, ModelSettings, Models};
use crate::pipeline::band::BandFill;
use crate::pipeline::chunks::ChunkPolicy;
use crate::pipeline::volume::SlabPolicy;
use crate::request::{Limits, Sampling};

/// A model of a fake server: its bundle and its runner.
pub struct FakeModel {
    pub bundle: Bundle,
    pub runner: FakeRunner,
}

impl FakeModel {
    /// A fake bundle in a folder named `name` (its model's name), rendering colours scaled by
    /// `tint`.
    pub fn new(name: &str, tint: f32) -> FakeModel {
        let bundle = named_bundle(name);
        let runner = FakeRunner { tint, ..FakeRunner::new(&bundle) };
        FakeModel { bundle, runner }
    }
}

/// The fake bundle of [`bundle`] in a folder named `name` (nothing on disk).
pub fn named_bundle(name: &str) -> Bundle {
    let mut bundle = bundle("scnerf", "near_far");
    bundle.dir = PathBuf::from("/nonexistent").join(name);
    bundle
}

/// A ready server of `models` (the first the default unless `default` names one), one executor
/// for all. With `reload_dir`, `POST /v1/models/reload` loads the bundle folders found there
/// over fake runners whose tint is their manifest's `provenance.tint` (see [`write_bundle`]) and
/// whose every graph run takes `provenance.delay_ms` (none when absent).
pub fn models_state(
    models: Vec<FakeModel>,
    default: Option<&str>,
    reload_dir: Option<&Path>,
    options: ServiceOptions,
) -> Result<AppState, String> {
    models_state_with(models, default, reload_dir, options, ExecutorOptions::with_capacity(8))
}

/// [`models_state`] with any executor settings (a memory budget).
pub fn models_state_with(
    models: Vec<FakeModel>,
    default: Option<&str>,
    reload_dir: Option<&Path>,
    options: ServiceOptions,
    executor_options: ExecutorOptions,
) -> Result<AppState, String> {
    build(models, default, reload_dir, options, executor_options, Deadlines::default())
}

/// A ready server of one model (`first`) whose reloads load the bundle folders of `dir` within
/// `deadlines`.
pub fn reload_state(dir: &Path, deadlines: Deadlines) -> AppState {
    let models = vec![FakeModel::new("first", 1.0)];
    build(models, None, Some(dir), Default::default(), ExecutorOptions::with_capacity(8), deadlines).expect("state")
}

fn build(
    models: Vec<FakeModel>,
    default: Option<&str>,
    reload_dir: Option<&Path>,
    options: ServiceOptions,
    executor_options: ExecutorOptions,
    deadlines: Deadlines,
) -> Result<AppState, String> {
    let settings = ModelSettings {
        chunking: ChunkPolicy { max_rays: 100, memory_budget_bytes: usize::MAX },
        slabs: SlabPolicy::default(),
        limits: Limits::default(),
        sampling: Sampling::Guided,
        band: BandFill::default(),
    };
    let mut served = Vec::new();
    let mut executor: Option<BackendHandle> = None;
    for FakeModel { bundle, runner } in models {
        let backend = match &executor {
            Some(executor) => executor.add_runner(Box::new(runner)),
            None => BackendHandle::spawn(Box::new(runner), executor_options.clone()).expect("spawn backend"),
        };
        executor.get_or_insert_with(|| backend.clone());
        served.push(Model::new(settings.pipeline(backend, bundle)));
    }
    let executor = executor.ok_or("no model")?;
    let loader = reload_dir.map(|dir| Loader {
        dir: dir.to_path_buf(),
        make_runner: Arc::new(|bundle: &Bundle| {
            let tint = bundle.manifest.provenance["tint"].as_f64().unwrap_or(1.0) as f32;
            let delay = Duration::from_millis(bundle.manifest.provenance["delay_ms"].as_u64().unwrap_or(0));
            Ok(Box::new(FakeRunner { tint, delay, ..FakeRunner::new(bundle) }) as Box<dyn GraphRunner>)
        }),
        settings,
        executor,
        warm_up: true,
        deadlines,
        refusals: Default::default(),
    });
    let models = Models::new(served, default, loader)?;
    let state = AppState::with_models(models, options);
    state.set_ready();
    Ok(state)
}

/// Writes a loadable bundle of [`bundle`]'s manifest into `dir`: stand-in graph files (their
/// sha256 in the manifest) and `provenance.tint` for [`models_state`]'s runners.
pub fn write_bundle(dir: &Path, tint: f32) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    let mut manifest: Manifest = bundle("scnerf", "near_far").manifest;
    for (name, entry) in manifest.graphs.iter_mut() {
        let path = dir.join(&entry.file);
        std::fs::write(&path, format!("stand-in for the {name} graph of tint {tint}"))?;
        entry.sha256 = sha256_file(&path)?;
    }
    manifest.provenance["tint"] = tint.into();
    manifest.model_id = manifest.expected_model_id();
    std::fs::write(dir.join("manifest.json"), serde_json::to_vec_pretty(&manifest).map_err(std::io::Error::other)?)
}
