//! A model's slot on the executor: `BackendHandle::add_runner` gives another model's runner a
//! slot and a handle that admits requests to it (see `runners.rs`).

use std::sync::Arc;

use super::executor::BackendHandle;
use super::GraphRunner;

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

    /// Drops this handle's runner (its sessions' memory goes back, its rates are forgotten); its
    /// requests' jobs fail.
    pub fn remove_runner(&self) {
        let mut q = self.shared.lock();
        q.rates.forget(self.model);
        q.runner_changes.push((self.model, None));
        drop(q);
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
