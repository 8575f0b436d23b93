//! An admitted request's handle ([`Ticket`]): it queues the request's graph runs and yields
//! their [`Outputs`].

use std::future::Future;
use std::sync::Arc;
use std::time::Instant;

use tokio::sync::oneshot;
use tracing::Span;

use super::queue::{Finish, Inputs, Job};
use super::runner::Outputs;
use super::shared::Shared;
use super::{BackendError, NamedTensors};
use crate::bundle::GraphKind;

/// An admitted request. Dropping it (the request finished, failed, timed out, or its client
/// went away and the handler future was dropped) removes its waiting jobs from the queue.
pub struct Ticket {
    pub(super) id: u64,
    /// The model whose runner runs the request's graphs.
    pub(super) model: usize,
    pub(super) deadline: Instant,
    pub(super) shared: Arc<Shared>,
}

impl Ticket {
    pub fn deadline(&self) -> Instant {
        self.deadline
    }

    /// Queues one graph run of `units` of work (see `Work`) now and returns a future of its
    /// outputs. Queuing happens before the future is first polled, so a caller can keep several
    /// runs in flight (see `pipeline::chunks`).
    pub fn run(
        &self,
        graph: GraphKind,
        units: f64,
        inputs: NamedTensors,
    ) -> impl Future<Output = Result<Outputs, BackendError>> + Send + 'static {
        self.run_job(graph, units, Inputs::Ready(inputs), None, false)
    }

    /// [`Ticket::run`] for the request's last run of `graph` (see `GraphRunner::run_and_release`).
    pub fn run_last(
        &self,
        graph: GraphKind,
        units: f64,
        inputs: NamedTensors,
    ) -> impl Future<Output = Result<Outputs, BackendError>> + Send + 'static {
        self.run_job(graph, units, Inputs::Ready(inputs), None, true)
    }

    /// [`Ticket::run`] with inputs that `prepare` makes on the executor thread when the job's turn
    /// comes (see the `backend` module doc).
    pub fn run_prepared(
        &self,
        graph: GraphKind,
        units: f64,
        prepare: impl FnOnce() -> NamedTensors + Send + 'static,
    ) -> impl Future<Output = Result<Outputs, BackendError>> + Send + 'static {
        self.run_job(graph, units, Inputs::Prepared(Box::new(prepare)), None, false)
    }

    /// [`Ticket::run_prepared`] whose outputs `finish` turns into the job's, on the executor
    /// thread, with the inputs the run read: CPU work right after a graph, on buffers the run no
    /// longer needs (G2's last step writes the volume into its input's buffer).
    pub fn run_prepared_then(
        &self,
        graph: GraphKind,
        units: f64,
        prepare: impl FnOnce() -> NamedTensors + Send + 'static,
        finish: impl FnOnce(NamedTensors, Outputs) -> Result<NamedTensors, BackendError> + Send + 'static,
    ) -> impl Future<Output = Result<Outputs, BackendError>> + Send + 'static {
        self.run_job(graph, units, Inputs::Prepared(Box::new(prepare)), Some(Box::new(finish)), false)
    }

    fn run_job(
        &self,
        graph: GraphKind,
        units: f64,
        inputs: Inputs,
        finish: Option<Finish>,
        last: bool,
    ) -> impl Future<Output = Result<Outputs, BackendError>> + Send + 'static {
        let (reply, rx) = oneshot::channel();
        let span = Span::current();
        let job = Job {
            ticket: self.id,
            model: self.model,
            graph,
            units,
            inputs,
            finish,
            reply,
            span,
            deadline: self.deadline,
            last,
        };
        let queued = {
            let mut q = self.shared.lock();
            if q.stopped {
                Err(BackendError::Stopped)
            } else {
                q.push(job);
                Ok(())
            }
        };
        self.shared.wake.notify_one();
        async move {
            queued?;
            let outputs = rx.await.map_err(|_| BackendError::Stopped)??;
            Ok(Outputs::new(graph, outputs))
        }
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        self.shared.lock().release(self.id);
    }
}
