//! Loading a bundle from its folder: the manifest, then every graph file's sha256 (`files`:
//! which files are read, and how).

use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

use super::files::{open_in, BundleFile, Stop, MAX_GRAPH_BYTES, MAX_MANIFEST_BYTES};
use super::graphs::{GraphKind, VolumeBuild, VolumeTail, GUIDED_GRAPHS};
use super::manifest::{BandRule, DepthNorm, GraphEntry, GuidedPolicy, Manifest, ModelConfig};
use super::onnx_data::refuse_external_data;
use super::validate::validate_manifest;

#[derive(Debug, thiserror::Error)]
#[error("bundle {dir}: {message}")]
pub struct BundleError {
    pub dir: PathBuf,
    pub message: String,
}

/// A verified bundle.
#[derive(Debug, Clone)]
pub struct Bundle {
    pub dir: PathBuf,
    pub manifest: Manifest,
    pub config: ModelConfig,
}

impl Bundle {
    /// Loads `dir/manifest.json` and verifies the bundle (hashes included).
    pub fn load(dir: &Path) -> Result<Bundle, BundleError> {
        Self::load_within(dir, &|| Ok(()))
    }

    /// [`Bundle::load`], reading no further once `stop` says so.
    pub fn load_within(dir: &Path, stop: Stop) -> Result<Bundle, BundleError> {
        let bundle = Self::read(dir)?;
        bundle.verify(stop).map_err(|message| BundleError { dir: dir.to_path_buf(), message })?;
        Ok(bundle)
    }

    /// Reads `dir/manifest.json` (at most [`MAX_MANIFEST_BYTES`]) and checks it, and that every
    /// graph it names is a regular file inside the bundle of at most [`MAX_GRAPH_BYTES`]; no
    /// graph is read (see [`Bundle::verify`]).
    pub fn read(dir: &Path) -> Result<Bundle, BundleError> {
        let err = |message: String| BundleError { dir: dir.to_path_buf(), message };
        let manifest = open_in(dir, "manifest.json", MAX_MANIFEST_BYTES, "the manifest")
            .and_then(|file| file.read_all(&|| Ok(())))
            .map_err(err)?;
        let manifest: Manifest = serde_json::from_slice(&manifest)
            .map_err(|e| err(format!("manifest.json is not a valid manifest: {e}")))?;
        let config = validate_manifest(&manifest).map_err(err)?;
        let bundle = Bundle { dir: dir.to_path_buf(), manifest, config };
        for kind in bundle.graphs() {
            bundle.open_graph(kind).map_err(err)?;
        }
        Ok(bundle)
    }

    /// Hashes every graph file and compares with the manifest.
    pub fn verify(&self, stop: Stop) -> Result<(), String> {
        self.graphs().into_iter().try_for_each(|kind| verify_file(&self.dir, kind, self.graph(kind), stop))
    }

    /// The graph files' sizes together: what their sessions hold at least.
    pub fn graph_bytes(&self) -> u64 {
        self.graphs().into_iter().filter_map(|kind| self.open_graph(kind).ok()).map(|f| f.len).sum()
    }

    /// A graph file's bytes, read once: checked against the manifest's sha256 and holding its
    /// weights (no external data), what ONNX Runtime then loads, so that the session runs the
    /// bytes that were verified and maps no file.
    pub fn read_graph(&self, kind: GraphKind) -> Result<Vec<u8>, String> {
        let entry = self.graph(kind);
        let bytes = self.open_graph(kind)?.read_all(&|| Ok(()))?;
        let actual = hex::encode(Sha256::digest(&bytes));
        same_digest(kind, entry, &actual)?;
        refuse_external_data(&bytes).map_err(|e| format!("graphs.{kind}: {e}"))?;
        Ok(bytes)
    }

    fn open_graph(&self, kind: GraphKind) -> Result<BundleFile, String> {
        open_in(&self.dir, &self.graph(kind).file, MAX_GRAPH_BYTES, &format!("graphs.{kind}.file"))
    }

    /// The files a load of `dir` reads: its manifest, and the graph files the manifest names as
    /// far as it can be read.
    pub fn files_named(dir: &Path) -> Vec<PathBuf> {
        let text = open_in(dir, "manifest.json", MAX_MANIFEST_BYTES, "manifest.json")
            .and_then(|file| file.read_all(&|| Ok(())))
            .unwrap_or_default();
        let manifest: serde_json::Value = serde_json::from_slice(&text).unwrap_or_default();
        let graphs = manifest["graphs"].as_object().into_iter().flatten().filter_map(|(_, g)| g["file"].as_str());
        std::iter::once(dir.join("manifest.json")).chain(graphs.map(|file| dir.join(file))).collect()
    }

    /// How the volume is built (validate_manifest checked that the graphs are one of the ways).
    pub fn volume_build(&self) -> VolumeBuild {
        VolumeBuild::of(&self.manifest.graphs).unwrap_or(VolumeBuild::Whole)
    }

    /// Who computes G2's last step (validate_manifest checked `volume_net`'s outputs).
    pub fn volume_tail(&self) -> VolumeTail {
        match self.manifest.graphs.get(GraphKind::VolumeNet.name()) {
            Some(entry) => VolumeTail::of(&entry.outputs).unwrap_or(VolumeTail::Graph),
            None => VolumeTail::Graph,
        }
    }

    /// The bundle's graphs in pipeline order.
    pub fn graphs(&self) -> Vec<GraphKind> {
        let mut graphs = self.volume_build().bundle_graphs();
        if self.manifest.guided.is_some() {
            graphs.extend(GUIDED_GRAPHS);
        }
        graphs
    }

    /// Guided sampling's policy when the bundle can render that way: its graphs are there, and the
    /// rectifiers' depth range is the request's (a depth range from the whole image would need
    /// the whole image first).
    pub fn guided(&self) -> Option<&GuidedPolicy> {
        self.manifest
            .guided
            .as_ref()
            .filter(|_| !self.renderer_takes("depth_range") || self.config.depth_norm == DepthNorm::NearFar)
    }

    /// Which views' bands the band stage recolours.
    pub fn band_rule(&self) -> BandRule {
        self.manifest.band.map(|b| b.fill).unwrap_or_default()
    }

    /// A graph of the bundle (one of `graphs()`).
    pub fn graph(&self, kind: GraphKind) -> &GraphEntry {
        &self.manifest.graphs[kind.name()]
    }

    pub fn graph_path(&self, kind: GraphKind) -> PathBuf {
        self.dir.join(&self.graph(kind).file)
    }

    /// Whether the renderer graph declares an input (optional inputs depend on the variant).
    pub fn renderer_takes(&self, name: &str) -> bool {
        self.graph(GraphKind::Renderer).inputs.iter().any(|t| t.name == name)
    }
}

/// Hashes the graph file and compares with the manifest. The digest is quoted only for a file
/// inside the bundle (`open_in` refuses any other before reading it).
pub(super) fn verify_file(dir: &Path, kind: GraphKind, entry: &GraphEntry, stop: Stop) -> Result<(), String> {
    let file = open_in(dir, &entry.file, MAX_GRAPH_BYTES, &format!("graphs.{kind}.file"))?;
    let actual = file.sha256(stop).map_err(|e| format!("graphs.{kind}: {e}"))?;
    same_digest(kind, entry, &actual)
}

fn same_digest(kind: GraphKind, entry: &GraphEntry, actual: &str) -> Result<(), String> {
    match actual.eq_ignore_ascii_case(&entry.sha256) {
        true => Ok(()),
        false => Err(format!("graphs.{kind}: sha256 of {} is {actual}, manifest says {}", entry.file, entry.sha256)),
    }
}

/// A file's sha256 (tests write bundles with it).
pub fn sha256_file(path: &Path) -> std::io::Result<String> {
    Ok(hex::encode(Sha256::digest(std::fs::read(path)?)))
}
