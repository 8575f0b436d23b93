//! Model bundle: `manifest.json` + its ONNX graphs (docs/bundle.md).
//!
//! Loading checks everything that can be checked before ONNX Runtime sees the files: format
//! version, variant, hyper-parameters, every file's sha256, and each graph's declared inputs and
//! outputs against what the pipeline feeds and reads. `check_signature` later compares the
//! declarations with what ONNX Runtime reports for the loaded graph. Every refusal names the
//! mismatch.

use std::collections::BTreeMap;
use std::fmt;
use std::io::Read;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::pipeline::guided::GuidedPolicy;

pub const FORMAT_VERSION: u32 = 1;
pub const VARIANTS: [&str; 4] = ["mvsnerf", "scnerf", "scnerf-geometry", "scnerf-appearance"];

#[derive(Debug, thiserror::Error)]
#[error("bundle {dir}: {message}")]
pub struct BundleError {
    pub dir: PathBuf,
    pub message: String,
}

/// The sub-graphs, in pipeline order. A bundle has the encoder, the renderer, and the graphs of
/// one way to build the encoding volume (`VolumeBuild`): `volume` (the cost volume and G2 in one
/// run), or `cost_slab` (the cost volume of a slab of depth planes and G2's first convolution
/// over it) and `volume_net` (the rest of G2, over the whole volume), or `cost_conv` (G2's first
/// convolution over a slab of the cost volume that the server computes) and `volume_net`. A bundle
/// that can render by guided sampling (`pipeline::guided`) also has `renderer_guide` and
/// `renderer_fine`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum GraphKind {
    Encoder,
    Volume,
    CostSlab,
    CostConv,
    VolumeNet,
    Renderer,
    RendererGuide,
    RendererFine,
}

/// Guided sampling's graphs: the renderer with each ray's weights and rectifier heads, and the
/// renderer at K given samples per ray.
pub const GUIDED_GRAPHS: [GraphKind; 2] = [GraphKind::RendererGuide, GraphKind::RendererFine];

impl GraphKind {
    pub const ALL: [GraphKind; 8] = [
        GraphKind::Encoder,
        GraphKind::Volume,
        GraphKind::CostSlab,
        GraphKind::CostConv,
        GraphKind::VolumeNet,
        GraphKind::Renderer,
        GraphKind::RendererGuide,
        GraphKind::RendererFine,
    ];

    /// Position in `ALL` (pipeline order): indexes per-graph arrays.
    pub fn index(self) -> usize {
        self as usize
    }

    pub fn name(self) -> &'static str {
        match self {
            GraphKind::Encoder => "encoder",
            GraphKind::Volume => "volume",
            GraphKind::CostSlab => "cost_slab",
            GraphKind::CostConv => "cost_conv",
            GraphKind::VolumeNet => "volume_net",
            GraphKind::Renderer => "renderer",
            GraphKind::RendererGuide => "renderer_guide",
            GraphKind::RendererFine => "renderer_fine",
        }
    }
}

/// How a bundle builds the encoding volume.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VolumeBuild {
    /// `volume.onnx`: the whole cost volume at once (`scnerf-export export --volume whole`).
    Whole,
    /// `cost_slab.onnx` over slabs of depth planes, then `volume_net.onnx`.
    Slabs,
    /// The server's plane sweep (`pipeline::sweep`) and `cost_conv.onnx` over slabs of depth
    /// planes, then `volume_net.onnx`.
    Sweep,
}

impl VolumeBuild {
    pub fn graphs(self) -> &'static [GraphKind] {
        match self {
            VolumeBuild::Whole => &[GraphKind::Volume],
            VolumeBuild::Slabs => &[GraphKind::CostSlab, GraphKind::VolumeNet],
            VolumeBuild::Sweep => &[GraphKind::CostConv, GraphKind::VolumeNet],
        }
    }

    /// The way the graphs a manifest names build the volume.
    fn of(graphs: &BTreeMap<String, GraphEntry>) -> Result<VolumeBuild, String> {
        let has = |kind: GraphKind| graphs.contains_key(kind.name());
        let volume = [GraphKind::Volume, GraphKind::CostSlab, GraphKind::CostConv, GraphKind::VolumeNet].map(has);
        match volume {
            [true, false, false, false] => Ok(VolumeBuild::Whole),
            [false, true, false, true] => Ok(VolumeBuild::Slabs),
            [false, false, true, true] => Ok(VolumeBuild::Sweep),
            [false, false, false, false] => {
                Err("graphs.volume: missing (or graphs.cost_slab and graphs.volume_net, or graphs.cost_conv and \
                 graphs.volume_net)"
                    .into())
            }
            _ => Err("graphs: one of volume, cost_slab and volume_net, or cost_conv and volume_net, not a mix".into()),
        }
    }

    /// The bundle's graphs in pipeline order.
    pub fn bundle_graphs(self) -> Vec<GraphKind> {
        [GraphKind::Encoder].iter().chain(self.graphs()).chain(&[GraphKind::Renderer]).copied().collect()
    }
}

/// Who computes G2's last step, `σ(N0(conv0)) + σ(N11(interleave(phases)))` (docs/bundle.md,
/// `volume_net.onnx`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VolumeTail {
    /// The graph: `volume_net.onnx` outputs `volume` (and `volume.onnx` always does).
    Graph,
    /// The server, from `volume_net.onnx`'s `phases`, `skip_affine` and `phases_affine`, in one
    /// pass over the volume (`pipeline::volume_tail`).
    Server,
}

impl VolumeTail {
    const PARTS: [&str; 3] = ["phases", "skip_affine", "phases_affine"];

    /// The tail of a `volume_net.onnx` that declares `outputs`: `volume`, or the three parts.
    fn of(outputs: &[TensorSpec]) -> Result<VolumeTail, String> {
        let has = |name: &str| outputs.iter().any(|t| t.name == name);
        match (has("volume"), Self::PARTS.map(has)) {
            (true, [false, false, false]) => Ok(VolumeTail::Graph),
            (false, [true, true, true]) => Ok(VolumeTail::Server),
            _ => {
                Err("graphs.volume_net.outputs: \"volume\", or \"phases\", \"skip_affine\" and \"phases_affine\""
                    .into())
            }
        }
    }
}

impl fmt::Display for GraphKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// One axis of a declared shape: a fixed size or a named dynamic axis ("R", "H", "W", ...).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Dim {
    Fixed(i64),
    Named(String),
}

impl fmt::Display for Dim {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Dim::Fixed(n) => write!(f, "{n}"),
            Dim::Named(s) => write!(f, "\"{s}\""),
        }
    }
}

fn fmt_shape(shape: &[Dim]) -> String {
    let items: Vec<String> = shape.iter().map(Dim::to_string).collect();
    format!("[{}]", items.join(", "))
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct TensorSpec {
    pub name: String,
    pub shape: Vec<Dim>,
    pub dtype: String,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct GraphEntry {
    pub file: String,
    pub sha256: String,
    pub inputs: Vec<TensorSpec>,
    pub outputs: Vec<TensorSpec>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DepthNorm {
    /// Rectification queries normalise depth by the request's [near, far].
    NearFar,
    /// ... by the min/max of the whole rendered depth image (two passes).
    ImageMinmax,
}

/// The hyper-parameters the server needs; the manifest's `config` may hold more (served as is).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModelConfig {
    pub views: usize,
    pub feature_channels: usize,
    pub volume_channels: usize,
    pub depth_planes: usize,
    pub samples: usize,
    pub pad: usize,
    pub image_multiple: usize,
    pub depth_norm: DepthNorm,
    /// Attention heads, their size and the trunk's width: the shape of a rectifier's heads
    /// (guided sampling's graphs pass them between rays); absent in configs that never need them.
    #[serde(default)]
    pub heads: usize,
    #[serde(default)]
    pub head_dim: usize,
    #[serde(default)]
    pub width: usize,
    /// G2's leaky ReLU slope: the server needs it when it computes G2's last step (`VolumeTail`).
    #[serde(default)]
    pub activation_slope: Option<f32>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    pub format_version: u32,
    pub model_id: String,
    pub variant: String,
    pub config: serde_json::Map<String, serde_json::Value>,
    pub graphs: BTreeMap<String, GraphEntry>,
    /// Guided sampling's policy, with its graphs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub guided: Option<GuidedPolicy>,
    pub provenance: serde_json::Value,
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

/// Checks everything in the manifest that does not need the graph files.
pub fn validate_manifest(m: &Manifest) -> Result<ModelConfig, String> {
    if m.format_version != FORMAT_VERSION {
        return Err(format!(
            "format_version is {}, this server reads format_version {FORMAT_VERSION}",
            m.format_version
        ));
    }
    if !VARIANTS.contains(&m.variant.as_str()) {
        return Err(format!("unknown variant \"{}\" (known: {})", m.variant, VARIANTS.join(", ")));
    }
    let config: ModelConfig =
        serde_json::from_value(serde_json::Value::Object(m.config.clone())).map_err(|e| format!("config: {e}"))?;
    validate_config(&config)?;
    for name in m.graphs.keys() {
        if !GraphKind::ALL.iter().any(|k| k.name() == name) {
            return Err(format!(
                "graphs.{name}: unknown graph (expected encoder, volume or cost_slab and volume_net or cost_conv and \
                 volume_net, renderer, and renderer_guide and renderer_fine)"
            ));
        }
    }
    for kind in VolumeBuild::of(&m.graphs)?.bundle_graphs() {
        let entry = m.graphs.get(kind.name()).ok_or_else(|| format!("graphs.{kind}: missing"))?;
        check_declared_io(kind, entry, &config)?;
        if kind == GraphKind::VolumeNet && VolumeTail::of(&entry.outputs)? == VolumeTail::Server {
            config
                .activation_slope
                .ok_or("config.activation_slope: missing (volume_net.onnx leaves G2's last step to the server)")?;
        }
    }
    validate_guided(m, &config)?;
    let renderer_sha = &m.graphs["renderer"].sha256;
    let expected_id = format!("scnerf-{}-{}", m.variant, &renderer_sha.get(..12).unwrap_or(renderer_sha));
    if m.model_id != expected_id {
        return Err(format!("model_id is \"{}\", expected \"{expected_id}\"", m.model_id));
    }
    Ok(config)
}

/// Guided sampling's graphs and policy come together, and the heads the guide returns are the
/// heads the fine renderer reads.
fn validate_guided(m: &Manifest, config: &ModelConfig) -> Result<(), String> {
    let present = GUIDED_GRAPHS.map(|k| m.graphs.contains_key(k.name()));
    let Some(policy) = &m.guided else {
        return match present.iter().any(|&p| p) {
            true => Err("graphs.renderer_guide and graphs.renderer_fine need the manifest's guided policy".into()),
            false => Ok(()),
        };
    };
    if !present.iter().all(|&p| p) {
        return Err("guided: needs graphs.renderer_guide and graphs.renderer_fine".into());
    }
    policy.validate(config.samples)?;
    for kind in GUIDED_GRAPHS {
        check_declared_io(kind, &m.graphs[kind.name()], config)?;
    }
    let heads =
        |names: Vec<&String>| -> Vec<String> { names.into_iter().filter(|n| n.ends_with("_heads")).cloned().collect() };
    let given = heads(m.graphs["renderer_guide"].outputs.iter().map(|t| &t.name).collect());
    let read = heads(m.graphs["renderer_fine"].inputs.iter().map(|t| &t.name).collect());
    if given != read {
        return Err(format!("graphs.renderer_fine reads the heads {read:?}, graphs.renderer_guide gives {given:?}"));
    }
    let index = m.graphs["renderer_fine"].inputs.iter().any(|t| t.name == "head_index");
    if index == read.is_empty() {
        return Err("graphs.renderer_fine: head_index goes with the rectifiers' heads".into());
    }
    Ok(())
}

fn validate_config(c: &ModelConfig) -> Result<(), String> {
    let positive = [
        ("views", c.views),
        ("feature_channels", c.feature_channels),
        ("volume_channels", c.volume_channels),
        ("depth_planes", c.depth_planes),
        ("samples", c.samples),
        ("image_multiple", c.image_multiple),
    ];
    for (name, value) in positive {
        if value == 0 {
            return Err(format!("config.{name} must be > 0"));
        }
    }
    // Features live at 1/4 resolution, so padded sources must divide by 4.
    if !c.image_multiple.is_multiple_of(4) {
        return Err(format!("config.image_multiple = {} is not a multiple of 4", c.image_multiple));
    }
    if c.depth_planes < 2 {
        return Err("config.depth_planes must be >= 2".into());
    }
    Ok(())
}

/// Hashes the graph file and compares with the manifest.
fn verify_file(dir: &Path, kind: GraphKind, entry: &GraphEntry) -> Result<(), String> {
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

/// What the pipeline feeds or reads for one tensor: its shape pattern and whether the graph must
/// declare it.
struct Expected {
    name: &'static str,
    required: bool,
    shape: Vec<Dim>,
}

fn fixed(n: usize) -> Dim {
    Dim::Fixed(n as i64)
}

fn named(s: &str) -> Dim {
    Dim::Named(s.to_string())
}

/// The I/O contract of docs/bundle.md, instantiated with the bundle's hyper-parameters.
fn expected_io(kind: GraphKind, c: &ModelConfig) -> (Vec<Expected>, Vec<Expected>) {
    let v = fixed(c.views);
    let images = vec![v.clone(), fixed(3), named("H"), named("W")];
    let features = vec![v.clone(), fixed(c.feature_channels), named("h"), named("w")];
    let volume = vec![fixed(1), fixed(c.volume_channels), fixed(c.depth_planes), named("Hp"), named("Wp")];
    let e = |name, required, shape| Expected { name, required, shape };
    let sources = |planes: Dim| {
        vec![
            e("features", true, features.clone()),
            e("images", true, images.clone()),
            e("projections", true, vec![v.clone(), fixed(4), fixed(4)]),
            e("depth_planes", true, vec![planes]),
        ]
    };
    match kind {
        GraphKind::Encoder => (vec![e("images", true, images)], vec![e("features", true, features)]),
        GraphKind::Volume => (sources(fixed(c.depth_planes)), vec![e("volume", true, volume)]),
        GraphKind::CostSlab => {
            let mut inputs = sources(named("Dh"));
            inputs.push(e("plane_inside", true, vec![named("Dh")]));
            let conv0 = vec![fixed(1), fixed(c.volume_channels), named("Ds"), named("Hp"), named("Wp")];
            (inputs, vec![e("conv0", true, conv0)])
        }
        GraphKind::CostConv => {
            let channels = 3 * c.views + c.feature_channels;
            let cost = vec![fixed(1), fixed(channels), named("Dh"), named("Hp"), named("Wp")];
            let conv0 = vec![fixed(1), fixed(c.volume_channels), named("Ds"), named("Hp"), named("Wp")];
            (vec![e("cost", true, cost)], vec![e("conv0", true, conv0)])
        }
        GraphKind::VolumeNet => {
            let cv = c.volume_channels;
            let conv0 = vec![fixed(1), fixed(cv), fixed(c.depth_planes), named("Hp"), named("Wp")];
            let phases = vec![fixed(1), fixed(8 * cv), fixed(c.depth_planes / 2), named("Hp/2"), named("Wp/2")];
            let affine = vec![fixed(2), fixed(cv)];
            let outputs = vec![
                e("volume", false, volume),
                e("phases", false, phases),
                e("skip_affine", false, affine.clone()),
                e("phases_affine", false, affine),
            ];
            (vec![e("conv0", true, conv0)], outputs)
        }
        GraphKind::Renderer | GraphKind::RendererGuide | GraphKind::RendererFine => {
            let mut inputs = vec![
                e("ray_origins", true, vec![named("R"), fixed(3)]),
                e("ray_directions", true, vec![named("R"), fixed(3)]),
                e("near_far", true, vec![fixed(2)]),
                e("depth_range", false, vec![fixed(2)]),
                e("volume", true, volume),
                e("images", true, images),
                e("features", false, features),
                e("intrinsics", true, vec![v.clone(), fixed(3), fixed(3)]),
                e("extrinsics", true, vec![v, fixed(4), fixed(4)]),
            ];
            let mut outputs = vec![
                e("rgb", true, vec![named("R"), fixed(3)]),
                e("depth", true, vec![named("R")]),
                e("opacity", true, vec![named("R")]),
            ];
            let heads = |rays: &str| vec![named(rays), fixed(c.heads * c.head_dim), fixed(c.width)];
            match kind {
                GraphKind::RendererGuide => {
                    outputs.push(e("sample_weights", true, vec![named("R"), fixed(c.samples)]));
                    outputs.push(e("geometry_heads", false, heads("R")));
                    outputs.push(e("appearance_heads", false, heads("R")));
                }
                GraphKind::RendererFine => {
                    inputs.push(e("sample_index", true, vec![named("R"), named("K")]));
                    inputs.push(e("sample_multiplicity", true, vec![named("R"), named("K")]));
                    inputs.push(e("geometry_heads", false, heads("G")));
                    inputs.push(e("appearance_heads", false, heads("G")));
                    inputs.push(e("head_index", false, vec![named("R")]));
                    outputs.push(e("sample_weights", true, vec![named("R"), named("K")]));
                }
                _ => {}
            }
            (inputs, outputs)
        }
    }
}

/// Checks a graph's declared inputs/outputs against what the pipeline needs.
fn check_declared_io(kind: GraphKind, entry: &GraphEntry, c: &ModelConfig) -> Result<(), String> {
    let (inputs, outputs) = expected_io(kind, c);
    check_side(kind, "inputs", &entry.inputs, &inputs)?;
    check_side(kind, "outputs", &entry.outputs, &outputs)
}

fn check_side(kind: GraphKind, side: &str, declared: &[TensorSpec], expected: &[Expected]) -> Result<(), String> {
    for (i, spec) in declared.iter().enumerate() {
        let at = format!("graphs.{kind}.{side}[{i}] \"{}\"", spec.name);
        let want = expected
            .iter()
            .find(|e| e.name == spec.name)
            .ok_or_else(|| format!("{at}: the server does not know this {}", &side[..side.len() - 1]))?;
        if declared.iter().filter(|s| s.name == spec.name).count() > 1 {
            return Err(format!("{at}: declared twice"));
        }
        if spec.dtype != "float32" {
            return Err(format!("{at}: dtype is {}, the pipeline uses float32", spec.dtype));
        }
        if spec.shape != want.shape {
            return Err(format!(
                "{at}: shape is {}, the pipeline expects {}",
                fmt_shape(&spec.shape),
                fmt_shape(&want.shape)
            ));
        }
    }
    for want in expected.iter().filter(|e| e.required) {
        if !declared.iter().any(|s| s.name == want.name) {
            return Err(format!("graphs.{kind}.{side}: \"{}\" is missing", want.name));
        }
    }
    Ok(())
}

/// A tensor as the runtime reports it: `None` for a dynamic axis.
#[derive(Debug, Clone)]
pub struct ActualTensor {
    pub name: String,
    pub shape: Vec<Option<i64>>,
    pub dtype: String,
}

/// Compares the manifest's declaration of one side of a graph with the loaded graph.
///
/// A fixed axis must match exactly, a named (dynamic) axis must be dynamic in the graph; a graph
/// that is dynamic where the manifest fixes a size is accepted (it is more general).
pub fn check_signature(
    kind: GraphKind,
    side: &str,
    declared: &[TensorSpec],
    actual: &[ActualTensor],
) -> Result<(), String> {
    for spec in declared {
        let at = format!("{kind}.onnx {side} \"{}\"", spec.name);
        let got = actual
            .iter()
            .find(|a| a.name == spec.name)
            .ok_or_else(|| format!("{at}: declared in manifest.json but absent from the graph"))?;
        if got.dtype != spec.dtype {
            return Err(format!("{at}: graph dtype {}, manifest says {}", got.dtype, spec.dtype));
        }
        let shape_ok = got.shape.len() == spec.shape.len()
            && got.shape.iter().zip(&spec.shape).all(|(g, d)| match (g, d) {
                (Some(n), Dim::Fixed(m)) => n == m,
                (None, _) => true,
                (Some(_), Dim::Named(_)) => false,
            });
        if !shape_ok {
            let g: Vec<String> = got.shape.iter().map(|d| d.map_or("?".into(), |n| n.to_string())).collect();
            return Err(format!(
                "{at}: graph shape [{}] does not match manifest shape {}",
                g.join(", "),
                fmt_shape(&spec.shape)
            ));
        }
    }
    for got in actual {
        if !declared.iter().any(|s| s.name == got.name) {
            return Err(format!(
                "{kind}.onnx {side} \"{}\": present in the graph but not declared in manifest.json",
                got.name
            ));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) fn sample_manifest() -> Manifest {
        let renderer_sha = "ab".repeat(32);
        let json = serde_json::json!({
            "format_version": 1,
            "model_id": format!("scnerf-scnerf-{}", &renderer_sha[..12]),
            "variant": "scnerf",
            "config": {"views": 3, "feature_channels": 32, "volume_channels": 8, "depth_planes": 128,
                       "samples": 128, "pad": 24, "image_multiple": 32, "depth_norm": "near_far"},
            "graphs": {
                "encoder": {"file": "encoder.onnx", "sha256": "00",
                    "inputs": [{"name": "images", "shape": [3, 3, "H", "W"], "dtype": "float32"}],
                    "outputs": [{"name": "features", "shape": [3, 32, "h", "w"], "dtype": "float32"}]},
                "volume": {"file": "volume.onnx", "sha256": "00",
                    "inputs": [{"name": "features", "shape": [3, 32, "h", "w"], "dtype": "float32"},
                               {"name": "images", "shape": [3, 3, "H", "W"], "dtype": "float32"},
                               {"name": "projections", "shape": [3, 4, 4], "dtype": "float32"},
                               {"name": "depth_planes", "shape": [128], "dtype": "float32"}],
                    "outputs": [{"name": "volume", "shape": [1, 8, 128, "Hp", "Wp"], "dtype": "float32"}]},
                "renderer": {"file": "renderer.onnx", "sha256": renderer_sha,
                    "inputs": [{"name": "ray_origins", "shape": ["R", 3], "dtype": "float32"},
                               {"name": "ray_directions", "shape": ["R", 3], "dtype": "float32"},
                               {"name": "near_far", "shape": [2], "dtype": "float32"},
                               {"name": "depth_range", "shape": [2], "dtype": "float32"},
                               {"name": "volume", "shape": [1, 8, 128, "Hp", "Wp"], "dtype": "float32"},
                               {"name": "images", "shape": [3, 3, "H", "W"], "dtype": "float32"},
                               {"name": "features", "shape": [3, 32, "h", "w"], "dtype": "float32"},
                               {"name": "intrinsics", "shape": [3, 3, 3], "dtype": "float32"},
                               {"name": "extrinsics", "shape": [3, 4, 4], "dtype": "float32"}],
                    "outputs": [{"name": "rgb", "shape": ["R", 3], "dtype": "float32"},
                                {"name": "depth", "shape": ["R"], "dtype": "float32"},
                                {"name": "opacity", "shape": ["R"], "dtype": "float32"}]}
            },
            "provenance": {"source_checkpoint": "x", "source_sha256": "y", "exporter_version": "0.1.0",
                           "training": null, "metrics": null, "created": "2026-01-01T00:00:00Z"}
        });
        serde_json::from_value(json).unwrap()
    }

    #[test]
    fn sample_manifest_is_valid() {
        let c = validate_manifest(&sample_manifest()).unwrap();
        assert_eq!(c.views, 3);
        assert_eq!(c.depth_norm, DepthNorm::NearFar);
    }

    #[test]
    fn refuses_wrong_format_version() {
        let mut m = sample_manifest();
        m.format_version = 2;
        assert!(validate_manifest(&m).unwrap_err().contains("format_version"));
    }

    #[test]
    fn refuses_unknown_variant() {
        let mut m = sample_manifest();
        m.variant = "nerf".into();
        assert!(validate_manifest(&m).unwrap_err().contains("unknown variant"));
    }

    #[test]
    fn refuses_unknown_input_name() {
        let mut m = sample_manifest();
        m.graphs.get_mut("renderer").unwrap().inputs[0].name = "origins".into();
        let e = validate_manifest(&m).unwrap_err();
        assert!(e.contains("\"origins\"") && e.contains("does not know"), "{e}");
    }

    #[test]
    fn refuses_missing_required_input() {
        let mut m = sample_manifest();
        m.graphs.get_mut("volume").unwrap().inputs.remove(2);
        let e = validate_manifest(&m).unwrap_err();
        assert!(e.contains("\"projections\" is missing"), "{e}");
    }

    #[test]
    fn accepts_missing_optional_input() {
        let mut m = sample_manifest();
        m.graphs.get_mut("renderer").unwrap().inputs.retain(|t| t.name != "features" && t.name != "depth_range");
        validate_manifest(&m).unwrap();
    }

    #[test]
    fn refuses_wrong_shape_and_dtype() {
        let mut m = sample_manifest();
        m.graphs.get_mut("encoder").unwrap().outputs[0].shape[1] = Dim::Fixed(16);
        let e = validate_manifest(&m).unwrap_err();
        assert!(e.contains("graphs.encoder.outputs[0] \"features\": shape is [3, 16, \"h\", \"w\"]"), "{e}");
        let mut m = sample_manifest();
        m.graphs.get_mut("encoder").unwrap().inputs[0].dtype = "float16".into();
        assert!(validate_manifest(&m).unwrap_err().contains("dtype is float16"));
    }

    #[test]
    fn refuses_view_count_inconsistent_with_config() {
        let mut m = sample_manifest();
        m.config.insert("views".into(), serde_json::json!(2));
        let e = validate_manifest(&m).unwrap_err();
        assert!(e.contains("shape is [3, 3"), "{e}");
    }

    #[test]
    fn refuses_wrong_model_id() {
        let mut m = sample_manifest();
        m.model_id = "scnerf-scnerf-000000000000".into();
        assert!(validate_manifest(&m).unwrap_err().contains("model_id"));
    }

    /// The manifest of a bundle that builds its volume slab by slab (`scnerf-export split-volume`).
    fn slab_manifest() -> Manifest {
        let mut m = sample_manifest();
        let volume = m.graphs.remove("volume").unwrap();
        let t = |name: &str, shape: serde_json::Value| {
            serde_json::from_value::<TensorSpec>(serde_json::json!({"name": name, "shape": shape, "dtype": "float32"}))
                .unwrap()
        };
        let mut inputs = volume.inputs.clone();
        inputs[3] = t("depth_planes", serde_json::json!(["Dh"]));
        inputs.push(t("plane_inside", serde_json::json!(["Dh"])));
        let conv0 = |planes: serde_json::Value| t("conv0", serde_json::json!([1, 8, planes, "Hp", "Wp"]));
        let graph =
            |file: &str, inputs, outputs| GraphEntry { file: file.into(), sha256: "00".into(), inputs, outputs };
        m.graphs.insert("cost_slab".into(), graph("cost_slab.onnx", inputs, vec![conv0(serde_json::json!("Ds"))]));
        m.graphs
            .insert("volume_net".into(), graph("volume_net.onnx", vec![conv0(serde_json::json!(128))], volume.outputs));
        m
    }

    /// The manifest of a bundle whose volume the server's plane sweep starts (`scnerf-export
    /// export`): `cost_conv` on the sweep's cost (41 channels: 3 views' images and 32 features).
    fn sweep_manifest() -> Manifest {
        let mut m = slab_manifest();
        let slab = m.graphs.remove("cost_slab").unwrap();
        let cost = serde_json::json!({"name": "cost", "shape": [1, 41, "Dh", "Hp", "Wp"], "dtype": "float32"});
        let inputs = vec![serde_json::from_value(cost).unwrap()];
        m.graphs.insert("cost_conv".into(), GraphEntry { file: "cost_conv.onnx".into(), inputs, ..slab });
        m
    }

    #[test]
    fn accepts_each_way_to_build_the_volume_but_not_a_mix() {
        let m = slab_manifest();
        validate_manifest(&m).unwrap();
        assert_eq!(VolumeBuild::of(&m.graphs), Ok(VolumeBuild::Slabs));
        assert_eq!(VolumeBuild::of(&sample_manifest().graphs), Ok(VolumeBuild::Whole));
        let m = sweep_manifest();
        validate_manifest(&m).unwrap();
        assert_eq!(VolumeBuild::of(&m.graphs), Ok(VolumeBuild::Sweep));
        assert_eq!(
            VolumeBuild::Sweep.bundle_graphs().iter().map(|k| k.name()).collect::<Vec<_>>(),
            ["encoder", "cost_conv", "volume_net", "renderer"]
        );
        let mut half = slab_manifest();
        half.graphs.remove("volume_net");
        assert!(validate_manifest(&half).unwrap_err().contains("not a mix"));
        let mut both = slab_manifest();
        both.graphs.insert("volume".into(), sample_manifest().graphs["volume"].clone());
        assert!(validate_manifest(&both).unwrap_err().contains("not a mix"));
        let mut mixed = sweep_manifest();
        mixed.graphs.insert("cost_slab".into(), slab_manifest().graphs["cost_slab"].clone());
        assert!(validate_manifest(&mixed).unwrap_err().contains("not a mix"));
        let mut wrong = slab_manifest();
        wrong.graphs.get_mut("cost_slab").unwrap().inputs.pop();
        assert!(validate_manifest(&wrong).unwrap_err().contains("\"plane_inside\" is missing"));
        // The cost has 3 channels per view's image, then the features.
        let mut wrong = sweep_manifest();
        wrong.graphs.get_mut("cost_conv").unwrap().inputs[0].shape[1] = Dim::Fixed(32);
        let e = validate_manifest(&wrong).unwrap_err();
        assert!(e.contains("\"cost\": shape is [1, 32, \"Dh\", \"Hp\", \"Wp\"], the pipeline expects [1, 41,"), "{e}");
    }

    /// `volume_net` outputs the volume, or the parts of G2's last step with the slope in the config.
    #[test]
    fn volume_net_outputs_the_volume_or_the_parts_of_its_last_step() {
        let spec = |name: &str, shape: serde_json::Value| -> TensorSpec {
            serde_json::from_value(serde_json::json!({"name": name, "shape": shape, "dtype": "float32"})).unwrap()
        };
        let parts = vec![
            spec("phases", serde_json::json!([1, 64, 64, "Hp/2", "Wp/2"])),
            spec("skip_affine", serde_json::json!([2, 8])),
            spec("phases_affine", serde_json::json!([2, 8])),
        ];
        let with_outputs = |outputs: Vec<TensorSpec>, slope: Option<f64>| {
            let mut m = sweep_manifest();
            m.graphs.get_mut("volume_net").unwrap().outputs = outputs;
            if let Some(slope) = slope {
                m.config.insert("activation_slope".into(), serde_json::json!(slope));
            }
            m
        };
        let volume = sweep_manifest().graphs["volume_net"].outputs.clone();
        assert_eq!(VolumeTail::of(&volume), Ok(VolumeTail::Graph));
        let server = with_outputs(parts.clone(), Some(0.01));
        assert_eq!(validate_manifest(&server).unwrap().activation_slope, Some(0.01));
        assert_eq!(VolumeTail::of(&server.graphs["volume_net"].outputs), Ok(VolumeTail::Server));
        let e = validate_manifest(&with_outputs(parts.clone(), None)).unwrap_err();
        assert!(e.contains("config.activation_slope: missing"), "{e}");
        let e = validate_manifest(&with_outputs(parts[..2].to_vec(), Some(0.01))).unwrap_err();
        assert!(e.contains("graphs.volume_net.outputs: \"volume\", or \"phases\""), "{e}");
        let e = validate_manifest(&with_outputs([volume, parts.clone()].concat(), Some(0.01))).unwrap_err();
        assert!(e.contains("graphs.volume_net.outputs: \"volume\", or \"phases\""), "{e}");
        let mut odd = parts;
        odd[0].shape[2] = Dim::Fixed(128);
        let e = validate_manifest(&with_outputs(odd, Some(0.01))).unwrap_err();
        assert!(e.contains("\"phases\": shape is [1, 64, 128,"), "{e}");
    }

    #[test]
    fn refuses_missing_graph_and_config_key() {
        let mut m = sample_manifest();
        m.graphs.remove("volume");
        assert!(validate_manifest(&m).unwrap_err().contains("graphs.volume: missing"));
        let mut m = sample_manifest();
        m.config.remove("samples");
        assert!(validate_manifest(&m).unwrap_err().contains("samples"));
    }

    #[test]
    fn file_hash_mismatch_names_the_file() {
        let dir = std::env::temp_dir().join(format!("scnerf-bundle-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("encoder.onnx"), b"not a graph").unwrap();
        let entry = sample_manifest().graphs["encoder"].clone();
        let e = verify_file(&dir, GraphKind::Encoder, &entry).unwrap_err();
        assert!(e.contains("sha256 of encoder.onnx is"), "{e}");
        let mut escaping = entry;
        escaping.file = "../x.onnx".into();
        assert!(verify_file(&dir, GraphKind::Encoder, &escaping).unwrap_err().contains("inside the bundle"));
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn signature_check() {
        let declared = &sample_manifest().graphs["renderer"].outputs;
        let mut actual: Vec<ActualTensor> = declared
            .iter()
            .map(|s| ActualTensor {
                name: s.name.clone(),
                shape: s
                    .shape
                    .iter()
                    .map(|d| match d {
                        Dim::Fixed(n) => Some(*n),
                        Dim::Named(_) => None,
                    })
                    .collect(),
                dtype: "float32".into(),
            })
            .collect();
        check_signature(GraphKind::Renderer, "output", declared, &actual).unwrap();
        actual[0].shape[0] = Some(4096);
        let e = check_signature(GraphKind::Renderer, "output", declared, &actual).unwrap_err();
        assert!(e.contains("renderer.onnx output \"rgb\": graph shape [4096, 3]"), "{e}");
        actual[0].shape[0] = None;
        actual.push(ActualTensor { name: "extra".into(), shape: vec![], dtype: "float32".into() });
        let e = check_signature(GraphKind::Renderer, "output", declared, &actual).unwrap_err();
        assert!(e.contains("\"extra\": present in the graph"), "{e}");
    }
}
