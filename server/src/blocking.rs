//! CPU work off the async workers that stops when its request is gone.
//!
//! A request's handler future is dropped when its deadline passes or its client leaves, and with
//! it every graph run it queued; work it handed to a blocking thread (decoding images, reading a
//! capture's files) would run on, taking the CPU from the requests still served. [`run`] gives
//! that work a [`Cancel`] flag, set when the future awaiting it is dropped; the work checks it
//! between its steps.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use crate::error::ApiError;

/// Set once nobody waits for the work any more.
#[derive(Debug, Clone, Default)]
pub struct Cancel(Arc<AtomicBool>);

impl Cancel {
    pub fn is_set(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }

    /// `Err` once set: what the work returns then goes nowhere (its request has been answered
    /// or its client has left).
    pub fn check(&self) -> Result<(), ApiError> {
        match self.is_set() {
            true => Err(ApiError::Unavailable { message: "the request was cancelled".into(), retry_after_secs: 1 }),
            false => Ok(()),
        }
    }
}

/// Sets the flag when the future holding it is dropped, finished or not.
struct SetOnDrop(Cancel);

impl Drop for SetOnDrop {
    fn drop(&mut self) {
        self.0 .0.store(true, Ordering::Relaxed);
    }
}

/// Runs `work` on a blocking thread; dropping the returned future sets the flag `work` is given.
pub async fn run<T: Send + 'static>(
    work: impl FnOnce(&Cancel) -> Result<T, ApiError> + Send + 'static,
) -> Result<T, ApiError> {
    let cancel = Cancel::default();
    let _set_on_drop = SetOnDrop(cancel.clone());
    tokio::task::spawn_blocking(move || work(&cancel))
        .await
        .map_err(|e| ApiError::Internal(format!("a blocking task failed: {e}")))?
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[tokio::test]
    async fn dropping_the_future_stops_the_work_at_its_next_check() {
        let steps = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let counted = steps.clone();
        let work = run(move |cancel| {
            for _ in 0..1000 {
                cancel.check()?;
                counted.fetch_add(1, Ordering::SeqCst);
                std::thread::sleep(Duration::from_millis(5));
            }
            Ok(())
        });
        assert!(tokio::time::timeout(Duration::from_millis(50), work).await.is_err());
        tokio::time::sleep(Duration::from_millis(50)).await;
        let stopped_at = steps.load(Ordering::SeqCst);
        tokio::time::sleep(Duration::from_millis(100)).await;
        assert_eq!(steps.load(Ordering::SeqCst), stopped_at, "the work went on after its future was dropped");
        assert!(stopped_at < 100, "{stopped_at}");
        assert_eq!(run(|_| Ok(7)).await.unwrap(), 7);
    }
}
