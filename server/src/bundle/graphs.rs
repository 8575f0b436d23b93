//! The sub-graphs a bundle holds, and which of them build the encoding volume.

use std::collections::BTreeMap;
use std::fmt;

use super::manifest::{GraphEntry, TensorSpec};

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
    pub(super) fn of(graphs: &BTreeMap<String, GraphEntry>) -> Result<VolumeBuild, String> {
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
    pub(super) fn of(outputs: &[TensorSpec]) -> Result<VolumeTail, String> {
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
