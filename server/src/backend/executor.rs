//! The executor: one thread that runs every graph, the handle requests reach it by, and what
//! they share with it.

use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use super::budget::{MemoryBudget, MemoryRefusals};
use super::queue::{Finish, Inputs, Job, Running};
use super::runner::Outputs;
use super::runners::Runners;
use super::shared::Shared;
use super::watchdog;
use super::{BackendError, GraphRunner, NamedTensors};
use crate::bundle::GraphKind;
use crate::sysmem::MemoryProbe;

/// Settings of the executor.
#[derive(Debug, Clone)]
pub struct ExecutorOptions {
    /// Requests admitted at once (`--queue-capacity`).
    pub capacity: usize,
    pub memory: MemoryBudget,
    /// Measures each graph run's memory (`--memory-probe`).
    pub probe: Option<Arc<MemoryProbe>>,
    /// The longest a request whose client chose no deadline may expect to wait for the executor
    /// (`--max-queue-wait-secs`; `None`: as long as its deadline allows).
    pub max_queue_wait: Option<Duration>,
}

impl ExecutorOptions {
    /// `capacity` requests at once, no memory bound, no probe.
    pub fn with_capacity(capacity: usize) -> ExecutorOptions {
        ExecutorOptions { capacity, memory: MemoryBudget::UNLIMITED, probe: None, max_queue_wait: None }
    }
}

/// Closes the queue when the last `BackendHandle` goes away.
pub(super) struct Closer(Arc<Shared>);

impl Drop for Closer {
    fn drop(&mut self) {
        self.0.lock().closed = true;
        self.0.wake.notify_all();
    }
}

/// Cheap-to-clone handle to the inference executor.
#[derive(Clone)]
pub struct BackendHandle {
    pub(super) shared: Arc<Shared>,
    /// The runner this handle's requests run on (`add_runner`): one executor serves every model.
    pub(super) model: usize,
    pub(super) closer: Arc<Closer>,
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
            watch: Condvar::new(),
            capacity: options.capacity.max(1),
            memory: Mutex::new(options.memory),
            probe: options.probe,
            max_queue_wait: options.max_queue_wait,
            reclaim: Mutex::new(None),
        });
        shared.lock().next_slot = 1;
        let worker_shared = shared.clone();
        let runners = Runners::new(runner);
        watchdog::spawn(shared.clone())?;
        std::thread::Builder::new().name("scnerf-inference".into()).spawn(move || worker(runners, worker_shared))?;
        Ok(BackendHandle { closer: Arc::new(Closer(shared.clone())), model: 0, shared })
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

/// Waits for the next job, with its request's turn, and says whether it is the last of its request's runs of its graph
/// with no other job waiting (then the runner releases what it keeps); `None` once the queue is
/// closed and empty.
fn next_job(shared: &Shared, runners: &mut Runners) -> Option<(Job, Instant, bool)> {
    let mut q = shared.lock();
    loop {
        runners.apply(std::mem::take(&mut q.runner_changes));
        if let Some((job, turn)) = q.pop() {
            let release = job.last && q.queued_jobs == 0;
            return Some((job, turn, release));
        }
        if q.closed {
            q.stopped = true;
            shared.watch.notify_all();
            return None;
        }
        q = shared.wake.wait(q).unwrap_or_else(|p| p.into_inner());
    }
}

fn worker(mut runners: Runners, shared: Arc<Shared>) {
    while let Some((mut job, turn, release)) = next_job(&shared, &mut runners) {
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
        let interrupt = runners.get(job.model).and_then(|runner| runner.interrupter());
        if let Some(interrupt) = &interrupt {
            interrupt.clear();
        }
        {
            let mut q = shared.lock();
            let secs = job.units * q.rates.of(job.model).per_unit(job.graph, true);
            q.running = Some(Running { turn, deadline: job.deadline, secs, started, interrupt, interrupted: false });
        }
        shared.watch.notify_all();
        let inputs = std::mem::replace(&mut job.inputs, Inputs::Ready(Vec::new()));
        let result = match runners.get(job.model) {
            Some(runner) => run_guarded(runner, job.graph, inputs, job.finish.take(), release),
            None => Err(BackendError::Run { graph: job.graph, message: "its model is no longer loaded".into() }),
        };
        let took = started.elapsed().as_secs_f64();
        if let Some(probe) = probe {
            probe.finish(job.graph.name());
        }
        tracing::debug!(graph = %job.graph, ms = took * 1e3, "graph run");
        let interrupted = {
            let mut q = shared.lock();
            q.done(&job, took);
            q.running.take().is_some_and(|run| run.interrupted)
        };
        let _ = job.reply.send(match result {
            Err(_) if interrupted => Err(BackendError::DeadlineExceeded),
            result => result,
        });
    }
}

/// A panic inside a runner or while the inputs are made or the outputs finished must not take
/// the process (or the executor thread) down.
fn run_guarded(
    runner: &mut dyn GraphRunner,
    graph: GraphKind,
    inputs: Inputs,
    finish: Option<Finish>,
    release: bool,
) -> Result<NamedTensors, BackendError> {
    let run = || {
        let inputs = inputs.make(graph);
        let outputs = if release { runner.run_and_release(graph, &inputs) } else { runner.run(graph, &inputs) }?;
        match finish {
            Some(finish) => finish(inputs, Outputs::new(graph, outputs)),
            None => Ok(outputs),
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

#[cfg(test)]
mod tests {
    use std::sync::mpsc;
    use std::time::Duration;

    use super::*;
    use crate::backend::testkit::{far, in_secs, recorder, tag_of, tagged, NONE};

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
            self.runs.lock().unwrap().push((tag_of(inputs), released));
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

    /// A job's finish turns its outputs into the job's on the executor thread, after the run,
    /// with the inputs the run read; a panic there is the run's error.
    #[tokio::test]
    async fn a_finish_runs_after_the_graph_with_its_inputs_on_the_executor() {
        let (backend, order, open) = recorder();
        open.send(()).unwrap();
        let ticket = backend.admit(far(), NONE, 0).unwrap();
        let ran = order.clone();
        let finished = ticket.run_prepared_then(
            GraphKind::VolumeNet,
            0.0,
            || tagged(3),
            move |inputs, _| {
                assert_eq!(*ran.lock().unwrap(), vec![3], "the graph ran first");
                let thread = std::thread::current().name().map(String::from);
                assert_eq!(thread.as_deref(), Some("scnerf-inference"));
                Ok(vec![("volume".into(), inputs[0].1.clone())])
            },
        );
        let mut outputs = finished.await.unwrap();
        let volume = outputs.take::<ndarray::Ix1>("volume", &[Some(1)]).unwrap();
        assert_eq!(volume.to_vec(), vec![3.0]);
        let failing = ticket.run_prepared_then(GraphKind::VolumeNet, 0.0, || tagged(4), |_, _| panic!("no volume"));
        let err = failing.await.unwrap_err();
        assert!(matches!(&err, BackendError::Run { message, .. } if message == "no volume"), "{err}");
        ticket.run(GraphKind::Renderer, 0.0, tagged(5)).await.unwrap();
        assert_eq!(*order.lock().unwrap(), vec![3, 4, 5]);
    }
}
