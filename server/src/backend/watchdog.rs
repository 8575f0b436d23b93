//! The watchdog: a thread beside the executor's that ends the graph run in progress once its
//! request's deadline passes (through its runner's `Interrupt`: ONNX Runtime's terminate flag).
//! Past its deadline a run's result is of no use (its client has had its 504, a warm-up has
//! failed), and a crafted graph (an endless `Loop`) would otherwise hold the one executor thread
//! and every model's requests behind it. The run returns an error, its job answers
//! `DeadlineExceeded`, and the executor takes the next job. A run its runner cannot end (one
//! operator that does not look at the flag) is left to `/readyz` (`stuck.rs`).

use std::sync::Arc;
use std::time::Instant;

use super::shared::Shared;

/// Starts the watchdog of `shared`'s executor; it ends with the executor.
pub(super) fn spawn(shared: Arc<Shared>) -> std::io::Result<()> {
    std::thread::Builder::new().name("scnerf-watchdog".into()).spawn(move || watch(&shared)).map(|_| ())
}

/// Waits for the run in progress to reach its deadline, ends it there, and waits for the next
/// (the executor wakes it at each run's start and when it stops).
fn watch(shared: &Shared) {
    let mut q = shared.lock();
    while !q.stopped {
        let now = Instant::now();
        let left = match q.running.as_mut() {
            Some(run) if !run.interrupted => match run.deadline.checked_duration_since(now) {
                Some(left) if !left.is_zero() => Some(left),
                _ => {
                    if let Some(interrupt) = &run.interrupt {
                        tracing::warn!(
                            late_ms = now.saturating_duration_since(run.deadline).as_secs_f64() * 1e3,
                            "a graph run went past its request's deadline: ending it"
                        );
                        interrupt.interrupt();
                        run.interrupted = true;
                    }
                    None
                }
            },
            _ => None,
        };
        q = match left {
            Some(left) => shared.watch.wait_timeout(q, left).unwrap_or_else(|p| p.into_inner()).0,
            None => shared.watch.wait(q).unwrap_or_else(|p| p.into_inner()),
        };
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::{Condvar, Mutex};
    use std::time::Duration;

    use crate::backend::testkit::{far, NONE};
    use crate::backend::{BackendError, BackendHandle, ExecutorOptions, GraphRunner, Interrupt, NamedTensors};
    use crate::bundle::GraphKind;

    use super::*;

    /// The flag an ONNX Runtime run polls, and a wake-up for the fake's wait on it.
    #[derive(Default)]
    struct Flag {
        set: Mutex<bool>,
        changed: Condvar,
        ever: AtomicBool,
    }

    impl Interrupt for Flag {
        fn interrupt(&self) {
            *self.set.lock().unwrap() = true;
            self.ever.store(true, Ordering::SeqCst);
            self.changed.notify_all();
        }

        fn clear(&self) {
            *self.set.lock().unwrap() = false;
        }
    }

    /// As an ONNX Runtime run polls its terminate flag: the encoder runs until the flag is set
    /// (an endless `Loop`), the renderer returns at once, failing if the flag is still set.
    struct Endless(Arc<Flag>);

    impl GraphRunner for Endless {
        fn run(&mut self, graph: GraphKind, _inputs: &NamedTensors) -> Result<NamedTensors, BackendError> {
            let set = self.0.set.lock().unwrap();
            let set = match graph {
                GraphKind::Encoder => self.0.changed.wait_while(set, |set| !*set).unwrap(),
                _ => set,
            };
            match *set {
                true => Err(BackendError::Run { graph, message: "Exiting due to terminate flag".into() }),
                false => Ok(vec![]),
            }
        }

        fn interrupter(&self) -> Option<Arc<dyn Interrupt>> {
            Some(self.0.clone())
        }
    }

    /// A run past its request's deadline is ended there: its job answers DeadlineExceeded, and
    /// the executor runs the next request's job, with the flag cleared.
    #[tokio::test]
    async fn a_run_past_its_deadline_is_ended_and_the_executor_serves_the_next() {
        let flag = Arc::new(Flag::default());
        let handle = BackendHandle::spawn(Box::new(Endless(flag.clone())), ExecutorOptions::with_capacity(2)).unwrap();
        let hung = handle.admit(Instant::now() + Duration::from_millis(200), NONE, 0).unwrap();
        let next = handle.admit(far(), NONE, 0).unwrap();
        let endless = hung.run(GraphKind::Encoder, 0.0, vec![]);
        let after = next.run(GraphKind::Renderer, 0.0, vec![]);
        assert!(matches!(endless.await, Err(BackendError::DeadlineExceeded)));
        assert!(flag.ever.load(Ordering::SeqCst), "the run was interrupted");
        after.await.expect("the next request's run, after the flag is cleared");
        assert_eq!(handle.overrun(), None);
    }
}
