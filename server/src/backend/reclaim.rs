//! Memory held outside the executor's requests that counts against its budget and that it may
//! reclaim to admit one: the scene cache. Its limit is not set aside up front: what it holds
//! counts as it holds it, and when a request or a lease finds too little room, idle entries
//! (those no request uses) are evicted to make it.

use std::sync::Arc;

use super::budget::Reclaim;
use super::executor::BackendHandle;
use super::shared::Shared;

impl BackendHandle {
    /// Counts what `reclaim` holds against the memory budget, and lets admission free it.
    pub fn set_reclaim(&self, reclaim: Arc<dyn Reclaim>) {
        *self.shared.reclaim.lock().unwrap_or_else(|p| p.into_inner()) = Some(reclaim);
    }
}

impl Shared {
    fn reclaimable(&self) -> Option<Arc<dyn Reclaim>> {
        self.reclaim.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }

    /// Bytes the reclaimable memory holds now (0 without one).
    pub(super) fn held_outside(&self) -> u64 {
        self.reclaimable().map_or(0, |r| r.held())
    }

    /// Before `more` bytes are held (within `budget`): when the admitted requests, the leases
    /// and the reclaimable memory leave less, frees the difference from the reclaimable memory.
    /// Called without the queue's lock (the cache takes its own).
    pub(super) fn make_room(&self, budget: u64, more: u64) {
        let Some(reclaim) = self.reclaimable() else { return };
        let in_use = self.lock().memory_in_use;
        let short = (in_use + reclaim.held()).saturating_add(more).saturating_sub(budget);
        if short > 0 {
            let freed = reclaim.reclaim(short);
            tracing::debug!(short_mib = short >> 20, freed_mib = freed >> 20, "reclaimed idle memory");
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::sync::Arc;

    use crate::backend::testkit::{budgeted, far, NONE};
    use crate::backend::{BackendError, Reclaim};

    /// A cache of `held` bytes, of which `idle` may go.
    struct Cache {
        held: AtomicU64,
        idle: AtomicU64,
    }

    impl Reclaim for Cache {
        fn held(&self) -> u64 {
            self.held.load(Ordering::SeqCst)
        }

        fn reclaim(&self, bytes: u64) -> u64 {
            let freed = bytes.min(self.idle.load(Ordering::SeqCst));
            self.idle.fetch_sub(freed, Ordering::SeqCst);
            self.held.fetch_sub(freed, Ordering::SeqCst);
            freed
        }
    }

    /// A request the idle part of the cache makes room for is admitted, evicting no more than
    /// it needs; one that would need what requests use is refused as busy.
    #[tokio::test]
    async fn idle_cached_memory_is_reclaimed_to_admit_a_request() {
        let (backend, _open) = budgeted(1000, 100);
        let cache = Arc::new(Cache { held: 600.into(), idle: 500.into() });
        backend.set_reclaim(cache.clone());
        let first = backend.admit(far(), NONE, 200).expect("900 budget: 600 cached, 200 fit");
        let second = backend.admit(far(), NONE, 400).expect("300 of the idle cache go");
        assert_eq!((cache.held(), backend.stats().memory_in_use), (300, 600));
        let busy = backend.admit(far(), NONE, 300);
        assert!(matches!(busy, Err(BackendError::MemoryBusy { .. })), "{:?}", busy.err());
        assert_eq!(cache.held(), 100, "the idle part went; what is in use stays");
        drop((first, second));
    }
}
