//! Whether the executor is stuck: one graph run going on long past its request's deadline. The
//! watchdog ends a run at its deadline (`watchdog.rs`); this is the run that did not end then
//! (a runner that cannot be interrupted, one operator that does not read ONNX Runtime's flag).
//! Nothing queued behind it can be answered in time, so `/readyz` says not ready until it ends.

use std::time::{Duration, Instant};

use super::executor::BackendHandle;

/// How far past its deadline a run may go before the executor counts as stuck: a run a little
/// late is routine (its deadline passed while it ran).
pub const STUCK_AFTER: Duration = Duration::from_secs(5);

impl BackendHandle {
    /// How long the graph run in progress has gone on past its request's deadline; `None` when
    /// none runs or it is within its deadline.
    pub fn overrun(&self) -> Option<Duration> {
        let deadline = self.shared.lock().running.as_ref()?.deadline;
        Instant::now().checked_duration_since(deadline)
    }

    /// `Err` saying so while the run in progress is more than [`STUCK_AFTER`] past its deadline.
    pub fn check_not_stuck(&self) -> Result<(), String> {
        match self.overrun().filter(|late| *late > STUCK_AFTER) {
            None => Ok(()),
            Some(late) => Err(format!(
                "the executor is stuck: a graph run has gone on {} s past its request's deadline",
                late.as_secs()
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::mpsc;
    use std::sync::Mutex;

    use super::*;
    use crate::backend::testkit::NONE;
    use crate::backend::{BackendError, ExecutorOptions, GraphRunner, NamedTensors};
    use crate::bundle::GraphKind;

    /// Says it started, then runs until told to stop.
    struct Blocking(mpsc::Sender<()>, Mutex<mpsc::Receiver<()>>);

    impl GraphRunner for Blocking {
        fn run(&mut self, _graph: GraphKind, _inputs: &NamedTensors) -> Result<NamedTensors, BackendError> {
            let _ = self.0.send(());
            let _ = self.1.lock().unwrap().recv();
            Ok(vec![])
        }
    }

    #[tokio::test]
    async fn a_run_past_its_deadline_is_an_overrun_until_it_ends() {
        let (started_tx, started) = mpsc::channel();
        let (stop, stop_rx) = mpsc::channel();
        let runner = Blocking(started_tx, Mutex::new(stop_rx));
        let handle = BackendHandle::spawn(Box::new(runner), ExecutorOptions::with_capacity(2)).unwrap();
        assert_eq!(handle.overrun(), None, "idle");
        let deadline = Instant::now() + Duration::from_millis(500);
        let ticket = handle.admit(deadline, NONE, 0).unwrap();
        let run = tokio::spawn(async move { ticket.run(GraphKind::Encoder, 0.0, vec![]).await.map(|_| ()) });
        tokio::task::spawn_blocking(move || started.recv().unwrap()).await.unwrap();
        tokio::time::sleep_until(deadline.into()).await;
        assert!(handle.overrun().is_some(), "the run goes on past its deadline");
        stop.send(()).unwrap();
        let _ = run.await.unwrap();
        assert_eq!(handle.overrun(), None, "the run ended");
    }
}
