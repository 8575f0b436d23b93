//! Inference backend: the graph sessions live on one dedicated OS thread, fed by a bounded
//! channel of jobs (graph + named inputs + oneshot reply + tracing span).
//!
//! Why a thread: `ort::Session::run` takes `&mut self` and blocks for seconds; keeping it off the
//! async runtime keeps handlers, health checks and uploads responsive. One job is one graph run
//! (the encoder, the volume net, or one renderer chunk), so a scheduler that interleaves the chunks
//! of concurrent requests can later replace the FIFO without touching the pipeline.

pub mod ort;

use std::sync::Arc;
use std::time::Instant;

use tokio::sync::{mpsc, oneshot};
use tracing::Span;

use crate::bundle::GraphKind;

/// A dense float32 tensor, row-major. The data is shared so that large inputs (the encoding
/// volume, the source images) are not copied for every renderer chunk.
#[derive(Debug, Clone)]
pub struct Tensor {
    pub shape: Vec<usize>,
    pub data: Arc<Vec<f32>>,
}

impl Tensor {
    /// Panics if `data` does not hold exactly the elements of `shape` (a programming error).
    pub fn new(shape: Vec<usize>, data: Vec<f32>) -> Tensor {
        assert_eq!(shape.iter().product::<usize>(), data.len(), "tensor data does not match shape {shape:?}");
        Tensor { shape, data: Arc::new(data) }
    }

    pub fn len(&self) -> usize {
        self.data.len()
    }

    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }
}

/// Named graph inputs or outputs.
pub type NamedTensors = Vec<(String, Tensor)>;

#[derive(Debug, Clone, thiserror::Error)]
pub enum BackendError {
    #[error("{graph}.onnx failed: {message}")]
    Run { graph: GraphKind, message: String },
    #[error("{graph}.onnx returned an unexpected output: {message}")]
    BadOutput { graph: GraphKind, message: String },
    #[error("the inference queue is full")]
    QueueFull,
    #[error("the inference thread has stopped")]
    Stopped,
}

/// Runs one graph to completion. Implemented by the ONNX Runtime backend and by test fakes.
pub trait GraphRunner: Send + 'static {
    fn run(&mut self, graph: GraphKind, inputs: &NamedTensors) -> Result<NamedTensors, BackendError>;
}

struct Job {
    graph: GraphKind,
    inputs: NamedTensors,
    reply: oneshot::Sender<Result<NamedTensors, BackendError>>,
    span: Span,
}

/// Cheap-to-clone handle to the inference thread.
#[derive(Clone)]
pub struct BackendHandle {
    tx: mpsc::Sender<Job>,
}

impl BackendHandle {
    /// Starts the inference thread. It ends when every handle is dropped.
    pub fn spawn(runner: Box<dyn GraphRunner>, queue_capacity: usize) -> std::io::Result<BackendHandle> {
        let (tx, rx) = mpsc::channel(queue_capacity.max(1));
        std::thread::Builder::new().name("scnerf-inference".into()).spawn(move || worker(runner, rx))?;
        Ok(BackendHandle { tx })
    }

    /// Queues one graph run and waits for its outputs. Fails fast with `QueueFull` instead of
    /// waiting for room, so that an overloaded server answers 503 rather than piling up requests.
    pub async fn run(&self, graph: GraphKind, inputs: NamedTensors) -> Result<Outputs, BackendError> {
        let (reply, rx) = oneshot::channel();
        let job = Job { graph, inputs, reply, span: Span::current() };
        self.tx.try_send(job).map_err(|e| match e {
            mpsc::error::TrySendError::Full(_) => BackendError::QueueFull,
            mpsc::error::TrySendError::Closed(_) => BackendError::Stopped,
        })?;
        let outputs = rx.await.map_err(|_| BackendError::Stopped)??;
        Ok(Outputs { graph, tensors: outputs })
    }
}

fn worker(mut runner: Box<dyn GraphRunner>, mut rx: mpsc::Receiver<Job>) {
    while let Some(job) = rx.blocking_recv() {
        // The request went away (client disconnected, deadline passed): skip its work.
        if job.reply.is_closed() {
            continue;
        }
        let _entered = job.span.enter();
        let started = Instant::now();
        // A panic inside a runner must not take the process (or this thread) down.
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| runner.run(job.graph, &job.inputs)))
            .unwrap_or_else(|panic| {
                let message = panic
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_else(|| "panic".into());
                Err(BackendError::Run { graph: job.graph, message })
            });
        tracing::debug!(graph = %job.graph, ms = started.elapsed().as_secs_f64() * 1e3, "graph run");
        let _ = job.reply.send(result);
    }
}

/// The outputs of one graph run, looked up by name.
#[derive(Debug)]
pub struct Outputs {
    graph: GraphKind,
    tensors: NamedTensors,
}

impl Outputs {
    /// Removes the named output and checks its shape (`None` = any size on that axis).
    pub fn take(&mut self, name: &str, shape: &[Option<usize>]) -> Result<Tensor, BackendError> {
        let graph = self.graph;
        let idx = self
            .tensors
            .iter()
            .position(|(n, _)| n == name)
            .ok_or_else(|| BackendError::BadOutput { graph, message: format!("no output \"{name}\"") })?;
        let (_, tensor) = self.tensors.swap_remove(idx);
        let ok =
            tensor.shape.len() == shape.len() && tensor.shape.iter().zip(shape).all(|(a, b)| b.is_none_or(|b| *a == b));
        if !ok {
            return Err(BackendError::BadOutput {
                graph,
                message: format!("\"{name}\" has shape {:?}, expected {shape:?}", tensor.shape),
            });
        }
        Ok(tensor)
    }
}
