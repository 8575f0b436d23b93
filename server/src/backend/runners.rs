//! Several models on the one executor. Each model's graphs have their own runner (its ONNX
//! Runtime sessions), in a slot of the executor's; a `BackendHandle` names a slot, and the jobs of
//! the requests it admits run on that slot's runner. The queue, the deadlines, the memory budget
//! and the measured rates stay shared: one thread runs every model's graphs, one at a time, so
//! models never oversubscribe the CPU and admission sees all the work ahead.
//!
//! Runners are added (a model loaded by a reload) and removed (one that did not fit) while the
//! executor runs: the change waits in the queue until the executor next takes a job, so a graph
//! run in progress is never waited for and never disturbed.

use std::sync::Arc;

use super::executor::BackendHandle;
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

impl BackendHandle {
    /// Gives `runner` (another model's graphs) a slot on this executor: the handle returned
    /// admits requests whose graphs run on it, within the same queue and memory budget.
    pub fn add_runner(&self, runner: Box<dyn GraphRunner>) -> BackendHandle {
        let slot = {
            let mut q = self.shared.lock();
            let slot = q.next_slot;
            q.next_slot += 1;
            q.runner_changes.push((slot, Some(runner)));
            slot
        };
        self.shared.wake.notify_one();
        BackendHandle { shared: self.shared.clone(), model: slot, closer: Arc::clone(&self.closer) }
    }

    /// Drops this handle's runner (its sessions' memory goes back); its requests' jobs fail.
    pub fn remove_runner(&self) {
        self.shared.lock().runner_changes.push((self.model, None));
        self.shared.wake.notify_one();
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Mutex;

    use super::*;
    use crate::backend::testkit::{far, NONE};
    use crate::backend::{BackendError, ExecutorOptions, NamedTensors};
    use crate::bundle::GraphKind;

    /// A runner that answers with its own number.
    struct Named(f32, Arc<Mutex<Vec<f32>>>);

    impl GraphRunner for Named {
        fn run(&mut self, _graph: GraphKind, _inputs: &NamedTensors) -> Result<NamedTensors, BackendError> {
            self.1.lock().unwrap().push(self.0);
            Ok(vec![("out".into(), ndarray::arr1(&[self.0]).into_dyn().into_shared())])
        }
    }

    async fn answer(handle: &BackendHandle) -> Result<f32, BackendError> {
        let ticket = handle.admit(far(), NONE, 0)?;
        let mut outputs = ticket.run(GraphKind::Encoder, 0.0, vec![]).await?;
        Ok(outputs.take::<ndarray::Ix1>("out", &[Some(1)])?[0])
    }

    #[tokio::test]
    async fn each_handle_runs_on_its_own_runner_and_a_removed_one_fails() {
        let ran = Arc::new(Mutex::new(Vec::new()));
        let first = BackendHandle::spawn(Box::new(Named(1.0, ran.clone())), ExecutorOptions::with_capacity(4)).unwrap();
        let second = first.add_runner(Box::new(Named(2.0, ran.clone())));
        assert_eq!(answer(&second).await.unwrap(), 2.0);
        assert_eq!(answer(&first).await.unwrap(), 1.0);
        second.remove_runner();
        assert!(matches!(answer(&second).await, Err(BackendError::Run { .. })));
        assert_eq!(answer(&first).await.unwrap(), 1.0);
        assert_eq!(*ran.lock().unwrap(), vec![2.0, 1.0, 1.0]);
    }
}
