//! Admission by time: a request is admitted only if its work, turned into seconds at the
//! measured rates, finishes by its deadline without making an admitted request miss its own.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use super::executor::BackendHandle;
use super::queue::{Admitted, Queue};
use super::rates::{Rates, Work};
use super::ticket::Ticket;
use super::BackendError;

impl Queue {
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
}

impl BackendHandle {
    /// Admits a request whose graph runs, `work` in all, must finish by `deadline`, and which
    /// adds at most `memory` bytes to the process: `TooLarge` when `memory` exceeds the whole
    /// budget, `QueueFull` when `capacity` requests are already admitted, `MemoryBusy` when the
    /// admitted requests' estimates leave less than `memory`, `WouldMissDeadline` when the
    /// estimate says it cannot finish in time (see the `backend` module doc). The request
    /// leaves when the ticket is dropped.
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

    /// Forgets the measured rates: the graphs count as unmeasured (admitted without an estimate)
    /// until they run again. The warm-up calls it: its tiny runs are mostly fixed cost, and their
    /// seconds per unit, extrapolated to a real request, would refuse it on an idle server.
    pub fn forget_rates(&self) {
        self.shared.lock().rates = Rates::default();
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
        backend.shared.lock().rates = scattered_rates();
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
