//! Admission by time: a request is admitted only if its work, turned into seconds at the
//! measured rates, finishes by its deadline without making an admitted request miss its own,
//! and, when its client chose no deadline, if the work ahead of it is within the server's
//! longest queue wait. Work ahead is the work of the requests whose turn comes first (`fair.rs`),
//! each at its own model's rates.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use super::executor::BackendHandle;
use super::queue::{Admitted, Client, Queue};
use super::rates::Work;
use super::ticket::Ticket;
use super::BackendError;

/// When a request is due, and whether its client chose that (`x-scnerf-deadline-ms`). Without
/// one a request has the server's long default deadline, and it is admitted only while its
/// expected wait stays within the longest queue wait (`ExecutorOptions::max_queue_wait`), or
/// its own expected service time when that is longer: a client is told at once to come back
/// (429 + Retry-After) rather than queued for minutes.
///
/// `client` is whom the request is for (the digest of its token): clients share the executor
/// fairly (`fair.rs`).
#[derive(Debug, Clone, Copy)]
pub struct Due {
    pub at: Instant,
    pub chosen: bool,
    pub client: Client,
}

/// A deadline as such, chosen by the client.
impl From<Instant> for Due {
    fn from(at: Instant) -> Due {
        Due { at, chosen: true, client: None }
    }
}

/// A request asking to be admitted: when it is due, its turn, its work's seconds.
struct Candidate {
    deadline: Instant,
    turn: Instant,
    secs: f64,
}

impl Queue {
    /// `Some(seconds of work ahead)` when `new` would miss its deadline, or make an admitted
    /// request miss one that it would meet now.
    fn would_miss(&self, now: Instant, new: &Candidate) -> Option<f64> {
        let queue = self.by_turn();
        let ahead = self.ahead(now, new.turn);
        let misses = |finish: f64, due: Instant| {
            let finish = Duration::try_from_secs_f64(finish).unwrap_or(Duration::MAX);
            now.checked_add(finish).is_none_or(|at| at > due)
        };
        if misses(ahead + new.secs, new.deadline) {
            return Some(ahead);
        }
        let mut finish = ahead;
        for &(_, due, secs) in queue.iter().filter(|(turn, _, _)| *turn > new.turn) {
            finish += secs;
            if misses(finish + new.secs, due) && !misses(finish, due) {
                return Some(finish);
            }
        }
        None
    }

    /// The admitted requests' turns, deadlines and seconds of remaining work, earliest turn first.
    fn by_turn(&self) -> Vec<(Instant, Instant, f64)> {
        let mut queue: Vec<(Instant, Instant, f64)> =
            self.requests.values().map(|r| (r.turn, r.deadline, self.remaining_secs(r))).collect();
        queue.sort_by_key(|&(turn, _, _)| turn);
        queue
    }

    /// Seconds of admitted work that run before a request whose turn is `turn`: that of the
    /// requests whose turn comes no later and, as a graph run cannot be interrupted, the rest of
    /// the run in progress of one whose turn is later. (A run of a request whose turn is sooner
    /// is in its remaining work.)
    fn ahead(&self, now: Instant, turn: Instant) -> f64 {
        let blocking = self
            .running
            .as_ref()
            .filter(|r| r.turn > turn)
            .map_or(0.0, |r| (r.secs - now.saturating_duration_since(r.started).as_secs_f64()).max(0.0));
        self.by_turn().iter().take_while(|(t, _, _)| *t <= turn).fold(blocking, |sum, (_, _, secs)| sum + secs)
    }
}

impl BackendHandle {
    /// Admits a request whose graph runs, `work` in all, must finish by `deadline`, and which
    /// adds at most `memory` bytes to the process: `TooLarge` when `memory` exceeds the whole
    /// budget, `QueueFull` when `capacity` requests are already admitted, `MemoryBusy` when the
    /// admitted requests' estimates leave less than `memory`, `WouldMissDeadline` when the
    /// estimate says it cannot finish in time (see the `backend` module doc), `QueueWaitTooLong`
    /// when its client chose no deadline and the work ahead of it exceeds both the longest queue
    /// wait and its own work. The request leaves when the ticket is dropped.
    pub fn admit(&self, due: impl Into<Due>, work: Work, memory: u64) -> Result<Ticket, BackendError> {
        let Due { at: deadline, chosen, client } = due.into();
        let budget = self.shared.memory().for_requests();
        self.shared.make_room(budget, memory);
        let outside = self.shared.held_outside();
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
        let now = Instant::now();
        let rates = q.rates.of(self.model);
        let planned = work.secs(&rates);
        // Alone, a request competes with nobody: planned at the mean rate. (Were the margin
        // kept, one slow run could refuse every request, and no run would come to correct it.)
        let alone = q.requests.is_empty() && q.running.is_none();
        let turn = if chosen { deadline } else { q.fair_turn(client, deadline, planned) };
        let new = Candidate { deadline, turn, secs: work.secs_with(&rates, !alone) };
        if let Some(ahead_secs) = q.would_miss(now, &new) {
            return Err(BackendError::WouldMissDeadline { work_secs: planned, ahead_secs });
        }
        if let Some(max) = self.shared.max_queue_wait.filter(|_| !chosen) {
            // A request may always wait as long as it will itself take: on a slow machine, or
            // for a large view, two requests may be in progress at once, whatever the bound.
            let max_secs = max.as_secs_f64().max(planned);
            let ahead_secs = q.ahead(now, turn);
            if ahead_secs > max_secs {
                return Err(BackendError::QueueWaitTooLong { ahead_secs, max_secs });
            }
        }
        q.hold(budget, 0, memory, outside)?;
        q.next_ticket += 1;
        let id = q.next_ticket;
        let model = self.model;
        q.requests
            .insert(id, Admitted { deadline, turn, model, client, remaining: work, memory, jobs: VecDeque::new() });
        Ok(Ticket { id, model: self.model, deadline, shared: self.shared.clone() })
    }

    /// Forgets this handle's model's measured rates: its graphs count as unmeasured (admitted
    /// without an estimate) until they run again. The warm-up calls it: its tiny runs are mostly
    /// fixed cost, and their seconds per unit, extrapolated to a real request, would refuse it on
    /// an idle server. Other models' rates stay.
    pub fn forget_rates(&self) {
        self.shared.lock().rates.forget(self.model);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::testkit::{far, plan_with, recorder, scattered_rates, tagged, NONE};
    use crate::bundle::GraphKind;

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

    /// A request whose client chose no deadline is admitted only while the work ahead of it is
    /// within the longest queue wait; one whose client chose a deadline, as long as it allows.
    #[tokio::test]
    async fn without_a_chosen_deadline_the_queue_wait_is_bounded() {
        use crate::backend::executor::ExecutorOptions;
        use crate::backend::testkit::Recorder;
        let options =
            ExecutorOptions { max_queue_wait: Some(Duration::from_millis(300)), ..ExecutorOptions::with_capacity(8) };
        let backend =
            BackendHandle::spawn(Box::new(Recorder { order: Default::default(), gate: None }), options).unwrap();
        plan_with(&backend, GraphKind::Renderer, 1e-3);
        let rays = |n: f64| Work::of(GraphKind::Renderer, n);
        let unchosen = || Due { at: far(), chosen: false, client: None };
        let first = backend.admit(far(), rays(500.0), 0).unwrap();
        match backend.admit(unchosen(), rays(100.0), 0) {
            Err(e @ BackendError::QueueWaitTooLong { ahead_secs, max_secs }) => {
                assert!((0.45..0.55).contains(&ahead_secs) && max_secs == 0.3, "{ahead_secs} {max_secs}");
                let api = crate::error::ApiError::from(e);
                assert_eq!(api.status(), 429);
                assert!(matches!(api, crate::error::ApiError::TooManyRequests { retry_after_secs: 1, .. }));
            }
            other => panic!("{:?}", other.err()),
        }
        let chosen = backend.admit(far(), rays(100.0), 0).expect("a deadline of the client's: within it");
        // A request may wait as long as it will itself take: 0.6 s ahead, 0.7 s of its own.
        let large = backend.admit(unchosen(), rays(700.0), 0).expect("a wait shorter than its own work");
        drop((first, large));
        let admitted = backend.admit(unchosen(), rays(100.0), 0).expect("100 ms ahead: within the wait");
        drop((chosen, admitted));
    }

    /// Rates are learnt per model: a slow model's runs, and forgetting its rates, leave another
    /// model's admission as it was.
    #[tokio::test]
    async fn a_slow_model_leaves_another_models_admission_unchanged() {
        use crate::backend::testkit::Recorder;
        let (default, _order, open) = recorder();
        open.send(()).unwrap();
        let slow = default.add_runner(Box::new(Recorder { order: Default::default(), gate: None }));
        plan_with(&default, GraphKind::Renderer, 1e-3);
        let soon = || Instant::now() + Duration::from_millis(200);
        let rays = Work::of(GraphKind::Renderer, 100.0);
        drop(default.admit(soon(), rays, 0).expect("100 ms of work due in 200 ms"));
        // One renderer run of 1 unit in 50 ms: 100 rays of the slow model plan at 5 s.
        let probe = slow.admit(far(), NONE, 0).unwrap();
        probe.run(GraphKind::Renderer, 1.0, tagged(50)).await.unwrap();
        drop(probe);
        assert!(matches!(slow.admit(soon(), rays, 0), Err(BackendError::WouldMissDeadline { .. })));
        drop(default.admit(soon(), rays, 0).expect("the default model's admission is unchanged"));
        let default_rate = || default.shared.lock().rates.of(default.model).per_unit(GraphKind::Renderer, false);
        assert_eq!(default_rate(), 1e-3);
        slow.forget_rates();
        assert_eq!(default_rate(), 1e-3);
        assert!(slow.admit(soon(), rays, 0).is_ok(), "the slow model's rates are forgotten");
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

    /// When requests compete, admission plans with the slow side of scattered run times (alone,
    /// a request is planned at the mean).
    #[tokio::test]
    async fn competing_requests_are_planned_on_the_slow_side_of_scattered_runs() {
        let (backend, _order, open) = recorder();
        open.send(()).unwrap();
        backend.shared.lock().rates.set(backend.model, scattered_rates());
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
}
