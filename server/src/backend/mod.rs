//! Inference backend: the graph sessions live on one dedicated OS thread (the executor) that
//! serves all requests, so ONNX Runtime's thread pool is never oversubscribed.
//!
//! Why a thread: `ort::Session::run` takes `&mut self` and blocks for seconds; keeping it off the
//! async runtime keeps handlers, health checks and uploads responsive.
//!
//! A job may make its inputs on the executor thread, just before its graph runs
//! (`Ticket::run_prepared`): CPU work of the pipeline outside ONNX Runtime (the plane sweep of
//! the volume build) then takes its turn with the graph runs instead of running beside them, its
//! time counts as the graph's, and its buffers exist only while the job runs.
//!
//! Scheduling. A request is first *admitted* (`BackendHandle::admit` -> `Ticket`) with its
//! deadline and an estimate of its work (`Work`: pixels for the encoder and the volume net, rays
//! for the renderer). One job is one graph run (the encoder, the volume net, or one renderer
//! chunk); each admitted request has its own job queue, and the executor always runs a job of
//! the request with the earliest deadline. Round robin, the policy before, finished concurrent
//! requests together: under overload all of them late. Earliest deadline first finishes as many
//! as the executor's speed allows.
//!
//! Admission refuses (503 + Retry-After, at once rather than a 504 later) a request that cannot
//! finish by its deadline given the work admitted before it, or whose work would make an
//! admitted request miss its deadline. Work is turned into time with the executor's measured
//! seconds per unit (`Rates`), on the slow side when requests compete: the rate plus twice its
//! deviation (as TCP estimates a retransmission timeout from round trips), so that the noise of
//! a shared machine does not turn admitted requests into 504s. Before the first run of a graph
//! there is no estimate: admitted. A graph run cannot be interrupted, so the rest of the run in
//! progress counts ahead of a request due sooner than its own. At most `capacity` requests
//! are admitted at once (`QueueFull`). Jobs whose request is gone (client disconnected: the
//! handler future and its `Ticket` were dropped) or past its deadline are dropped unrun.
//!
//! Admission by memory. Each request comes with an estimate of the most memory it adds to the
//! process (`pipeline::memory`), and the executor admits requests while the estimates of the
//! admitted ones add up to at most its memory budget (`MemoryBudget`): beyond it the request is
//! refused at once (`MemoryBusy`, 503 + Retry-After: the seconds until enough admitted work has
//! finished), and a request whose estimate alone exceeds the budget is refused for good
//! (`TooLarge`, 422). Summing peaks over-counts (graph runs take turns on the one executor
//! thread, so only one run's working memory exists at a time) but cannot under-count. Memory a
//! request holds outside its estimate, its body as it arrives and a capture's files while they
//! are parsed, is held against the same budget by a `MemoryLease`.

pub mod ort;

use std::collections::{HashMap, VecDeque};
use std::future::Future;
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use ndarray::{ArcArray, ArcArrayD, Dimension};
use tokio::sync::oneshot;
use tracing::Span;

use crate::bundle::GraphKind;
use crate::sysmem::MemoryProbe;

/// A graph input or output: float32, any rank, standard (row-major) layout. Shared, so that
/// large inputs (the encoding volume, the source images) are not copied for every renderer
/// chunk; ONNX Runtime reads it in place.
pub type Tensor = ArcArrayD<f32>;

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
    #[error(
        "the request cannot finish before its deadline: about {work_secs:.1} s of work, after {ahead_secs:.1} s \
         of work admitted ahead of it"
    )]
    WouldMissDeadline { work_secs: f64, ahead_secs: f64 },
    #[error("the request's deadline passed before its graph runs finished")]
    DeadlineExceeded,
    #[error("not enough memory: the requests in progress hold {in_use_mib} of {budget_mib} MiB")]
    MemoryBusy { in_use_mib: u64, budget_mib: u64, ahead_secs: f64 },
    #[error("an estimated {needed_mib} MiB, more than the {budget_mib} MiB a request may have")]
    TooLarge { needed_mib: u64, budget_mib: u64 },
    #[error("the inference thread has stopped")]
    Stopped,
}

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

/// Work of graph runs, in units per graph (`GraphKind::ALL` order): what a run's time grows
/// with, source pixels (V·H·W of the padded images) for the encoder and the volume graphs (for a
/// cost slab, times its share of the depth planes), rays for the renderer.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Work(pub [f64; GraphKind::ALL.len()]);

impl Work {
    pub fn of(graph: GraphKind, units: f64) -> Work {
        let mut work = Work::default();
        work.0[graph.index()] = units;
        work
    }

    pub fn plus(self, other: Work) -> Work {
        Work(std::array::from_fn(|i| self.0[i] + other.0[i]))
    }

    /// Planned seconds at `rates` (unmeasured graphs count 0).
    fn secs(&self, rates: &Rates) -> f64 {
        self.secs_with(rates, true)
    }

    /// Seconds at `rates`, with or without the margin of their deviation.
    fn secs_with(&self, rates: &Rates, margin: bool) -> f64 {
        GraphKind::ALL.iter().map(|&g| self.0[g.index()] * rates.per_unit(g, margin)).sum()
    }
}

/// Measured seconds per unit of work, per graph: sums of the runs' seconds, units and
/// deviations from the rate, each decayed by `1 - RATE_WEIGHT` a run. Summed rather than
/// averaged per run, so that a run weighs by its units: a request's last chunk of a few rays,
/// whose time is mostly the run's fixed cost, does not swing the rate.
#[derive(Debug, Clone, Copy, Default)]
struct Rates([Option<Rate>; GraphKind::ALL.len()]);

#[derive(Debug, Clone, Copy)]
struct Rate {
    secs: f64,
    units: f64,
    deviation: f64,
}

impl Rate {
    fn mean(&self) -> f64 {
        self.secs / self.units
    }

    /// What admission plans with when requests compete: the mean plus twice the deviation.
    fn planned(&self) -> f64 {
        self.mean() + 2.0 * self.deviation / self.units
    }
}

/// Weight of the latest run: a few runs follow a change of load.
const RATE_WEIGHT: f64 = 0.3;

impl Rates {
    fn record(&mut self, graph: GraphKind, units: f64, took: f64) {
        if units <= 0.0 {
            return;
        }
        let keep = 1.0 - RATE_WEIGHT;
        let rate = &mut self.0[graph.index()];
        *rate = Some(match *rate {
            None => Rate { secs: took, units, deviation: 0.0 },
            Some(r) => Rate {
                secs: keep * r.secs + took,
                units: keep * r.units + units,
                deviation: keep * r.deviation + (took - r.mean() * units).abs(),
            },
        });
    }

    /// Seconds per unit of `graph` (0 while unmeasured): the mean, or with `margin` the planned
    /// rate.
    fn per_unit(&self, graph: GraphKind, margin: bool) -> f64 {
        self.0[graph.index()].map_or(0.0, |r| if margin { r.planned() } else { r.mean() })
    }
}

/// A job's inputs: given, or made by the executor when the job runs.
enum Inputs {
    Ready(NamedTensors),
    Prepared(Box<dyn FnOnce() -> NamedTensors + Send>),
}

impl Inputs {
    fn make(self, graph: GraphKind) -> NamedTensors {
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

struct Job {
    ticket: u64,
    graph: GraphKind,
    units: f64,
    inputs: Inputs,
    reply: oneshot::Sender<Result<NamedTensors, BackendError>>,
    span: Span,
    deadline: Instant,
    /// The request's last run of this graph: release what the runner keeps for the next run
    /// when nothing else waits (`GraphRunner::run_and_release`).
    last: bool,
}

/// The graph run in progress: its request's deadline, its planned seconds, when it started.
#[derive(Debug, Clone, Copy)]
struct Running {
    deadline: Instant,
    secs: f64,
    started: Instant,
}

/// An admitted request: its deadline, the work it has not finished, the memory it may use at
/// most, its waiting jobs.
struct Admitted {
    deadline: Instant,
    remaining: Work,
    memory: u64,
    jobs: VecDeque<Job>,
}

/// Executor queue state, behind `Shared::queue`.
#[derive(Default)]
struct Queue {
    /// Requests admitted and not yet finished (running, waiting, or between jobs).
    requests: HashMap<u64, Admitted>,
    queued_jobs: usize,
    next_ticket: u64,
    rates: Rates,
    /// Sum of the admitted requests' memory estimates and of the leases, bytes.
    memory_in_use: u64,
    /// The leases' part of it.
    memory_leased: u64,
    /// The graph run in progress.
    running: Option<Running>,
    refusals: MemoryRefusals,
    /// Every handle is gone: the executor finishes the queued jobs and stops.
    closed: bool,
    /// The executor thread has ended; new jobs fail with `Stopped`.
    stopped: bool,
}

impl Queue {
    fn push(&mut self, job: Job) {
        if let Some(request) = self.requests.get_mut(&job.ticket) {
            request.jobs.push_back(job);
            self.queued_jobs += 1;
        }
    }

    /// The next job of the request with the earliest deadline (the earlier admitted on a tie).
    fn pop(&mut self) -> Option<Job> {
        let (_, request) = self
            .requests
            .iter_mut()
            .filter(|(_, r)| !r.jobs.is_empty())
            .min_by_key(|(&ticket, r)| (r.deadline, ticket))?;
        self.queued_jobs -= 1;
        request.jobs.pop_front()
    }

    /// A job finished: its request has that much less to do, and the rates learn its time.
    fn done(&mut self, job: &Job, took: f64) {
        self.rates.record(job.graph, job.units, took);
        if let Some(request) = self.requests.get_mut(&job.ticket) {
            let left = &mut request.remaining.0[job.graph.index()];
            *left = (*left - job.units).max(0.0);
        }
    }

    /// `Some(seconds of work ahead)` when a request due at `deadline` with `work` would miss
    /// its deadline, or make an admitted request miss one that it would meet now.
    fn would_miss(&self, now: Instant, deadline: Instant, work: Work) -> Option<f64> {
        // Alone, a request competes with nobody: planned at the mean rate. (Were the margin
        // kept, one slow run could refuse every request, and no run would come to correct it.)
        let alone = self.requests.is_empty() && self.running.is_none();
        let cost = work.secs_with(&self.rates, !alone);
        let mut queue: Vec<(Instant, f64)> =
            self.requests.values().map(|r| (r.deadline, r.remaining.secs(&self.rates))).collect();
        queue.sort_by_key(|&(due, _)| due);
        // A run of a request due later cannot be interrupted: the rest of it comes first. (A run
        // of a request due sooner is in that request's remaining work.)
        let blocking = self
            .running
            .filter(|r| r.deadline > deadline)
            .map_or(0.0, |r| (r.secs - now.saturating_duration_since(r.started).as_secs_f64()).max(0.0));
        let ahead = queue.iter().take_while(|(due, _)| *due <= deadline).fold(blocking, |sum, (_, secs)| sum + secs);
        let misses = |finish: f64, due: Instant| {
            let finish = Duration::try_from_secs_f64(finish).unwrap_or(Duration::MAX);
            now.checked_add(finish).is_none_or(|at| at > due)
        };
        if misses(ahead + cost, deadline) {
            return Some(ahead);
        }
        let mut finish = ahead;
        for &(due, secs) in queue.iter().filter(|(due, _)| *due > deadline) {
            finish += secs;
            if misses(finish + cost, due) && !misses(finish, due) {
                return Some(finish);
            }
        }
        None
    }

    /// Seconds of admitted work, in the order the executor runs it (earliest deadline first),
    /// until requests holding `needed` bytes of estimates have finished.
    fn secs_until_freed(&self, needed: u64) -> f64 {
        let mut queue: Vec<(Instant, f64, u64)> =
            self.requests.values().map(|r| (r.deadline, r.remaining.secs(&self.rates), r.memory)).collect();
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

    /// Forgets a finished request and drops the jobs it left behind.
    fn release(&mut self, ticket: u64) {
        if let Some(request) = self.requests.remove(&ticket) {
            self.queued_jobs -= request.jobs.len();
            self.memory_in_use -= request.memory;
        }
    }

    /// The refusal of `needed` bytes, more than the budget for requests ever has.
    fn too_large(&mut self, needed: u64, budget: u64) -> BackendError {
        self.refusals.too_large += 1;
        BackendError::TooLarge { needed_mib: needed.div_ceil(1 << 20), budget_mib: budget >> 20 }
    }

    /// Holds `more` bytes of the budget for requests (`budget`) for something that holds
    /// `held` already: `TooLarge` when `held + more` exceeds it, `MemoryBusy` when what is held
    /// now leaves too little.
    fn hold(&mut self, budget: u64, held: u64, more: u64) -> Result<(), BackendError> {
        if held.saturating_add(more) > budget {
            return Err(self.too_large(held.saturating_add(more), budget));
        }
        if self.memory_in_use + more > budget {
            self.refusals.busy += 1;
            return Err(BackendError::MemoryBusy {
                in_use_mib: self.memory_in_use >> 20,
                budget_mib: budget >> 20,
                ahead_secs: self.secs_until_freed(self.memory_in_use + more - budget),
            });
        }
        self.memory_in_use += more;
        Ok(())
    }
}

/// Requests refused for memory since the start (for /metrics).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MemoryRefusals {
    /// Would have exceeded the budget with the requests in progress (503).
    pub busy: u64,
    /// Larger than the whole budget (422).
    pub too_large: u64,
}

/// The executor's memory budget: the bytes that the admitted requests' estimates may add up to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MemoryBudget {
    /// What the process may use in all (`--memory-budget-mb`).
    pub total: u64,
    /// Held apart from requests: the process at rest and the scene cache. Set once the server
    /// has warmed up (`BackendHandle::reserve`).
    pub reserved: u64,
}

impl MemoryBudget {
    /// No bound (tests, and the warm-up before the budget is known).
    pub const UNLIMITED: MemoryBudget = MemoryBudget { total: u64::MAX, reserved: 0 };

    /// What requests may have between them.
    pub fn for_requests(&self) -> u64 {
        self.total.saturating_sub(self.reserved)
    }
}

/// Settings of the executor.
#[derive(Debug, Clone)]
pub struct ExecutorOptions {
    /// Requests admitted at once (`--queue-capacity`).
    pub capacity: usize,
    pub memory: MemoryBudget,
    /// Measures each graph run's memory (`--memory-probe`).
    pub probe: Option<Arc<MemoryProbe>>,
}

impl ExecutorOptions {
    /// `capacity` requests at once, no memory bound, no probe.
    pub fn with_capacity(capacity: usize) -> ExecutorOptions {
        ExecutorOptions { capacity, memory: MemoryBudget::UNLIMITED, probe: None }
    }
}

struct Shared {
    queue: Mutex<Queue>,
    wake: Condvar,
    capacity: usize,
    memory: Mutex<MemoryBudget>,
    probe: Option<Arc<MemoryProbe>>,
}

impl Shared {
    /// A poisoned lock only means a thread panicked while holding it; the queue stays consistent
    /// (every update is a single push/pop), so keep serving.
    fn lock(&self) -> MutexGuard<'_, Queue> {
        self.queue.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn memory(&self) -> MemoryBudget {
        *self.memory.lock().unwrap_or_else(|p| p.into_inner())
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
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct QueueStats {
    pub admitted: usize,
    pub queued_jobs: usize,
    pub capacity: usize,
    pub memory: MemoryBudget,
    /// Sum of the admitted requests' memory estimates and of the leases.
    pub memory_in_use: u64,
    /// The leases' part of it.
    pub memory_leased: u64,
    pub refusals: MemoryRefusals,
}

impl BackendHandle {
    /// Starts the executor thread. The thread ends when every handle is dropped.
    pub fn spawn(runner: Box<dyn GraphRunner>, options: ExecutorOptions) -> std::io::Result<BackendHandle> {
        let shared = Arc::new(Shared {
            queue: Mutex::default(),
            wake: Condvar::new(),
            capacity: options.capacity.max(1),
            memory: Mutex::new(options.memory),
            probe: options.probe,
        });
        let worker_shared = shared.clone();
        std::thread::Builder::new().name("scnerf-inference".into()).spawn(move || worker(runner, worker_shared))?;
        Ok(BackendHandle { _closer: Arc::new(Closer(shared.clone())), shared })
    }

    /// Admits a request whose graph runs, `work` in all, must finish by `deadline`, and which
    /// adds at most `memory` bytes to the process: `TooLarge` when `memory` exceeds the whole
    /// budget, `QueueFull` when `capacity` requests are already admitted, `MemoryBusy` when the
    /// admitted requests' estimates leave less than `memory`, `WouldMissDeadline` when the
    /// estimate says it cannot finish in time (see the module doc). The request leaves when the
    /// ticket is dropped.
    pub fn admit(&self, deadline: Instant, work: Work, memory: u64) -> Result<Ticket, BackendError> {
        let budget = self.shared.memory().for_requests();
        let mut q = self.shared.lock();
        if q.stopped {
            return Err(BackendError::Stopped);
        }
        if memory > budget {
            return Err(q.too_large(memory, budget));
        }
        if q.requests.len() >= self.shared.capacity {
            return Err(BackendError::QueueFull);
        }
        if let Some(ahead_secs) = q.would_miss(Instant::now(), deadline, work) {
            return Err(BackendError::WouldMissDeadline { work_secs: work.secs(&q.rates), ahead_secs });
        }
        q.hold(budget, 0, memory)?;
        q.next_ticket += 1;
        let id = q.next_ticket;
        q.requests.insert(id, Admitted { deadline, remaining: work, memory, jobs: VecDeque::new() });
        Ok(Ticket { id, deadline, shared: self.shared.clone() })
    }

    /// Holds `bytes` of the memory budget outside any admitted request (see [`MemoryLease`]):
    /// `TooLarge` when they exceed what requests may have at all, `MemoryBusy` when the budget
    /// lacks room now.
    pub fn lease(&self, bytes: u64) -> Result<MemoryLease, BackendError> {
        let mut lease = MemoryLease { bytes: 0, shared: self.shared.clone() };
        lease.grow(bytes)?;
        Ok(lease)
    }

    /// Forgets the measured rates: the graphs count as unmeasured (admitted without an estimate)
    /// until they run again. The warm-up calls it: its tiny runs are mostly fixed cost, and their
    /// seconds per unit, extrapolated to a real request, would refuse it on an idle server.
    pub fn forget_rates(&self) {
        self.shared.lock().rates = Rates::default();
    }

    /// Sets aside `bytes` of the memory budget for what is held apart from requests (the
    /// process at rest, the scene cache); fails when that leaves nothing for requests.
    pub fn reserve(&self, bytes: u64) -> Result<MemoryBudget, String> {
        let mut memory = self.shared.memory.lock().unwrap_or_else(|p| p.into_inner());
        if bytes >= memory.total {
            return Err(format!(
                "the memory budget ({} MiB) leaves nothing for requests: the server holds {} MiB at rest \
                 with the scene cache",
                memory.total >> 20,
                bytes >> 20
            ));
        }
        memory.reserved = bytes;
        Ok(*memory)
    }

    /// The per-stage memory probe, when `--memory-probe` is on.
    pub fn probe(&self) -> Option<&MemoryProbe> {
        self.shared.probe.as_deref()
    }

    pub fn stats(&self) -> QueueStats {
        let memory = self.shared.memory();
        let q = self.shared.lock();
        QueueStats {
            admitted: q.requests.len(),
            queued_jobs: q.queued_jobs,
            capacity: self.shared.capacity,
            memory,
            memory_in_use: q.memory_in_use,
            memory_leased: q.memory_leased,
            refusals: q.refusals,
        }
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

    /// Queues one graph run of `units` of work (see `Work`) now and returns a future of its
    /// outputs. Queuing happens before the future is first polled, so a caller can keep several
    /// runs in flight (see `pipeline::chunks`).
    pub fn run(
        &self,
        graph: GraphKind,
        units: f64,
        inputs: NamedTensors,
    ) -> impl Future<Output = Result<Outputs, BackendError>> + Send + 'static {
        self.run_job(graph, units, Inputs::Ready(inputs), false)
    }

    /// [`Ticket::run`] for the request's last run of `graph` (see `GraphRunner::run_and_release`).
    pub fn run_last(
        &self,
        graph: GraphKind,
        units: f64,
        inputs: NamedTensors,
    ) -> impl Future<Output = Result<Outputs, BackendError>> + Send + 'static {
        self.run_job(graph, units, Inputs::Ready(inputs), true)
    }

    /// [`Ticket::run`] with inputs that `prepare` makes on the executor thread when the job's turn
    /// comes (see the module doc).
    pub fn run_prepared(
        &self,
        graph: GraphKind,
        units: f64,
        prepare: impl FnOnce() -> NamedTensors + Send + 'static,
    ) -> impl Future<Output = Result<Outputs, BackendError>> + Send + 'static {
        self.run_job(graph, units, Inputs::Prepared(Box::new(prepare)), false)
    }

    fn run_job(
        &self,
        graph: GraphKind,
        units: f64,
        inputs: Inputs,
        last: bool,
    ) -> impl Future<Output = Result<Outputs, BackendError>> + Send + 'static {
        let (reply, rx) = oneshot::channel();
        let span = Span::current();
        let job = Job { ticket: self.id, graph, units, inputs, reply, span, deadline: self.deadline, last };
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
            Ok(Outputs { graph, tensors: outputs })
        }
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        self.shared.lock().release(self.id);
    }
}

/// Memory held against the budget beside the admitted requests' estimates (a request's body as
/// it arrives, a capture's files while they are parsed); given back when dropped.
pub struct MemoryLease {
    bytes: u64,
    shared: Arc<Shared>,
}

impl MemoryLease {
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Holds `more` bytes more, or fails as [`BackendHandle::lease`] does (and holds as before).
    pub fn grow(&mut self, more: u64) -> Result<(), BackendError> {
        let budget = self.shared.memory().for_requests();
        let mut q = self.shared.lock();
        q.hold(budget, self.bytes, more)?;
        q.memory_leased += more;
        self.bytes += more;
        Ok(())
    }
}

impl Drop for MemoryLease {
    fn drop(&mut self) {
        let mut q = self.shared.lock();
        q.memory_in_use -= self.bytes;
        q.memory_leased -= self.bytes;
    }
}

/// Waits for the next job and says whether it is the last of its request's runs of its graph
/// with no other job waiting (then the runner releases what it keeps); `None` once the queue is
/// closed and empty.
fn next_job(shared: &Shared) -> Option<(Job, bool)> {
    let mut q = shared.lock();
    loop {
        if let Some(job) = q.pop() {
            let release = job.last && q.queued_jobs == 0;
            return Some((job, release));
        }
        if q.closed {
            q.stopped = true;
            return None;
        }
        q = shared.wake.wait(q).unwrap_or_else(|p| p.into_inner());
    }
}

fn worker(mut runner: Box<dyn GraphRunner>, shared: Arc<Shared>) {
    while let Some((mut job, release)) = next_job(&shared) {
        // The request went away (client disconnected, deadline passed): skip its work.
        if job.reply.is_closed() {
            continue;
        }
        if Instant::now() >= job.deadline {
            let _ = job.reply.send(Err(BackendError::DeadlineExceeded));
            continue;
        }
        let _entered = job.span.enter();
        let probe = shared.probe.as_deref().map(MemoryProbe::start);
        let started = Instant::now();
        {
            let mut q = shared.lock();
            let secs = job.units * q.rates.per_unit(job.graph, true);
            q.running = Some(Running { deadline: job.deadline, secs, started });
        }
        let inputs = std::mem::replace(&mut job.inputs, Inputs::Ready(Vec::new()));
        let result = run_guarded(runner.as_mut(), job.graph, inputs, release);
        let took = started.elapsed().as_secs_f64();
        if let Some(probe) = probe {
            probe.finish(job.graph.name());
        }
        tracing::debug!(graph = %job.graph, ms = took * 1e3, "graph run");
        {
            let mut q = shared.lock();
            q.running = None;
            q.done(&job, took);
        }
        let _ = job.reply.send(result);
    }
}

/// A panic inside a runner or while the inputs are made must not take the process (or the
/// executor thread) down.
fn run_guarded(
    runner: &mut dyn GraphRunner,
    graph: GraphKind,
    inputs: Inputs,
    release: bool,
) -> Result<NamedTensors, BackendError> {
    let run = || {
        let inputs = inputs.make(graph);
        if release {
            runner.run_and_release(graph, &inputs)
        } else {
            runner.run(graph, &inputs)
        }
    };
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(run)).unwrap_or_else(|panic| {
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::mpsc;

    /// Records the tag (first input value) of every job it runs and sleeps that many
    /// milliseconds; the first job waits for a signal so that a test can fill the queue before
    /// anything runs.
    struct Recorder {
        order: Arc<Mutex<Vec<u32>>>,
        gate: Option<mpsc::Receiver<()>>,
    }

    impl GraphRunner for Recorder {
        fn run(&mut self, _graph: GraphKind, inputs: &NamedTensors) -> Result<NamedTensors, BackendError> {
            if let Some(gate) = self.gate.take() {
                let _ = gate.recv();
            }
            let tag = inputs[0].1.first().copied().unwrap_or_default() as u32;
            self.order.lock().unwrap().push(tag);
            std::thread::sleep(Duration::from_millis(u64::from(tag)));
            Ok(vec![])
        }
    }

    fn tagged(tag: u32) -> NamedTensors {
        vec![("tag".into(), ndarray::arr1(&[tag as f32]).into_shared().into_dyn())]
    }

    fn recorder() -> (BackendHandle, Arc<Mutex<Vec<u32>>>, mpsc::Sender<()>) {
        let order = Arc::new(Mutex::new(Vec::new()));
        let (open, gate) = mpsc::channel();
        let backend = BackendHandle::spawn(
            Box::new(Recorder { order: order.clone(), gate: Some(gate) }),
            ExecutorOptions::with_capacity(4),
        )
        .unwrap();
        (backend, order, open)
    }

    fn in_secs(secs: u64) -> Instant {
        Instant::now() + Duration::from_secs(secs)
    }

    fn far() -> Instant {
        in_secs(60)
    }

    const NONE: Work = Work([0.0; GraphKind::ALL.len()]);

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

    /// Sets the rates admission plans with, as if measured without any scatter: admission's
    /// arithmetic checked apart from the timing of the machine that runs the test.
    fn plan_with(backend: &BackendHandle, graph: GraphKind, secs_per_unit: f64) {
        backend.shared.lock().rates.0[graph.index()] = Some(Rate { secs: secs_per_unit, units: 1.0, deviation: 0.0 });
    }

    #[tokio::test]
    async fn admission_refuses_work_that_cannot_finish_by_its_deadline() {
        let (backend, _order, open) = recorder();
        open.send(()).unwrap();
        plan_with(&backend, GraphKind::Renderer, 1e-3);
        let ms = |ms: u64| Instant::now() + Duration::from_millis(ms);
        let rays = |n: f64| Work::of(GraphKind::Renderer, n);
        // Unmeasured graphs cost nothing yet.
        assert!(backend.admit(ms(1), Work::of(GraphKind::Encoder, 1e9), 0).is_ok());
        // 500 ms of work due in 200 ms: refused at once.
        let refused = backend.admit(ms(200), rays(500.0), 0);
        assert!(matches!(refused, Err(BackendError::WouldMissDeadline { .. })), "{:?}", refused.err());
        let a = backend.admit(ms(1000), rays(500.0), 0).unwrap();
        // Fits before `a` but would push `a` past its deadline: refused to protect `a`.
        let pushy = backend.admit(ms(600), rays(550.0), 0);
        assert!(matches!(pushy, Err(BackendError::WouldMissDeadline { .. })));
        // Fits before `a`, and `a` still meets its deadline.
        let b = backend.admit(ms(600), rays(300.0), 0).unwrap();
        // After both: 800 ms of work ahead.
        match backend.admit(ms(900), rays(200.0), 0) {
            Err(BackendError::WouldMissDeadline { ahead_secs, .. }) => {
                assert!((0.7..1.0).contains(&ahead_secs), "{ahead_secs}")
            }
            other => panic!("{:?}", other.err()),
        }
        assert!(backend.admit(far(), rays(200.0), 0).is_ok());
        drop((a, b));
    }

    #[tokio::test]
    async fn forgotten_rates_admit_what_they_would_have_refused() {
        let (backend, _order, open) = recorder();
        open.send(()).unwrap();
        let probe = backend.admit(far(), NONE, 0).unwrap();
        probe.run(GraphKind::Renderer, 1.0, tagged(20)).await.unwrap();
        drop(probe);
        let soon = || Instant::now() + Duration::from_millis(200);
        let rays = Work::of(GraphKind::Renderer, 100.0);
        assert!(matches!(backend.admit(soon(), rays, 0), Err(BackendError::WouldMissDeadline { .. })));
        backend.forget_rates();
        assert!(backend.admit(soon(), rays, 0).is_ok());
    }

    #[tokio::test]
    async fn admission_is_bounded_and_released_on_drop() {
        let (backend, _order, _open) = recorder();
        let tickets: Vec<Ticket> = (0..4).map(|_| backend.admit(far(), NONE, 0).unwrap()).collect();
        assert!(matches!(backend.admit(far(), NONE, 0), Err(BackendError::QueueFull)));
        assert_eq!(backend.stats().admitted, 4);
        drop(tickets);
        assert_eq!(backend.stats().admitted, 0);
        assert!(backend.admit(far(), NONE, 0).is_ok());
    }

    /// An executor whose requests may hold `total` bytes of estimates, after `reserved`.
    fn budgeted(total: u64, reserved: u64) -> (BackendHandle, mpsc::Sender<()>) {
        let (open, gate) = mpsc::channel();
        let recorder = Recorder { order: Arc::default(), gate: Some(gate) };
        let options = ExecutorOptions { capacity: 8, memory: MemoryBudget { total, reserved }, probe: None };
        (BackendHandle::spawn(Box::new(recorder), options).unwrap(), open)
    }

    #[tokio::test]
    async fn admission_by_memory_sums_the_estimates_within_the_budget() {
        let (backend, open) = budgeted(1000, 0);
        open.send(()).unwrap();
        let a = backend.admit(far(), NONE, 600).unwrap();
        let b = backend.admit(far(), NONE, 400).unwrap(); // exactly the budget
        assert!(matches!(backend.admit(far(), NONE, 1), Err(BackendError::MemoryBusy { .. })));
        assert_eq!(backend.stats().memory_in_use, 1000);
        drop(a);
        assert_eq!(backend.stats().memory_in_use, 400);
        let c = backend.admit(far(), NONE, 600).unwrap();
        // Larger than the whole budget: refused for good, however empty the executor is.
        drop((b, c));
        assert!(matches!(
            backend.admit(far(), NONE, 1001),
            Err(BackendError::TooLarge { needed_mib: 1, budget_mib: 0 })
        ));
        // What is reserved (the process at rest, the scene cache) is not the requests'.
        let reserved = backend.reserve(700).unwrap();
        assert_eq!(reserved.for_requests(), 300);
        assert!(matches!(backend.admit(far(), NONE, 301), Err(BackendError::TooLarge { .. })));
        assert!(backend.reserve(1000).is_err(), "a reservation must leave requests something");
        let stats = backend.stats();
        assert_eq!(stats.refusals, MemoryRefusals { busy: 1, too_large: 2 });
        assert_eq!((stats.memory.total, stats.memory.reserved, stats.memory_in_use), (1000, 700, 0));
    }

    /// Retry-After of a request refused for memory: the measured seconds of the admitted
    /// requests that must finish first (earliest deadline first) to free what it needs.
    #[tokio::test]
    async fn a_memory_refusal_says_how_long_until_enough_is_freed() {
        let (backend, open) = budgeted(1000, 0);
        open.send(()).unwrap();
        plan_with(&backend, GraphKind::Renderer, 1e-3);
        let rays = |n: f64| Work::of(GraphKind::Renderer, n);
        let _first = backend.admit(in_secs(10), rays(300.0), 500).unwrap();
        let _second = backend.admit(in_secs(20), rays(700.0), 500).unwrap();
        // 200 bytes are needed: the first (due sooner, ~0.3 s) frees enough.
        match backend.admit(far(), NONE, 200) {
            Err(BackendError::MemoryBusy { ahead_secs, .. }) => {
                assert!((0.29..0.31).contains(&ahead_secs), "{ahead_secs}")
            }
            other => panic!("{:?}", other.err()),
        }
        // 900 bytes: both must finish (~1 s).
        match backend.admit(far(), NONE, 900) {
            Err(BackendError::MemoryBusy { ahead_secs, .. }) => {
                assert!((0.99..1.01).contains(&ahead_secs), "{ahead_secs}")
            }
            other => panic!("{:?}", other.err()),
        }
    }

    #[tokio::test]
    async fn leases_hold_the_budget_beside_admitted_requests() {
        let (backend, open) = budgeted(1000, 0);
        open.send(()).unwrap();
        let mut body = backend.lease(600).unwrap();
        assert!(matches!(backend.admit(far(), NONE, 500), Err(BackendError::MemoryBusy { .. })));
        body.grow(300).unwrap();
        assert_eq!((body.bytes(), backend.stats().memory_in_use), (900, 900));
        // Past the whole budget by itself: it can never fit.
        assert!(matches!(body.grow(200), Err(BackendError::TooLarge { .. })));
        // Within it, but not beside another lease.
        let other = backend.lease(50).unwrap();
        assert!(matches!(body.grow(60), Err(BackendError::MemoryBusy { .. })));
        assert_eq!(body.bytes(), 900, "a refused growth holds what was held");
        drop(other);
        assert!(matches!(backend.lease(1001), Err(BackendError::TooLarge { .. })));
        drop(body);
        assert_eq!(backend.stats().memory_in_use, 0);
        let admitted = backend.admit(far(), NONE, 500).unwrap();
        assert!(matches!(backend.lease(501), Err(BackendError::MemoryBusy { .. })));
        drop(admitted);
    }

    /// A graph run cannot be interrupted: a request due before the one whose run is in
    /// progress still waits for the rest of that run.
    #[tokio::test]
    async fn the_run_in_progress_counts_ahead_of_a_request_due_sooner() {
        let (backend, _order, open) = recorder();
        open.send(()).unwrap();
        plan_with(&backend, GraphKind::Renderer, 1e-3);
        let late = backend.admit(far(), Work::of(GraphKind::Renderer, 400.0), 0).unwrap();
        let long_run = late.run(GraphKind::Renderer, 400.0, tagged(400));
        tokio::time::sleep(Duration::from_millis(50)).await;
        // 100 ms of work due in 250 ms: it would fit, were the 400 ms run not in the way.
        let soon = Instant::now() + Duration::from_millis(250);
        match backend.admit(soon, Work::of(GraphKind::Renderer, 100.0), 0) {
            Err(BackendError::WouldMissDeadline { ahead_secs, .. }) => {
                assert!(ahead_secs > 0.15 && ahead_secs <= 0.4, "{ahead_secs}")
            }
            other => panic!("{:?}", other.err()),
        }
        long_run.await.unwrap();
        drop(late);
        plan_with(&backend, GraphKind::Renderer, 1e-3);
        assert!(backend
            .admit(Instant::now() + Duration::from_millis(250), Work::of(GraphKind::Renderer, 100.0), 0)
            .is_ok());
    }

    /// Runs whose times scatter make admission plan with more than their mean.
    #[tokio::test]
    async fn scattered_run_times_are_planned_on_the_slow_side() {
        let mut rates = Rates::default();
        for took in [0.005, 0.035, 0.005, 0.035, 0.005, 0.035] {
            rates.record(GraphKind::Renderer, 20.0, took); // 0.25 or 1.75 ms a unit
        }
        let rate = rates.0[GraphKind::Renderer.index()].unwrap();
        assert!((0.8e-3..1.3e-3).contains(&rate.mean()), "{rate:?}");
        assert!(rate.planned() > rate.mean() + 1e-3, "{rate:?}");
        let steady = (0..6).fold(Rates::default(), |mut r, _| {
            r.record(GraphKind::Renderer, 20.0, 0.02);
            r
        });
        assert!((steady.per_unit(GraphKind::Renderer, true) - 1e-3).abs() < 1e-12);
        // A run of 2 units at 10 ms a unit (its fixed cost) moves a rate built on runs of 20 to
        // 1.4 ms, not to the 3.7 ms of an average per run.
        let mut tail = steady;
        tail.record(GraphKind::Renderer, 2.0, 0.02);
        assert!(tail.per_unit(GraphKind::Renderer, false) < 1.5e-3, "{tail:?}");

        let (backend, _order, open) = recorder();
        open.send(()).unwrap();
        backend.shared.lock().rates = rates;
        // Another request is admitted: the margin applies (alone, a request is planned at the mean).
        let _other = backend.admit(far(), NONE, 0).unwrap();
        // At the mean (~1 ms a unit) 300 units take ~300 ms: within 500 ms, but not on the slow side.
        let due = Instant::now() + Duration::from_millis(500);
        assert!(matches!(
            backend.admit(due, Work::of(GraphKind::Renderer, 300.0), 0),
            Err(BackendError::WouldMissDeadline { .. })
        ));
        assert!(backend
            .admit(Instant::now() + Duration::from_secs(2), Work::of(GraphKind::Renderer, 300.0), 0)
            .is_ok());
    }

    /// Records (tag, released) per run; the first run waits for a signal.
    struct Releases {
        runs: Arc<Mutex<Vec<(u32, bool)>>>,
        gate: Option<mpsc::Receiver<()>>,
    }

    impl Releases {
        fn record(&mut self, inputs: &NamedTensors, released: bool) -> Result<NamedTensors, BackendError> {
            if let Some(gate) = self.gate.take() {
                let _ = gate.recv();
            }
            let tag = inputs[0].1.first().copied().unwrap_or_default() as u32;
            self.runs.lock().unwrap().push((tag, released));
            Ok(vec![])
        }
    }

    impl GraphRunner for Releases {
        fn run(&mut self, _graph: GraphKind, inputs: &NamedTensors) -> Result<NamedTensors, BackendError> {
            self.record(inputs, false)
        }

        fn run_and_release(&mut self, _graph: GraphKind, inputs: &NamedTensors) -> Result<NamedTensors, BackendError> {
            self.record(inputs, true)
        }
    }

    /// A request's last run releases the runner's kept memory only when no other job waits: a
    /// busy executor keeps its arena for the next request.
    #[tokio::test]
    async fn the_last_run_releases_only_when_nothing_else_waits() {
        let runs = Arc::new(Mutex::new(Vec::new()));
        let (open, gate) = mpsc::channel();
        let runner = Releases { runs: runs.clone(), gate: Some(gate) };
        let backend = BackendHandle::spawn(Box::new(runner), ExecutorOptions::with_capacity(4)).unwrap();
        let a = backend.admit(in_secs(10), NONE, 0).unwrap();
        let b = backend.admit(in_secs(20), NONE, 0).unwrap();
        let held = a.run(GraphKind::Encoder, 0.0, tagged(0)); // waits at the gate
        tokio::time::sleep(Duration::from_millis(50)).await;
        let a_last = a.run_last(GraphKind::Renderer, 0.0, tagged(1)); // b's run still waits after it
        let b_last = b.run_last(GraphKind::Renderer, 0.0, tagged(2)); // nothing after it
        open.send(()).unwrap();
        held.await.unwrap();
        a_last.await.unwrap();
        b_last.await.unwrap();
        assert_eq!(*runs.lock().unwrap(), vec![(0, false), (1, false), (2, true)]);
    }

    #[tokio::test]
    async fn a_dropped_request_leaves_no_jobs_and_expired_jobs_do_not_run() {
        let (backend, order, open) = recorder();
        let blocker = backend.admit(far(), NONE, 0).unwrap();
        let first = blocker.run(GraphKind::Encoder, 0.0, tagged(0));
        tokio::time::sleep(Duration::from_millis(50)).await;
        let gone = backend.admit(far(), NONE, 0).unwrap();
        let abandoned: Vec<_> = (0..5).map(|_| gone.run(GraphKind::Renderer, 0.0, tagged(1))).collect();
        drop(abandoned);
        drop(gone); // its five jobs leave the queue
        let late = backend.admit(Instant::now() + Duration::from_millis(20), NONE, 0).unwrap();
        let expired = late.run(GraphKind::Renderer, 0.0, tagged(2));
        assert_eq!(backend.stats().queued_jobs, 1);
        tokio::time::sleep(Duration::from_millis(40)).await;
        open.send(()).unwrap();
        first.await.unwrap();
        assert!(matches!(expired.await, Err(BackendError::DeadlineExceeded)));
        assert_eq!(*order.lock().unwrap(), vec![0]);
    }

    /// Prepared inputs are made on the executor thread in the job's turn (after the job queued
    /// before it), and a panic while making them is the run's error, not the executor's end.
    #[tokio::test]
    async fn prepared_inputs_are_made_in_the_jobs_turn_on_the_executor() {
        let (backend, order, open) = recorder();
        let ticket = backend.admit(far(), NONE, 0).unwrap();
        let first = ticket.run(GraphKind::Encoder, 0.0, tagged(0));
        let made_on = Arc::new(Mutex::new((None, 0)));
        let (made, made_order) = (made_on.clone(), order.clone());
        let prepared = ticket.run_prepared(GraphKind::CostConv, 0.0, move || {
            *made.lock().unwrap() = (std::thread::current().name().map(String::from), made_order.lock().unwrap().len());
            tagged(1)
        });
        let failing = ticket.run_prepared(GraphKind::CostConv, 0.0, || panic!("no inputs"));
        open.send(()).unwrap();
        first.await.unwrap();
        prepared.await.unwrap();
        let err = failing.await.unwrap_err();
        assert!(matches!(&err, BackendError::Run { message, .. } if message == "no inputs"), "{err}");
        assert_eq!(*made_on.lock().unwrap(), (Some("scnerf-inference".to_string()), 1));
        assert_eq!(*order.lock().unwrap(), vec![0, 1]);
        ticket.run(GraphKind::Renderer, 0.0, tagged(2)).await.unwrap();
    }
}
