//! A bundle loaded into a served model: verified, its runner (its graphs' sessions) in a new
//! slot of the executor, warmed up, and the memory it holds at rest set aside from the budget.
//! A reload rescans `--models DIR` (`find.rs`) and loads the bundle folders not served yet; one
//! that fails any step is skipped with the reason (`skips.rs`) and takes nothing down.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use serde::Serialize;

use super::find::{room_for, Search};
use super::skips::{one_line, report, Refusals, Skipped, Snapshot};
use super::warm::{try_warm_up, WarmUpError};
use super::{Model, ModelInfo};
use crate::backend::{BackendHandle, GraphRunner};
use crate::bundle::Bundle;
use crate::error::clip_quoted;
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
    pub deadlines: Deadlines,
    /// Folders refused for what they hold, not read again until that changes (kept from the
    /// start-up scan on).
    pub refusals: Arc<Refusals>,
}

/// How long the models folder's search (the scan and the new bundles' hashes) and a new model's
/// warm-up may take (`--models-timeout-secs`, `--warmup-timeout-secs`).
#[derive(Debug, Clone, Copy)]
pub struct Deadlines {
    pub search: Duration,
    pub warm_up: Duration,
}

impl Default for Deadlines {
    fn default() -> Deadlines {
        Deadlines { search: Duration::from_secs(120), warm_up: Duration::from_secs(30) }
    }
}

/// The answer of a reload: the models it loaded and the bundle folders it skipped, with why.
#[derive(Default, Serialize, utoipa::ToSchema)]
pub struct Reloaded {
    /// The folder rescanned (`--models`); null when the server has none (nothing to rescan).
    pub dir: Option<String>,
    pub loaded: Vec<ModelInfo>,
    /// The first 64 folders skipped.
    pub skipped: Vec<Skipped>,
    /// How many more folders were skipped than `skipped` lists.
    pub skipped_more: usize,
    /// The models loaded, until the registry takes them.
    #[serde(skip)]
    pub(super) models: Vec<Model>,
}

impl Loader {
    /// Loads the bundle folders below DIR whose names no model of `served` (name, folder) has;
    /// a folder of a served name elsewhere is skipped (two models of one name). `renderer`: the
    /// renderer run set aside so far (`Models::largest_renderer_run`).
    pub(super) async fn load_new(&self, served: &[(Arc<str>, PathBuf)], mut renderer: u64) -> Reloaded {
        let found = Search {
            dir: self.dir.clone(),
            served: served.to_vec(),
            memory: Some(self.executor.stats().memory),
            refusals: self.refusals.clone(),
            timeout: self.deadlines.search,
        }
        .run()
        .await;
        let mut out = Reloaded { dir: Some(clip_quoted(&self.dir.display().to_string())), ..Reloaded::default() };
        let mut skipped = found.skipped;
        for bundle in found.bundles {
            let dir = bundle.dir.clone();
            match self.load(bundle, &mut renderer).await {
                Ok(model) => {
                    let (name, path) = (one_line(&model.name), one_line(&dir.display().to_string()));
                    tracing::info!(model = %name, path = %path, "model loaded");
                    out.models.push(model);
                }
                Err(reason) => skipped.push(Skipped::new(&dir, &reason)),
            }
        }
        (out.skipped, out.skipped_more) = report(skipped);
        out
    }

    /// Makes a verified bundle's model, or says why it cannot serve; `renderer` grows to its
    /// renderer run's when larger. Whatever fails on the way, or the reload being dropped,
    /// empties its slot: its sessions go.
    async fn load(&self, bundle: Bundle, renderer: &mut u64) -> Result<Model, String> {
        let dir = bundle.dir.clone();
        let graphs = bundle.graph_bytes();
        room_for(graphs, &self.executor.stats().memory)?;
        // Its sessions hold at least its graphs: held against the budget as a request's memory
        // is, until what the model added at rest is set aside (`settle`).
        let _loading = self.executor.lease(graphs).map_err(|e| format!("not enough memory now to load it: {e}"))?;
        let before = Snapshot::of(&dir);
        let refused = |reason: String| {
            self.refusals.remember(before.clone(), &reason);
            reason
        };
        let before = resident();
        let make = self.make_runner.clone();
        let for_runner = bundle.clone();
        let runner = tokio::task::spawn_blocking(move || make(&for_runner)).await.map_err(|e| e.to_string())?;
        let slot = Slot { backend: self.executor.add_runner(runner.map_err(refused)?), kept: false };
        let model = Model::new(self.settings.pipeline(slot.backend.clone(), bundle));
        if self.warm_up {
            match try_warm_up(&model.pipeline, self.deadlines.warm_up).await {
                Ok(_) => {}
                Err(busy @ WarmUpError::Busy(_)) => return Err(format!("warm-up render: {busy}")),
                Err(failed) => return Err(refused(format!("warm-up render failed: {failed}"))),
            }
        }
        self.settle(&model, before, renderer)?;
        slot.keep();
        Ok(model)
    }

    /// What the new model added to the process at rest (its sessions, their weights, measured
    /// after its warm-up) and what its renderer run adds to the one set aside (`renderer`) from
    /// the memory budget, as the models' at start were.
    fn settle(&self, model: &Model, before: u64, renderer: &mut u64) -> Result<(), String> {
        let grown = resident().saturating_sub(before);
        let own = model.pipeline.renderer_run_bytes();
        let reserved = self.executor.stats().memory.reserved;
        self.executor.reserve(reserved + grown + own.saturating_sub(*renderer))?;
        *renderer = (*renderer).max(own);
        Ok(())
    }
}

/// A new model's slot on the executor, emptied when dropped unless kept: a load that fails, or
/// a reload dropped mid warm-up, leaves no sessions behind.
struct Slot {
    backend: BackendHandle,
    kept: bool,
}

impl Slot {
    fn keep(mut self) {
        self.kept = true;
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        if !self.kept {
            self.backend.remove_runner();
        }
    }
}

fn resident() -> u64 {
    sysmem::resident().map_or(0, |r| r.now)
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicBool, Ordering};

    use super::*;
    use crate::backend::{BackendError, ExecutorOptions, GraphRunner, NamedTensors, Work};
    use crate::bundle::GraphKind;

    /// Sets its flag when dropped (its sessions' memory would go back then).
    struct Flagged(Arc<AtomicBool>);

    impl GraphRunner for Flagged {
        fn run(&mut self, _graph: GraphKind, _inputs: &NamedTensors) -> Result<NamedTensors, BackendError> {
            Ok(vec![])
        }
    }

    impl Drop for Flagged {
        fn drop(&mut self) {
            self.0.store(true, Ordering::SeqCst);
        }
    }

    /// Runs a job on `handle`: the executor applies the slot changes before it.
    async fn one_run(handle: &BackendHandle) {
        let far = std::time::Instant::now() + Duration::from_secs(60);
        let ticket = handle.admit(far, Work::default(), 0).unwrap();
        let _ = ticket.run(GraphKind::Encoder, 0.0, vec![]).await;
    }

    #[tokio::test]
    async fn a_slot_not_kept_gives_its_runner_back_and_a_kept_one_stays() {
        let executor =
            BackendHandle::spawn(Box::new(Flagged(Arc::default())), ExecutorOptions::with_capacity(4)).unwrap();
        let (dropped, stays) = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicBool::new(false)));
        let abandoned = Slot { backend: executor.add_runner(Box::new(Flagged(dropped.clone()))), kept: false };
        let kept = Slot { backend: executor.add_runner(Box::new(Flagged(stays.clone()))), kept: false };
        drop(abandoned);
        kept.keep();
        one_run(&executor).await;
        assert!(dropped.load(Ordering::SeqCst), "the abandoned model's runner is dropped");
        assert!(!stays.load(Ordering::SeqCst), "the kept model's runner stays");
    }
}
