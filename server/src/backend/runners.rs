//! Several models on the one executor. Each model's graphs have their own runner (its ONNX
//! Runtime sessions), in a slot of the executor's; a `BackendHandle` names a slot, and the jobs of
//! the requests it admits run on that slot's runner. The queue, the deadlines and the memory
//! budget stay shared: one thread runs every model's graphs, one at a time, so models never
//! oversubscribe the CPU and admission sees all the work ahead. The measured rates are each
//! model's own (`rates.rs`): one slow model never changes another's admission.
//!
//! Runners are added (a model loaded by a reload) and removed (one that did not fit) while the
//! executor runs (`BackendHandle::add_runner`, in `slots.rs`): the change waits in the queue
//! until the executor next takes a job, so a graph run in progress is never waited for and never
//! disturbed.

use super::GraphRunner;

/// A runner added to a slot, or a slot emptied.
pub(super) type RunnerChange = (usize, Option<Box<dyn GraphRunner>>);

/// The executor thread's runners, by slot.
pub(super) struct Runners(Vec<Option<Box<dyn GraphRunner>>>);

impl Runners {
    pub(super) fn new(first: Box<dyn GraphRunner>) -> Runners {
        Runners(vec![Some(first)])
    }

    pub(super) fn apply(&mut self, changes: Vec<RunnerChange>) {
        for (slot, runner) in changes {
            if self.0.len() <= slot {
                self.0.resize_with(slot + 1, || None);
            }
            self.0[slot] = runner;
        }
    }

    pub(super) fn get(&mut self, slot: usize) -> Option<&mut dyn GraphRunner> {
        Some(self.0.get_mut(slot)?.as_mut()?.as_mut())
    }
}
