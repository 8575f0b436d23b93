//! The graphs' I/O contract (docs/bundle.md): what the pipeline feeds and reads, checked against
//! the manifest's declarations, and the declarations against the loaded graphs.

use super::graphs::GraphKind;
use super::manifest::{fmt_shape, Dim, GraphEntry, ModelConfig, TensorSpec};

/// What the pipeline feeds or reads for one tensor: its shape pattern and whether the graph must
/// declare it.
pub(super) struct Expected {
    pub(super) name: &'static str,
    pub(super) required: bool,
    pub(super) shape: Vec<Dim>,
}

fn fixed(n: usize) -> Dim {
    Dim::Fixed(n as i64)
}

fn named(s: &str) -> Dim {
    Dim::Named(s.to_string())
}

/// The I/O contract of docs/bundle.md, instantiated with the bundle's hyper-parameters: (inputs,
/// outputs). The exporter's `export/bundle.py::graph_contract` is its twin; both are held to
/// tests/fixtures/rules/graph_contract.json (`bundle/tests.rs`).
pub(super) fn expected_io(kind: GraphKind, c: &ModelConfig) -> (Vec<Expected>, Vec<Expected>) {
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
pub(super) fn check_declared_io(kind: GraphKind, entry: &GraphEntry, c: &ModelConfig) -> Result<(), String> {
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
