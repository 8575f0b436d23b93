//! Inference backend: the graph sessions live on one dedicated OS thread (the executor) that
//! serves all requests, so ONNX Runtime's thread pool is never oversubscribed.
//!
//! Why a thread: `ort::Session::run` takes `&mut self` and blocks for seconds; keeping it off the
//! async runtime keeps handlers, health checks and uploads responsive.
//!
//! Scheduling. A request is first *admitted* (`BackendHandle::admit` -> `Ticket`); at most
//! `capacity` requests are admitted at once and the next one is refused at once (`QueueFull`,
//! 503 + Retry-After) rather than piling up. One job is one graph run (the encoder, the volume
//! net, or one renderer chunk). Each admitted request has its own job queue, and the executor
//! takes jobs round-robin across requests, so the chunks of concurrent requests interleave and a
//! large view does not starve a small one. Jobs whose request is gone (client disconnected:
//! the handler future and its `Ticket` were dropped) or past its deadline are dropped unrun.

pub mod ort;

use std::collections::{HashMap, VecDeque};
use std::future::Future;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Instant;

use tokio::sync::oneshot;
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
    #[error("the request's deadline passed before its graph runs finished")]
    DeadlineExceeded,
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
    deadline: Instant,
}

/// Executor queue state, behind `Shared::queue`.
#[derive(Default)]
struct Queue {
    /// Admitted requests that have jobs waiting, in service order (round robin).
    ring: VecDeque<u64>,
    /// Waiting jobs per admitted request.
    jobs: HashMap<u64, VecDeque<Job>>,
    /// Requests admitted and not yet finished (running, waiting, or between jobs).
    admitted: usize,
    queued_jobs: usize,
    next_ticket: u64,
    /// Every handle is gone: the executor finishes the queued jobs and stops.
    closed: bool,
    /// The executor thread has ended; new jobs fail with `Stopped`.
    stopped: bool,
}

impl Queue {
    fn push(&mut self, ticket: u64, job: Job) {
        let jobs = self.jobs.entry(ticket).or_default();
        if jobs.is_empty() {
            self.ring.push_back(ticket);
        }
        jobs.push_back(job);
        self.queued_jobs += 1;
    }

    /// The next job in round-robin order across requests.
    fn pop(&mut self) -> Option<Job> {
        while let Some(ticket) = self.ring.pop_front() {
            let Some(jobs) = self.jobs.get_mut(&ticket) else { continue };
            let Some(job) = jobs.pop_front() else { continue };
            if !jobs.is_empty() {
                self.ring.push_back(ticket);
            }
            self.queued_jobs -= 1;
            return Some(job);
        }
        None
    }

    /// Forgets a finished request and drops the jobs it left behind.
    fn release(&mut self, ticket: u64) {
        if let Some(jobs) = self.jobs.remove(&ticket) {
            self.queued_jobs -= jobs.len();
        }
        self.ring.retain(|&t| t != ticket);
        self.admitted -= 1;
    }
}

struct Shared {
    queue: Mutex<Queue>,
    wake: Condvar,
    capacity: usize,
}

impl Shared {
    /// A poisoned lock only means a thread panicked while holding it; the queue stays consistent
    /// (every update is a single push/pop), so keep serving.
    fn lock(&self) -> MutexGuard<'_, Queue> {
        self.queue.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// Closes the queue when the last `BackendHandle` goes away.
struct Closer(Arc<Shared>);

impl Drop for Closer {
    fn drop(&mut self) {
        self.0.lock().closed = true;
        self.0.wake.notify_all();
    }
}

/// Cheap-to-clone handle to the inference executor.
#[derive(Clone)]
pub struct BackendHandle {
    shared: Arc<Shared>,
    _closer: Arc<Closer>,
}

/// How busy the executor is (for /metrics).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct QueueStats {
    pub admitted: usize,
    pub queued_jobs: usize,
    pub capacity: usize,
}

impl BackendHandle {
    /// Starts the executor thread; `capacity` requests may be admitted at once. The thread ends
    /// when every handle is dropped.
    pub fn spawn(runner: Box<dyn GraphRunner>, capacity: usize) -> std::io::Result<BackendHandle> {
        let shared = Arc::new(Shared { queue: Mutex::default(), wake: Condvar::new(), capacity: capacity.max(1) });
        let worker_shared = shared.clone();
        std::thread::Builder::new().name("scnerf-inference".into()).spawn(move || worker(runner, worker_shared))?;
        Ok(BackendHandle { _closer: Arc::new(Closer(shared.clone())), shared })
    }

    /// Admits a request whose graph runs must finish by `deadline`; `QueueFull` when `capacity`
    /// requests are already admitted. The request leaves when the ticket is dropped.
    pub fn admit(&self, deadline: Instant) -> Result<Ticket, BackendError> {
        let mut q = self.shared.lock();
        if q.stopped {
            return Err(BackendError::Stopped);
        }
        if q.admitted >= self.shared.capacity {
            return Err(BackendError::QueueFull);
        }
        q.admitted += 1;
        q.next_ticket += 1;
        Ok(Ticket { id: q.next_ticket, deadline, shared: self.shared.clone() })
    }

    pub fn stats(&self) -> QueueStats {
        let q = self.shared.lock();
        QueueStats { admitted: q.admitted, queued_jobs: q.queued_jobs, capacity: self.shared.capacity }
    }
}

/// An admitted request. Dropping it (the request finished, failed, timed out, or its client
/// went away and the handler future was dropped) removes its waiting jobs from the queue.
pub struct Ticket {
    id: u64,
    deadline: Instant,
    shared: Arc<Shared>,
}

impl Ticket {
    pub fn deadline(&self) -> Instant {
        self.deadline
    }

    /// Queues one graph run now and returns a future of its outputs. Queuing happens before the
    /// future is first polled, so a caller can keep several runs in flight (see
    /// `pipeline::chunks`).
    pub fn run(
        &self,
        graph: GraphKind,
        inputs: NamedTensors,
    ) -> impl Future<Output = Result<Outputs, BackendError>> + Send + 'static {
        let (reply, rx) = oneshot::channel();
        let job = Job { graph, inputs, reply, span: Span::current(), deadline: self.deadline };
        let queued = {
            let mut q = self.shared.lock();
            if q.stopped {
                Err(BackendError::Stopped)
            } else {
                q.push(self.id, job);
                Ok(())
            }
        };
        self.shared.wake.notify_one();
        async move {
            queued?;
            let outputs = rx.await.map_err(|_| BackendError::Stopped)??;
            Ok(Outputs { graph, tensors: outputs })
        }
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        self.shared.lock().release(self.id);
    }
}

/// Waits for the next job; `None` once the queue is closed and empty.
fn next_job(shared: &Shared) -> Option<Job> {
    let mut q = shared.lock();
    loop {
        if let Some(job) = q.pop() {
            return Some(job);
        }
        if q.closed {
            q.stopped = true;
            return None;
        }
        q = shared.wake.wait(q).unwrap_or_else(|p| p.into_inner());
    }
}

fn worker(mut runner: Box<dyn GraphRunner>, shared: Arc<Shared>) {
    while let Some(job) = next_job(&shared) {
        // The request went away (client disconnected, deadline passed): skip its work.
        if job.reply.is_closed() {
            continue;
        }
        if Instant::now() >= job.deadline {
            let _ = job.reply.send(Err(BackendError::DeadlineExceeded));
            continue;
        }
        let _entered = job.span.enter();
        let started = Instant::now();
        let result = run_guarded(runner.as_mut(), job.graph, &job.inputs);
        tracing::debug!(graph = %job.graph, ms = started.elapsed().as_secs_f64() * 1e3, "graph run");
        let _ = job.reply.send(result);
    }
}

/// A panic inside a runner must not take the process (or the executor thread) down.
fn run_guarded(
    runner: &mut dyn GraphRunner,
    graph: GraphKind,
    inputs: &NamedTensors,
) -> Result<NamedTensors, BackendError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| runner.run(graph, inputs))).unwrap_or_else(|panic| {
        let message = panic
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "panic".into());
        Err(BackendError::Run { graph, message })
    })
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::mpsc;
    use std::time::Duration;

    /// Records the tag (first input value) of every job it runs; the first job waits for a
    /// signal so that a test can fill the queue before anything runs.
    struct Recorder {
        order: Arc<Mutex<Vec<u32>>>,
        gate: Option<mpsc::Receiver<()>>,
    }

    impl GraphRunner for Recorder {
        fn run(&mut self, _graph: GraphKind, inputs: &NamedTensors) -> Result<NamedTensors, BackendError> {
            if let Some(gate) = self.gate.take() {
                let _ = gate.recv();
            }
            self.order.lock().unwrap().push(inputs[0].1.data[0] as u32);
            Ok(vec![])
        }
    }

    fn tagged(tag: u32) -> NamedTensors {
        vec![("tag".into(), Tensor::new(vec![1], vec![tag as f32]))]
    }

    fn recorder() -> (BackendHandle, Arc<Mutex<Vec<u32>>>, mpsc::Sender<()>) {
        let order = Arc::new(Mutex::new(Vec::new()));
        let (open, gate) = mpsc::channel();
        let backend = BackendHandle::spawn(Box::new(Recorder { order: order.clone(), gate: Some(gate) }), 4).unwrap();
        (backend, order, open)
    }

    fn far() -> Instant {
        Instant::now() + Duration::from_secs(60)
    }

    #[tokio::test]
    async fn jobs_of_concurrent_requests_interleave_round_robin() {
        let (backend, order, open) = recorder();
        let blocker = backend.admit(far()).unwrap();
        let first = blocker.run(GraphKind::Encoder, tagged(0)); // holds the executor at the gate
        tokio::time::sleep(Duration::from_millis(50)).await;
        let big = backend.admit(far()).unwrap();
        let small = backend.admit(far()).unwrap();
        let mut pending: Vec<_> = (0..6).map(|_| big.run(GraphKind::Renderer, tagged(1))).collect();
        pending.extend((0..2).map(|_| small.run(GraphKind::Renderer, tagged(2))));
        assert_eq!(backend.stats().queued_jobs, 8);
        open.send(()).unwrap();
        first.await.unwrap();
        for p in pending {
            p.await.unwrap();
        }
        assert_eq!(*order.lock().unwrap(), vec![0, 1, 2, 1, 2, 1, 1, 1, 1]);
    }

    #[tokio::test]
    async fn admission_is_bounded_and_released_on_drop() {
        let (backend, _order, _open) = recorder();
        let tickets: Vec<Ticket> = (0..4).map(|_| backend.admit(far()).unwrap()).collect();
        assert!(matches!(backend.admit(far()), Err(BackendError::QueueFull)));
        assert_eq!(backend.stats().admitted, 4);
        drop(tickets);
        assert_eq!(backend.stats().admitted, 0);
        assert!(backend.admit(far()).is_ok());
    }

    #[tokio::test]
    async fn a_dropped_request_leaves_no_jobs_and_expired_jobs_do_not_run() {
        let (backend, order, open) = recorder();
        let blocker = backend.admit(far()).unwrap();
        let first = blocker.run(GraphKind::Encoder, tagged(0));
        tokio::time::sleep(Duration::from_millis(50)).await;
        let gone = backend.admit(far()).unwrap();
        let abandoned: Vec<_> = (0..5).map(|_| gone.run(GraphKind::Renderer, tagged(1))).collect();
        drop(abandoned);
        drop(gone); // its five jobs leave the queue
        let late = backend.admit(Instant::now()).unwrap();
        let expired = late.run(GraphKind::Renderer, tagged(2));
        assert_eq!(backend.stats().queued_jobs, 1);
        open.send(()).unwrap();
        first.await.unwrap();
        assert!(matches!(expired.await, Err(BackendError::DeadlineExceeded)));
        assert_eq!(*order.lock().unwrap(), vec![0]);
    }
}
