//! `manifest.json`: its types, and the checks that need no graph file.

use std::collections::BTreeMap;
use std::fmt;

use serde::{Deserialize, Serialize};

pub const FORMAT_VERSION: u32 = 1;
pub const VARIANTS: [&str; 4] = ["mvsnerf", "scnerf", "scnerf-geometry", "scnerf-appearance"];

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

pub(super) fn fmt_shape(shape: &[Dim]) -> String {
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
    /// When the band stage recolours a view's band from its sources; absent: where it is dark.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub band: Option<BandPolicy>,
    pub provenance: serde_json::Value,
}

/// The manifest's `band` object (docs/bundle.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BandPolicy {
    pub fill: BandRule,
}

/// Which views' bands take their sources' colour.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BandRule {
    /// Views whose band the network renders darker than its sources
    /// ([`DARKER`](crate::pipeline::band::DARKER)): the default model's dark band.
    #[default]
    WhenDark,
    /// Every view: a network refined on a capture renders its band brighter than the default
    /// does, yet further from the photos than the sources' colours (`scnerf-export refine`
    /// measures both on the held-out views and writes this when the sources' win).
    Always,
}

/// The manifest's `guided` object (docs/bundle.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct GuidedPolicy {
    /// Spacing of the level-0 grid (a power of two).
    pub step: usize,
    /// Samples per pixel of each later level, coarse to fine (one per halving of the spacing).
    pub samples: Vec<usize>,
    /// A neighbour's (dilated) weight from which a sample counts as matter.
    pub support_threshold: f32,
    /// Largest spread of the neighbours' colours, per channel, for a pixel to take their mean.
    pub smooth_tolerance: f32,
    /// Coarsest grid spacing at which pixels may take their neighbours' mean.
    pub smooth_max_step: usize,
    /// A pixel rendered at K samples whose composited colour lies further than this outside its
    /// neighbours' range in a channel, or whose opacity lies this far below theirs, is rendered
    /// again at `verify_samples` ([`disagreeing`]). Absent: no pixel is rendered again.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verify_tolerance: Option<f32>,
    /// The largest share of a level's K-sample pixels rendered again, the worst first: bounds a
    /// view's work when most of its pixels disagree.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verify_share: Option<f64>,
    /// A pixel whose neighbours' composited colours span more than this in a channel lies on an
    /// edge, where a few samples miss the surface one side saw: it runs at `edge_samples` samples
    /// when its level's count is lower. Absent: every pixel runs at its level's count.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub edge_span: Option<f32>,
    /// Samples per pixel on an edge.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub edge_samples: Option<usize>,
    /// A pixel runs at as many samples as its neighbours' support spans, rounded up to a multiple
    /// of [`SAMPLE_QUANTUM`], at least this many and at most its level's (or its edge's) count: K
    /// samples that cover the whole support miss nothing a neighbour saw. Absent: every pixel runs
    /// at its level's (or its edge's) count.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min_samples: Option<usize>,
    /// Samples of a pixel rendered again: its neighbours' support and the rest spread over the
    /// ray ([`spread_samples`](crate::pipeline::guided::spread_samples)). Absent: all S.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub verify_samples: Option<usize>,
}

/// Fitted sample counts are multiples of this, so a level runs a few counts, not dozens.
pub const SAMPLE_QUANTUM: usize = 4;

impl GuidedPolicy {
    /// Checks the policy against a model of `samples` samples per ray.
    pub fn validate(&self, samples: usize) -> Result<(), String> {
        if self.step == 0 || !self.step.is_power_of_two() {
            return Err(format!("guided.step must be a power of two, got {}", self.step));
        }
        if self.samples.len() != self.step.trailing_zeros() as usize {
            return Err(format!("guided.samples needs one count per level below step {}", self.step));
        }
        if let Some(k) = self.samples.iter().find(|&&k| k == 0 || k > samples) {
            return Err(format!("guided.samples: {k} is not within 1..={samples}"));
        }
        let finite = [self.support_threshold, self.smooth_tolerance].iter().all(|v| v.is_finite() && *v >= 0.0);
        if !finite {
            return Err("guided.support_threshold and guided.smooth_tolerance must be finite and >= 0".into());
        }
        match (self.verify_tolerance, self.verify_share) {
            (None, None) => Ok(()),
            (Some(t), Some(share)) if t.is_finite() && t >= 0.0 && (0.0..=1.0).contains(&share) => Ok(()),
            _ => Err(String::from(
                "guided.verify_tolerance (finite, >= 0) and guided.verify_share (0 to 1) come together",
            )),
        }?;
        match (self.edge_span, self.edge_samples) {
            (None, None) => Ok(()),
            (Some(span), Some(k)) if span.is_finite() && span >= 0.0 && (1..=samples).contains(&k) => Ok(()),
            _ => Err(format!("guided.edge_span (finite, >= 0) and guided.edge_samples (1..={samples}) come together")),
        }?;
        let within = |k: Option<usize>| k.is_none_or(|k| (1..=samples).contains(&k));
        if !within(self.min_samples) || !within(self.verify_samples) {
            return Err(format!("guided.min_samples and guided.verify_samples must be within 1..={samples}"));
        }
        Ok(())
    }

    /// Samples per pixel of a pixel of a level of `count` samples whose neighbours' colours span
    /// `span` and whose neighbours' weights count `support` samples as matter.
    pub fn samples_at(&self, count: usize, span: f32, support: usize) -> usize {
        let most = match (self.edge_span, self.edge_samples) {
            (Some(edge), Some(k)) if span > edge => count.max(k),
            _ => count,
        };
        self.min_samples.map_or(most, |least| support.min(most).next_multiple_of(SAMPLE_QUANTUM).max(least).min(most))
    }

    /// Samples of a pixel rendered again, of a model of `samples` per ray.
    pub fn rerun_samples(&self, samples: usize) -> usize {
        self.verify_samples.unwrap_or(samples).min(samples)
    }

    /// The most pixels of a level of `fine` K-sample pixels that are rendered again.
    pub fn most_reruns(&self, fine: usize) -> usize {
        self.verify_share.map_or(0, |share| (share * fine as f64).floor() as usize)
    }

    /// (grid spacing, samples per pixel) of every level after the first, coarse to fine.
    pub fn levels(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        self.samples.iter().enumerate().map(|(i, &k)| (self.step >> (i + 1), k))
    }
}
