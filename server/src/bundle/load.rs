//! Loading a bundle from its folder: the manifest, then every graph file's sha256.

use std::io::Read;
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

use super::graphs::{GraphKind, VolumeBuild, VolumeTail, GUIDED_GRAPHS};
use super::manifest::{BandRule, DepthNorm, GraphEntry, GuidedPolicy, Manifest, ModelConfig};
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
        let err = |message: String| BundleError { dir: dir.to_path_buf(), message };
        let manifest_path = dir.join("manifest.json");
        let text = std::fs::read_to_string(&manifest_path)
            .map_err(|e| err(format!("cannot read {}: {e}", manifest_path.display())))?;
        let manifest: Manifest =
            serde_json::from_str(&text).map_err(|e| err(format!("manifest.json is not a valid manifest: {e}")))?;
        let config = validate_manifest(&manifest).map_err(err)?;
        let bundle = Bundle { dir: dir.to_path_buf(), manifest, config };
        for kind in bundle.graphs() {
            verify_file(dir, kind, bundle.graph(kind)).map_err(err)?;
        }
        Ok(bundle)
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

/// Hashes the graph file and compares with the manifest.
pub(super) fn verify_file(dir: &Path, kind: GraphKind, entry: &GraphEntry) -> Result<(), String> {
    let rel = Path::new(&entry.file);
    if rel.is_absolute() || rel.components().any(|c| matches!(c, std::path::Component::ParentDir)) {
        return Err(format!("graphs.{kind}.file \"{}\" must be a path inside the bundle", entry.file));
    }
    let path = dir.join(rel);
    let actual = sha256_file(&path).map_err(|e| format!("graphs.{kind}: cannot read {}: {e}", path.display()))?;
    if !actual.eq_ignore_ascii_case(&entry.sha256) {
        return Err(format!("graphs.{kind}: sha256 of {} is {actual}, manifest says {}", entry.file, entry.sha256));
    }
    Ok(())
}

pub fn sha256_file(path: &Path) -> std::io::Result<String> {
    let mut file = std::fs::File::open(path)?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = file.read(&mut buf)?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
    }
    Ok(hex::encode(hasher.finalize()))
}
