//! The models a server serves: one per bundle (`--bundle`, repeatable, and every bundle folder
//! below `--models DIR`), each named by its bundle's folder. A request names its model
//! (`"model"`) or gets the default one (the first bundle, or `--default-model`).
//!
//! Each model is a `Pipeline` over its own runner (its graphs' ONNX Runtime sessions, loaded
//! once) in a slot of the one executor (`backend::runners`): models share the inference thread,
//! its queue, the memory budget and the scene cache, whose scenes each belong to one model.
//!
//! `scan.rs` finds the bundle folders of `--models DIR`; `find.rs` reads and verifies the new
//! ones off the async workers before a deadline, `skips.rs` says which it skipped and remembers
//! refusals; `load.rs` loads a verified bundle into a model (runner, pipeline, warm-up, the
//! memory it holds at rest) on a reload; `warm.rs` is the warm-up render every model gets
//! before it serves, within its deadline.

mod find;
mod load;
pub mod names;
pub mod scan;
mod skips;
mod warm;

use std::path::{Path, PathBuf};
use std::sync::{Arc, RwLock};

use serde::Serialize;

pub use find::{Candidates, Search};
pub use load::{Deadlines, Loader, MakeRunner, ModelSettings, Reloaded};
pub use skips::{one_line, report, Refusals, Skipped, Snapshot};
pub use warm::{warm_up, warm_up_within};

use crate::bundle::Bundle;
use crate::error::{clip_quoted, ApiError};
use crate::pipeline::Pipeline;
use crate::request::Sampling;

/// One served model: its name and the pipeline over its bundle and runner.
pub struct Model {
    pub name: Arc<str>,
    pub pipeline: Pipeline,
}

impl Model {
    /// A model named by its bundle's folder.
    pub fn new(pipeline: Pipeline) -> Model {
        Model { name: model_name(&pipeline.bundle().dir).into(), pipeline }
    }

    pub fn bundle(&self) -> &Bundle {
        self.pipeline.bundle()
    }
}

/// A bundle folder's name, in NFC (`names.rs`): its model's name (`/srv/models/lego-refined`
/// serves `lego-refined`).
/// The name as given, a link's own (a link in `--models DIR` names its model); resolved only
/// for a path without one (`.`, `..`).
pub fn model_name(dir: &Path) -> String {
    let resolved;
    let named = match dir.file_name() {
        Some(_) => dir,
        None => {
            resolved = std::fs::canonicalize(dir).unwrap_or_else(|_| dir.to_path_buf());
            &resolved
        }
    };
    let name = named.file_name().map_or_else(|| named.display().to_string(), |n| n.to_string_lossy().into_owned());
    names::normalized(&name)
}

/// The registry: the models in the order they were loaded, the default's name, and how to
/// load more (`--models DIR`).
pub struct Models {
    list: RwLock<Vec<Arc<Model>>>,
    default: Arc<Model>,
    loader: Option<Loader>,
    /// One reload at a time: two would load the same new bundle twice.
    reloading: tokio::sync::Mutex<()>,
}

impl Models {
    /// A registry of one model (tests, and servers of one bundle).
    pub fn single(pipeline: Pipeline) -> Models {
        Models::new(vec![Model::new(pipeline)], None, None).unwrap_or_else(|_| unreachable!("one model, no default"))
    }

    /// `models` in order; the default is `default` (which must be among them) or the first.
    /// Two models of one name fail, naming both bundles' folders.
    pub fn new(models: Vec<Model>, default: Option<&str>, loader: Option<Loader>) -> Result<Models, String> {
        for (i, m) in models.iter().enumerate() {
            if let Some(first) = models[..i].iter().find(|f| f.name == m.name) {
                return Err(duplicate_name(&m.name, &first.bundle().dir, &m.bundle().dir));
            }
        }
        let list: Vec<Arc<Model>> = models.into_iter().map(Arc::new).collect();
        let default = match default {
            Some(name) => list.iter().find(|m| &*m.name == name).ok_or_else(|| {
                let names: Vec<&str> = list.iter().map(|m| &*m.name).collect();
                format!("--default-model {name}: no such model (serving {})", names.join(", "))
            })?,
            None => list.first().ok_or("no model to serve: give --bundle or --models")?,
        }
        .clone();
        Ok(Models { list: RwLock::new(list), default, loader, reloading: Default::default() })
    }

    /// The model a request names (in NFC), or the default when it names none; 404
    /// `model_not_found` naming it otherwise, 422 for a name with a control character.
    pub fn get(&self, name: Option<&str>) -> Result<Arc<Model>, ApiError> {
        let Some(name) = name else { return Ok(self.default.clone()) };
        let name = names::requested(name)?;
        let found = self.all().into_iter().find(|m| *m.name == name);
        found.ok_or_else(|| ApiError::ModelNotFound { name: name.to_string() })
    }

    pub fn default_model(&self) -> &Arc<Model> {
        &self.default
    }

    /// Every model, in the order they were loaded.
    pub fn all(&self) -> Vec<Arc<Model>> {
        self.list.read().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// The models' names: the only values of the metrics' `model` label.
    pub fn names(&self) -> Vec<Arc<str>> {
        self.all().iter().map(|m| m.name.clone()).collect()
    }

    /// The working memory of the largest model's renderer run. Every model's runs take turns on
    /// the one executor (and share one ONNX Runtime arena, `backend::ort`), so it is set aside
    /// from the memory budget once, with the process at rest, not counted per request.
    pub fn largest_renderer_run(&self) -> u64 {
        self.all().iter().map(|m| m.pipeline.renderer_run_bytes()).max().unwrap_or(0)
    }

    /// What `GET /v1/models` says of each model.
    pub fn describe(&self) -> Vec<ModelInfo> {
        self.all().iter().map(|m| ModelInfo::of(m, m.name == self.default.name)).collect()
    }

    /// Rescans `--models DIR` and loads the bundle folders not served yet (none without DIR).
    pub async fn reload(&self) -> Reloaded {
        let _one = self.reloading.lock().await;
        let Some(loader) = &self.loader else { return Reloaded::default() };
        let served: Vec<(Arc<str>, PathBuf)> =
            self.all().iter().map(|m| (m.name.clone(), m.bundle().dir.clone())).collect();
        let mut reloaded = loader.load_new(&served, self.largest_renderer_run()).await;
        let mut list = self.list.write().unwrap_or_else(|p| p.into_inner());
        for model in reloaded.models.drain(..) {
            reloaded.loaded.push(ModelInfo::of(&model, false));
            list.push(Arc::new(model));
        }
        reloaded
    }
}

/// Whether two paths name one folder (a link and its target, `a/../b` and `b`): given twice, it
/// serves one model.
pub fn same_folder(a: &Path, b: &Path) -> bool {
    let canonical = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
    canonical(a) == canonical(b)
}

/// Two bundle folders of one name: which model a request meant would be a guess.
pub fn duplicate_name(name: &str, first: &Path, second: &Path) -> String {
    format!(
        "two bundles are named \"{name}\": {} and {} (a model's name is its bundle's folder name; rename one)",
        first.display(),
        second.display()
    )
}

/// A served model as `GET /v1/models` lists it: its name (what requests send as `"model"`), its
/// bundle, and what its manifest says that a user chooses by.
#[derive(Debug, Clone, Serialize, serde::Deserialize, utoipa::ToSchema)]
pub struct ModelInfo {
    /// The name requests use (`"model"`): the bundle's folder name.
    pub name: String,
    /// The bundle's folder on the server.
    pub path: String,
    /// Requests that name no model render with this one.
    pub default: bool,
    /// The manifest's model id (content-addressed: changes with any graph).
    pub model_id: String,
    /// mvsnerf, scnerf, scnerf-geometry or scnerf-appearance.
    pub variant: String,
    /// Where the weights came from: `provenance.source_kind` (or `derived_from`'s), else the
    /// source checkpoint's name.
    pub source: Option<String>,
    /// Whether the bundle was refined on a capture (`scnerf-export refine`).
    pub refined: bool,
    /// The model id of the bundle it was refined from.
    pub base_model_id: Option<String>,
    /// Source views per render.
    pub views: usize,
    /// Depth planes of the encoding volume.
    pub depth_planes: usize,
    /// Samples per ray of full sampling.
    pub samples: usize,
    /// How its views can be sampled, and the default.
    pub sampling_modes: Vec<Sampling>,
    pub default_sampling: Sampling,
}

impl ModelInfo {
    fn of(model: &Model, default: bool) -> ModelInfo {
        let bundle = model.bundle();
        let provenance = &bundle.manifest.provenance;
        // Free text of the manifest, echoed: clipped as any text the server repeats is.
        let text = |v: &serde_json::Value| v.as_str().map(clip_quoted);
        let source = text(&provenance["source_kind"])
            .or_else(|| text(&provenance["derived_from"]["source_kind"]))
            .or_else(|| text(&provenance["source_checkpoint"]));
        let refinement = &provenance["refinement"];
        ModelInfo {
            name: model.name.to_string(),
            path: bundle.dir.display().to_string(),
            default,
            model_id: bundle.manifest.model_id.clone(),
            variant: bundle.manifest.variant.clone(),
            source,
            refined: refinement.is_object(),
            base_model_id: text(&refinement["base_model_id"]),
            views: bundle.config.views,
            depth_planes: bundle.config.depth_planes,
            samples: bundle.config.samples,
            sampling_modes: model.pipeline.samplings(),
            default_sampling: model.pipeline.default_sampling(),
        }
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::model_name;
    use crate::testing::{models_state, FakeModel};

    #[test]
    fn a_model_is_named_by_its_folder_or_its_link_never_by_where_a_link_leads() {
        assert_eq!(model_name(Path::new("/srv/models/lego-refined/")), "lego-refined");
        let dir = std::env::temp_dir().join(format!("scnerf-names-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("target")).unwrap();
        std::os::unix::fs::symlink(dir.join("target"), dir.join("link")).unwrap();
        assert_eq!(model_name(&dir.join("link")), "link");
        assert_eq!(model_name(&dir.join("target/.")), "target");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[tokio::test]
    async fn one_renderer_run_is_set_aside_however_many_models() {
        let one = models_state(vec![FakeModel::new("a", 1.0)], None, None, Default::default()).unwrap();
        let run = one.pipeline().renderer_run_bytes();
        assert!(run > 0);
        assert_eq!(one.models().largest_renderer_run(), run);
        let models = vec![FakeModel::new("a", 1.0), FakeModel::new("b", 1.0), FakeModel::new("c", 1.0)];
        let three = models_state(models, None, None, Default::default()).unwrap();
        assert_eq!(three.models().largest_renderer_run(), run, "the models' renderer runs take turns");
    }
}
