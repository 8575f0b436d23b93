//! Memory held against the budget outside any admitted request, and the part of the budget set
//! aside for the process at rest.

use std::sync::Arc;

use super::budget::MemoryBudget;
use super::executor::BackendHandle;
use super::shared::Shared;
use super::BackendError;

impl BackendHandle {
    /// Holds `bytes` of the memory budget outside any admitted request (see [`MemoryLease`]):
    /// `TooLarge` when they exceed what requests may have at all, `MemoryBusy` when the budget
    /// lacks room now.
    pub fn lease(&self, bytes: u64) -> Result<MemoryLease, BackendError> {
        let mut lease = MemoryLease { bytes: 0, shared: self.shared.clone() };
        lease.grow(bytes)?;
        Ok(lease)
    }

    /// Sets aside `bytes` of the memory budget for what is held apart from requests (the
    /// process at rest); fails when that leaves nothing for requests. (The scene cache counts
    /// as it fills, see `reclaim.rs`.)
    pub fn reserve(&self, bytes: u64) -> Result<MemoryBudget, String> {
        let mut memory = self.shared.memory.lock().unwrap_or_else(|p| p.into_inner());
        if bytes >= memory.total {
            return Err(format!(
                "the memory budget ({} MiB) leaves nothing for requests: the server holds {} MiB at rest",
                memory.total >> 20,
                bytes >> 20
            ));
        }
        memory.reserved = bytes;
        Ok(*memory)
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
        self.shared.make_room(budget, more);
        let outside = self.shared.held_outside();
        let mut q = self.shared.lock();
        q.hold(budget, self.bytes, more, outside)?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::budget::MemoryRefusals;
    use crate::backend::testkit::{budgeted, far, in_secs, plan_with, NONE};
    use crate::backend::Work;
    use crate::bundle::GraphKind;

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
    /// requests that must finish first (earliest turn first) to free what it needs.
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
}
