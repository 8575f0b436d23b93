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
//! the request with the earliest turn: its deadline when its client chose one, else its fair
//! turn among the clients (`fair.rs`). Round robin, the policy before, finished concurrent
//! requests together: under overload all of them late. Earliest deadline first finishes as many
//! as the executor's speed allows; the fair turns keep a client's flood behind itself.
//!
//! Admission refuses (503 + Retry-After, at once rather than a 504 later) a request that cannot
//! finish by its deadline given the work admitted before it, or whose work would make an
//! admitted request miss its deadline. Work is turned into time with the executor's measured
//! seconds per unit (`Rates`, each model's own), on the slow side when requests compete: the rate plus twice its
//! deviation (as TCP estimates a retransmission timeout from round trips), so that the noise of
//! a shared machine does not turn admitted requests into 504s. Before the first run of a graph
//! there is no estimate: admitted. A graph run is not preempted, so the rest of the run in
//! progress counts ahead of a request due sooner than its own; a run still going at its own
//! request's deadline is ended there (`watchdog.rs`). At most `capacity` requests
//! are admitted at once (`QueueFull`). Jobs whose request is gone (client disconnected: the
//! handler future and its `Ticket` were dropped) or past its deadline are dropped unrun.
//!
//! Admission by memory. Each request comes with an estimate of the most memory it adds to the
//! process (`pipeline::estimate`), and the executor admits requests while the estimates of the
//! admitted ones add up to at most its memory budget (`MemoryBudget`): beyond it the request is
//! refused at once (`MemoryBusy`, 503 + Retry-After: the seconds until enough admitted work has
//! finished), and a request whose estimate alone exceeds the budget is refused for good
//! (`TooLarge`, 422). Summing peaks over-counts (graph runs take turns on the one executor
//! thread, so only one run's working memory exists at a time) but cannot under-count. Memory a
//! request holds outside its estimate, its body as it arrives and a capture's files while they
//! are parsed, is held against the same budget by a `MemoryLease`. The scene cache counts too,
//! as it fills rather than its limit up front, and gives up idle scenes to admit a request
//! (`reclaim.rs`).
//!
//! Where each part lives: `executor.rs` (the thread, `BackendHandle`), `queue.rs` (the admitted
//! requests and their jobs, earliest turn first), `fair.rs` (the turns), `admission.rs`
//! (admission by time), `budget.rs` and `lease.rs` (the memory budget and its leases),
//! `reclaim.rs` (the scene cache in it), `rates.rs` (`Work` and the measured rates),
//! `ticket.rs` (`Ticket` and the `Outputs` of a run), `runner.rs` (the `GraphRunner` the
//! executor drives), `runners.rs` and `slots.rs` (several models' runners on the one executor,
//! each in a slot that a `BackendHandle` names), `watchdog.rs` and `stuck.rs` (a run past its
//! deadline: ended; one that does not end), `ort.rs` (ONNX Runtime's), `error.rs`
//! (`BackendError`).

mod admission;
mod budget;
pub mod device;
mod error;
mod executor;
mod fair;
mod lease;
pub mod ort;
mod queue;
mod rates;
mod reclaim;
mod runner;
mod runners;
mod shared;
mod slots;
mod stuck;
#[cfg(test)]
mod testkit;
mod ticket;
mod watchdog;

pub use admission::Due;
pub use budget::{MemoryBudget, MemoryRefusals, Reclaim};
pub use error::BackendError;
pub use executor::{BackendHandle, ExecutorOptions, QueueStats};
pub use lease::MemoryLease;
pub use queue::Client;
pub use rates::Work;
pub use runner::{GraphRunner, Interrupt, NamedTensors, Outputs, Tensor};
pub use stuck::STUCK_AFTER;
pub use ticket::Ticket;
