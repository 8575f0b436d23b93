//! The executor's queue: the admitted requests, each with its own jobs, and the order they run
//! in (the job of the request with the earliest turn first: its deadline when its client chose
//! one, else its fair turn among the clients, see `fair.rs`).

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;
use std::time::Instant;

use tokio::sync::oneshot;
use tracing::Span;

use super::budget::MemoryRefusals;
use super::rates::{ModelRates, Work};
use super::runner::{Interrupt, Outputs};
use super::runners::RunnerChange;
use super::{BackendError, NamedTensors};
use crate::bundle::GraphKind;

/// What a job does with its outputs on the executor thread, given the inputs the run read
/// (`Ticket::run_prepared_then`): its result is the job's.
pub(super) type Finish = Box<dyn FnOnce(NamedTensors, Outputs) -> Result<NamedTensors, BackendError> + Send>;

/// A job's inputs: given, or made by the executor when the job runs.
pub(super) enum Inputs {
    Ready(NamedTensors),
    Prepared(Box<dyn FnOnce() -> NamedTensors + Send>),
}

impl Inputs {
    pub(super) fn make(self, graph: GraphKind) -> NamedTensors {
        match self {
            Inputs::Ready(tensors) => tensors,
            Inputs::Prepared(prepare) => {
                let started = Instant::now();
                let tensors = prepare();
                tracing::debug!(%graph, ms = started.elapsed().as_secs_f64() * 1e3, "inputs prepared");
                tensors
            }
        }
    }
}

pub(super) struct Job {
    pub(super) ticket: u64,
    /// The model whose runner runs it (`BackendHandle::add_runner`'s slot).
    pub(super) model: usize,
    pub(super) graph: GraphKind,
    pub(super) units: f64,
    pub(super) inputs: Inputs,
    pub(super) finish: Option<Finish>,
    pub(super) reply: oneshot::Sender<Result<NamedTensors, BackendError>>,
    pub(super) span: Span,
    pub(super) deadline: Instant,
    /// The request's last run of this graph: release what the runner keeps for the next run
    /// when nothing else waits (`GraphRunner::run_and_release`).
    pub(super) last: bool,
}

/// The graph run in progress: its request's turn, its planned seconds, when it started.
#[derive(Clone)]
pub(super) struct Running {
    pub(super) turn: Instant,
    /// Its request's deadline: the watchdog ends the run there (`watchdog.rs`); how late a run
    /// that cannot be ended is (`stuck.rs`).
    pub(super) deadline: Instant,
    pub(super) secs: f64,
    pub(super) started: Instant,
    /// What ends it (its runner's), when something can.
    pub(super) interrupt: Option<Arc<dyn Interrupt>>,
    /// The watchdog asked it to end.
    pub(super) interrupted: bool,
}

/// Whom a request is for: the digest of its token (`auth::Principal::owner`), `None` without
/// authentication.
pub type Client = Option<[u8; 32]>;

/// An admitted request: its deadline, its turn, its model and client, the work it has not
/// finished, the memory it may use at most, its waiting jobs.
pub(super) struct Admitted {
    pub(super) deadline: Instant,
    /// Where it runs in the executor's order (earliest first): see `fair.rs`.
    pub(super) turn: Instant,
    /// The slot of the model whose runner runs it: its work is planned at that model's rates.
    pub(super) model: usize,
    pub(super) client: Client,
    pub(super) remaining: Work,
    pub(super) memory: u64,
    pub(super) jobs: VecDeque<Job>,
}

/// Executor queue state, behind `Shared::queue`.
#[derive(Default)]
pub(super) struct Queue {
    /// Requests admitted and not yet finished (running, waiting, or between jobs).
    pub(super) requests: HashMap<u64, Admitted>,
    pub(super) queued_jobs: usize,
    pub(super) next_ticket: u64,
    pub(super) rates: ModelRates,
    /// Sum of the admitted requests' memory estimates and of the leases, bytes.
    pub(super) memory_in_use: u64,
    /// The leases' part of it.
    pub(super) memory_leased: u64,
    /// The graph run in progress.
    pub(super) running: Option<Running>,
    pub(super) refusals: MemoryRefusals,
    /// Every handle is gone: the executor finishes the queued jobs and stops.
    pub(super) closed: bool,
    /// The executor thread has ended; new jobs fail with `Stopped`.
    pub(super) stopped: bool,
    /// Runners added or removed since the executor last looked (see `runners.rs`).
    pub(super) runner_changes: Vec<RunnerChange>,
    /// The slot the next runner added gets (0 is the first runner's).
    pub(super) next_slot: usize,
}

impl Queue {
    pub(super) fn push(&mut self, job: Job) {
        if let Some(request) = self.requests.get_mut(&job.ticket) {
            request.jobs.push_back(job);
            self.queued_jobs += 1;
        }
    }

    /// The next job of the request with the earliest turn (the earlier admitted on a tie), and
    /// that request's turn.
    pub(super) fn pop(&mut self) -> Option<(Job, Instant)> {
        let (_, request) =
            self.requests.iter_mut().filter(|(_, r)| !r.jobs.is_empty()).min_by_key(|(&ticket, r)| (r.turn, ticket))?;
        self.queued_jobs -= 1;
        Some((request.jobs.pop_front()?, request.turn))
    }

    /// Seconds of `request`'s remaining work, at its model's rates.
    pub(super) fn remaining_secs(&self, request: &Admitted) -> f64 {
        request.remaining.secs(&self.rates.of(request.model))
    }

    /// A job finished: its request has that much less to do, and its model's rates learn its time.
    pub(super) fn done(&mut self, job: &Job, took: f64) {
        self.rates.record(job.model, job.graph, job.units, took);
        if let Some(request) = self.requests.get_mut(&job.ticket) {
            let left = &mut request.remaining.0[job.graph.index()];
            *left = (*left - job.units).max(0.0);
        }
    }

    /// Forgets a finished request and drops the jobs it left behind.
    pub(super) fn release(&mut self, ticket: u64) {
        if let Some(request) = self.requests.remove(&ticket) {
            self.queued_jobs -= request.jobs.len();
            self.memory_in_use -= request.memory;
        }
    }
}

/// Admission by memory.
impl Queue {
    /// Seconds of admitted work, in the order the executor runs it (earliest turn first),
    /// until requests holding `needed` bytes of estimates have finished.
    fn secs_until_freed(&self, needed: u64) -> f64 {
        let mut queue: Vec<(Instant, f64, u64)> =
            self.requests.values().map(|r| (r.turn, self.remaining_secs(r), r.memory)).collect();
        queue.sort_by_key(|&(due, _, _)| due);
        let (mut secs, mut freed) = (0.0, 0u64);
        for (_, took, memory) in queue {
            if freed >= needed {
                break;
            }
            secs += took;
            freed += memory;
        }
        secs
    }

    /// The refusal of `needed` bytes, more than the budget for requests ever has.
    pub(super) fn too_large(&mut self, needed: u64, budget: u64) -> BackendError {
        self.refusals.too_large += 1;
        BackendError::TooLarge { needed_mib: needed.div_ceil(1 << 20), budget_mib: budget >> 20 }
    }

    /// Holds `more` bytes of the budget for requests (`budget`) for something that holds
    /// `held` already: `TooLarge` when `held + more` exceeds it, `MemoryBusy` when what is held
    /// now, by requests and leases and `outside` them (the scene cache), leaves too little.
    pub(super) fn hold(&mut self, budget: u64, held: u64, more: u64, outside: u64) -> Result<(), BackendError> {
        if held.saturating_add(more) > budget {
            return Err(self.too_large(held.saturating_add(more), budget));
        }
        if (self.memory_in_use + outside).saturating_add(more) > budget {
            self.refusals.busy += 1;
            return Err(BackendError::MemoryBusy {
                in_use_mib: (self.memory_in_use + outside) >> 20,
                budget_mib: budget >> 20,
                ahead_secs: self.secs_until_freed((self.memory_in_use + outside).saturating_add(more) - budget),
            });
        }
        self.memory_in_use += more;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use crate::backend::testkit::{far, in_secs, recorder, tagged, NONE};
    use crate::bundle::GraphKind;

    #[tokio::test]
    async fn jobs_run_earliest_deadline_first() {
        let (backend, order, open) = recorder();
        let blocker = backend.admit(far(), NONE, 0).unwrap();
        let first = blocker.run(GraphKind::Encoder, 0.0, tagged(0)); // holds the executor at the gate
        tokio::time::sleep(Duration::from_millis(50)).await;
        let late = backend.admit(in_secs(30), NONE, 0).unwrap();
        let soon = backend.admit(in_secs(10), NONE, 0).unwrap();
        let mut pending: Vec<_> = (0..3).map(|_| late.run(GraphKind::Renderer, 0.0, tagged(1))).collect();
        pending.extend((0..2).map(|_| soon.run(GraphKind::Renderer, 0.0, tagged(2))));
        assert_eq!(backend.stats().queued_jobs, 5);
        open.send(()).unwrap();
        first.await.unwrap();
        for p in pending {
            p.await.unwrap();
        }
        assert_eq!(*order.lock().unwrap(), vec![0, 2, 2, 1, 1, 1]);
    }
}
