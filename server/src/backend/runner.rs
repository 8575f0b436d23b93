//! What the executor runs: a graph, given named tensors, through a [`GraphRunner`].

use ndarray::ArcArrayD;

use super::BackendError;
use crate::bundle::GraphKind;

/// A graph input or output: float32, any rank, standard (row-major) layout. Shared, so that
/// large inputs (the encoding volume, the source images) are not copied for every renderer
/// chunk; ONNX Runtime reads it in place.
pub type Tensor = ArcArrayD<f32>;

/// Named graph inputs or outputs.
pub type NamedTensors = Vec<(String, Tensor)>;

/// Runs one graph to completion. Implemented by the ONNX Runtime backend and by test fakes.
pub trait GraphRunner: Send + 'static {
    fn run(&mut self, graph: GraphKind, inputs: &NamedTensors) -> Result<NamedTensors, BackendError>;

    /// `run`, then gives back what the runner keeps for the graph's next run (ONNX Runtime's
    /// arena). The executor asks after a request's last renderer run when no other job waits:
    /// the process then returns to its resting size between requests, and a busy executor keeps
    /// the arena warm.
    fn run_and_release(&mut self, graph: GraphKind, inputs: &NamedTensors) -> Result<NamedTensors, BackendError> {
        self.run(graph, inputs)
    }
}
