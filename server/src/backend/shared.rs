//! What the executor thread and the requests' handles share: the queue, the wake-up, the budget.

use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::Duration;

use super::budget::{MemoryBudget, Reclaim};
use super::queue::Queue;
use crate::sysmem::MemoryProbe;

pub(super) struct Shared {
    pub(super) queue: Mutex<Queue>,
    /// The executor waits on it for jobs.
    pub(super) wake: Condvar,
    /// The watchdog waits on it for the run in progress to change (`watchdog.rs`).
    pub(super) watch: Condvar,
    pub(super) capacity: usize,
    pub(super) memory: Mutex<MemoryBudget>,
    pub(super) probe: Option<Arc<MemoryProbe>>,
    pub(super) max_queue_wait: Option<Duration>,
    /// The scene cache, whose bytes count against the budget (`reclaim.rs`).
    pub(super) reclaim: Mutex<Option<Arc<dyn Reclaim>>>,
}

impl Shared {
    /// A poisoned lock only means a thread panicked while holding it; the queue stays consistent
    /// (every update is a single push/pop), so keep serving.
    pub(super) fn lock(&self) -> MutexGuard<'_, Queue> {
        self.queue.lock().unwrap_or_else(|p| p.into_inner())
    }

    pub(super) fn memory(&self) -> MemoryBudget {
        *self.memory.lock().unwrap_or_else(|p| p.into_inner())
    }
}
