//! Model bundle: `manifest.json` + its ONNX graphs (docs/bundle.md).
//!
//! Loading checks everything that can be checked before ONNX Runtime sees the files: format
//! version, variant, hyper-parameters, every file's sha256, and each graph's declared inputs and
//! outputs against what the pipeline feeds and reads ([`contract`]). `check_signature` later
//! compares the declarations with what ONNX Runtime reports for the loaded graph. Every refusal
//! names the mismatch.

mod contract;
mod files;
mod graphs;
mod load;
mod manifest;
mod onnx_data;
#[cfg(test)]
mod tests;
mod validate;

pub use contract::{check_signature, ActualTensor};
pub use files::{FileId, Stop, MAX_GRAPH_BYTES, MAX_MANIFEST_BYTES};
pub use graphs::{GraphKind, VolumeBuild, VolumeTail, GUIDED_GRAPHS};
pub use load::{sha256_file, Bundle, BundleError};
pub use manifest::{
    BandPolicy, BandRule, DepthNorm, Dim, GraphEntry, GuidedPolicy, Manifest, ModelConfig, TensorSpec, FORMAT_VERSION,
    VARIANTS,
};
pub use validate::{model_id, validate_manifest};
