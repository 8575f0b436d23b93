//! A bundle loaded into a served model: verified, its runner (its graphs' sessions) in a new
//! slot of the executor, warmed up, and the memory it holds at rest set aside from the budget.
//! A reload rescans `--models DIR` and loads the bundle folders not served yet; one that fails
//! any step is skipped with the reason and takes nothing down.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::Serialize;

use super::{duplicate_name, model_name, same_folder, scan, warm_up, Model, ModelInfo};
use crate::backend::{BackendHandle, GraphRunner};
use crate::bundle::Bundle;
use crate::pipeline::band::BandFill;
use crate::pipeline::chunks::ChunkPolicy;
use crate::pipeline::volume::SlabPolicy;
use crate::pipeline::Pipeline;
use crate::request::{Limits, Sampling};
use crate::sysmem;

/// Makes a bundle's runner: ONNX Runtime's sessions in the server, a fake in tests.
pub type MakeRunner = Arc<dyn Fn(&Bundle) -> Result<Box<dyn GraphRunner>, String> + Send + Sync>;

/// What every model's pipeline is built with (the server's flags).
#[derive(Clone)]
pub struct ModelSettings {
    pub chunking: ChunkPolicy,
    pub slabs: SlabPolicy,
    pub limits: Limits,
    /// `--sampling`: each model's default where its bundle can.
    pub sampling: Sampling,
    /// `--band`.
    pub band: BandFill,
}

impl ModelSettings {
    pub fn pipeline(&self, backend: BackendHandle, bundle: Bundle) -> Pipeline {
        Pipeline::new(backend, bundle, self.chunking, self.slabs, self.limits.clone())
            .with_default_sampling(self.sampling)
            .with_band(self.band)
    }
}

/// How a reload loads the bundle folders it finds.
pub struct Loader {
    /// `--models DIR`.
    pub dir: PathBuf,
    pub make_runner: MakeRunner,
    pub settings: ModelSettings,
    /// The executor (any model's handle): new models get a slot on it.
    pub executor: BackendHandle,
    /// Whether a new model renders a warm-up view before it serves (`--skip-warmup` off).
    pub warm_up: bool,
}

/// The answer of a reload: the models it loaded and the bundle folders it skipped, with why.
#[derive(Default, Serialize, utoipa::ToSchema)]
pub struct Reloaded {
    /// The folder rescanned (`--models`); null when the server has none (nothing to rescan).
    pub dir: Option<String>,
    pub loaded: Vec<ModelInfo>,
    pub skipped: Vec<Skipped>,
    /// The models loaded, until the registry takes them.
    #[serde(skip)]
    pub(super) models: Vec<Model>,
}

/// A bundle folder a reload did not load.
#[derive(Debug, Clone, Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct Skipped {
    /// The model's name it would have had (its folder's name).
    pub name: String,
    pub path: String,
    /// What is wrong with it (the manifest, a graph's hash or signature, its name, memory).
    pub reason: String,
}

impl Reloaded {
    fn skip(&mut self, dir: &Path, reason: String) {
        tracing::warn!(path = %dir.display(), %reason, "bundle skipped");
        self.skipped.push(Skipped { name: model_name(dir), path: dir.display().to_string(), reason });
    }
}

impl Loader {
    /// Loads the bundle folders below DIR whose names no model of `served` (name, folder) has;
    /// a folder of a served name elsewhere is skipped (two models of one name). `renderer`: the
    /// renderer run set aside so far (`Models::largest_renderer_run`).
    pub(super) async fn load_new(&self, served: &[(Arc<str>, PathBuf)], mut renderer: u64) -> Reloaded {
        let (dirs, unreadable) = scan::bundle_dirs(&self.dir);
        let mut out = Reloaded { dir: Some(self.dir.display().to_string()), ..Reloaded::default() };
        for (dir, reason) in unreadable {
            out.skip(&dir, reason);
        }
        for dir in dirs {
            let name = model_name(&dir);
            let loaded = out.models.iter().map(|m| (&*m.name, m.bundle().dir.as_path()));
            let taken = served.iter().map(|(n, d)| (&**n, d.as_path())).chain(loaded).find(|(n, _)| *n == name);
            match taken {
                Some((_, first)) if same_folder(first, &dir) => {}
                Some((_, first)) => out.skip(&dir, duplicate_name(&name, first, &dir)),
                None => match self.load(&dir, &mut renderer).await {
                    Ok(model) => {
                        tracing::info!(model = %model.name, path = %dir.display(), "model loaded");
                        out.models.push(model);
                    }
                    Err(reason) => out.skip(&dir, reason),
                },
            }
        }
        out
    }

    /// Loads one bundle folder into a model, or says why it cannot serve; `renderer` grows to its
    /// renderer run's when larger.
    async fn load(&self, dir: &Path, renderer: &mut u64) -> Result<Model, String> {
        let bundle = Bundle::load(dir).map_err(|e| e.message)?;
        self.check_room(&bundle)?;
        let before = resident();
        let make = self.make_runner.clone();
        let for_runner = bundle.clone();
        let runner = tokio::task::spawn_blocking(move || make(&for_runner)).await.map_err(|e| e.to_string())??;
        let backend = self.executor.add_runner(runner);
        let model = Model::new(self.settings.pipeline(backend.clone(), bundle));
        match self.settle(&model, before, renderer).await {
            Ok(()) => Ok(model),
            Err(e) => {
                backend.remove_runner();
                Err(e)
            }
        }
    }

    /// The new model's warm-up, then what it added to the process at rest (its sessions, their
    /// weights) and what its renderer run adds to the one set aside (`renderer`) from the memory
    /// budget, as the models' at start were.
    async fn settle(&self, model: &Model, before: u64, renderer: &mut u64) -> Result<(), String> {
        if self.warm_up {
            warm_up(&model.pipeline).await.map_err(|e| format!("warm-up render failed: {e}"))?;
        }
        let grown = resident().saturating_sub(before);
        let own = model.pipeline.renderer_run_bytes();
        let reserved = self.executor.stats().memory.reserved;
        self.executor.reserve(reserved + grown + own.saturating_sub(*renderer))?;
        *renderer = (*renderer).max(own);
        Ok(())
    }

    /// Refuses a bundle whose graphs alone would not fit the memory left beside what is set
    /// aside now (sessions hold at least their weights), before any session is made.
    fn check_room(&self, bundle: &Bundle) -> Result<(), String> {
        let graphs: u64 = bundle
            .graphs()
            .into_iter()
            .filter_map(|k| std::fs::metadata(bundle.graph_path(k)).ok())
            .map(|m| m.len())
            .sum();
        let memory = self.executor.stats().memory;
        match memory.reserved.saturating_add(graphs) < memory.total {
            true => Ok(()),
            false => Err(format!(
                "not enough memory: its graphs ({} MiB) and the {} MiB held at rest exceed the budget ({} MiB)",
                graphs >> 20,
                memory.reserved >> 20,
                memory.total >> 20
            )),
        }
    }
}

fn resident() -> u64 {
    sysmem::resident().map_or(0, |r| r.now)
}
