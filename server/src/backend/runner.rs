//! What the executor runs: a graph, given named tensors, through a [`GraphRunner`].

use std::sync::Arc;

use ndarray::{ArcArray, ArcArrayD, Dimension};

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

    /// What ends this runner's run in progress from another thread, if anything can: the
    /// executor's watchdog uses it on a run past its request's deadline (`watchdog.rs`).
    fn interrupter(&self) -> Option<Arc<dyn Interrupt>> {
        None
    }
}

/// Ends a runner's graph run in progress from another thread: the run returns an error soon
/// after, instead of holding the one executor thread (a crafted graph's endless `Loop`).
pub trait Interrupt: Send + Sync {
    /// Asks the run in progress to end as soon as it can.
    fn interrupt(&self);
    /// Withdraws the request, before the runner's next run.
    fn clear(&self);
}

/// The outputs of one graph run, looked up by name.
#[derive(Debug)]
pub struct Outputs {
    graph: GraphKind,
    tensors: NamedTensors,
}

impl Outputs {
    pub fn new(graph: GraphKind, tensors: NamedTensors) -> Outputs {
        Outputs { graph, tensors }
    }

    /// Removes the named output and checks its shape (`None` = any size on that axis), which
    /// also fixes its rank `D`.
    pub fn take<D: Dimension>(
        &mut self,
        name: &str,
        shape: &[Option<usize>],
    ) -> Result<ArcArray<f32, D>, BackendError> {
        let graph = self.graph;
        let idx = self
            .tensors
            .iter()
            .position(|(n, _)| n == name)
            .ok_or_else(|| BackendError::BadOutput { graph, message: format!("no output \"{name}\"") })?;
        let (_, tensor) = self.tensors.swap_remove(idx);
        let ok =
            tensor.ndim() == shape.len() && tensor.shape().iter().zip(shape).all(|(a, b)| b.is_none_or(|b| *a == b));
        if !ok {
            return Err(BackendError::BadOutput {
                graph,
                message: format!("\"{name}\" has shape {:?}, expected {shape:?}", tensor.shape()),
            });
        }
        // Cannot fail once the rank matched (`shape` has D's rank).
        tensor
            .into_dimensionality::<D>()
            .map_err(|e| BackendError::BadOutput { graph, message: format!("\"{name}\": {e}") })
    }
}
