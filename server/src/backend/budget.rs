//! The memory budget the admitted requests' estimates and the leases add up to within, and the
//! refusals it makes.

/// What holds memory beside the requests, counted against the budget as it holds it, and can
/// give some of it back to admit one (the scene cache, see `reclaim.rs`).
pub trait Reclaim: Send + Sync {
    /// Bytes held now.
    fn held(&self) -> u64;
    /// Frees about `bytes` (more or less) from what no request uses; the bytes freed.
    fn reclaim(&self, bytes: u64) -> u64;
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
    /// Held apart from requests: the process at rest and one renderer run. Set once the server
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
