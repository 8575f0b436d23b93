//! Fair shares of the executor between clients (their tokens). A request whose client chose a
//! deadline takes its turn at that deadline (earliest deadline first: admission promised it).
//! One whose client chose none takes its turn at the later of its default deadline and the
//! latest turn of its client's admitted requests plus its own planned seconds: a virtual clock
//! per client (L. Zhang, "VirtualClock", SIGCOMM 1990). A client alone is served in the order it
//! sent; a client that floods pushes its own requests back by their work, so another client's
//! request comes after at most about one of the flood's, and the work admission counts ahead of
//! it is its share, not the flood. Requests without a token (authentication off) are one client.
//!
//! Before a graph has run once its work counts 0 seconds (see `rates.rs`), and then a flood's
//! turns all fall on their deadlines: fairness starts with the first measured runs.

use std::time::{Duration, Instant};

use super::queue::{Client, Queue};

impl Queue {
    /// The turn of a request of `client`, due at `deadline` (not chosen by the client), of
    /// `secs` planned seconds.
    pub(super) fn fair_turn(&self, client: Client, deadline: Instant, secs: f64) -> Instant {
        let own = self.requests.values().filter(|r| r.client == client).map(|r| r.turn).max();
        let Some(latest) = own else { return deadline };
        let after_own = Duration::try_from_secs_f64(secs).ok().and_then(|d| latest.checked_add(d)).unwrap_or(latest);
        after_own.max(deadline)
    }
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, Instant};

    use crate::backend::testkit::{plan_with, recorder_with, tagged};
    use crate::backend::{BackendError, Due, ExecutorOptions, Work};
    use crate::bundle::GraphKind;

    fn from(token: u8) -> Due {
        Due { at: Instant::now() + Duration::from_secs(60), chosen: false, client: Some([token; 32]) }
    }

    /// Under a flood from client A (ten requests queued), a request of client B without a
    /// deadline runs after one of A's, not after all ten; A's requests keep their order.
    #[tokio::test]
    async fn a_flooding_client_waits_behind_itself() {
        let (backend, order, open) = recorder_with(16);
        plan_with(&backend, GraphKind::Renderer, 1e-3);
        let blocker = backend.admit(from(0), Work::default(), 0).unwrap();
        let held = blocker.run(GraphKind::Encoder, 0.0, tagged(0)); // holds the executor at the gate
        let rays = Work::of(GraphKind::Renderer, 100.0);
        let flood: Vec<_> = (0..10).map(|_| backend.admit(from(1), rays, 0).unwrap()).collect();
        let runs: Vec<_> = flood.iter().map(|t| t.run(GraphKind::Renderer, 100.0, tagged(1))).collect();
        let quiet = backend.admit(from(2), rays, 0).unwrap();
        let quiet_run = quiet.run(GraphKind::Renderer, 100.0, tagged(2));
        open.send(()).unwrap();
        held.await.unwrap();
        quiet_run.await.unwrap();
        for run in runs {
            run.await.unwrap();
        }
        let ran = order.lock().unwrap().clone();
        let position = ran.iter().position(|&tag| tag == 2).unwrap();
        assert!(position <= 2, "the quiet client's request ran {position}th: {ran:?}");
        assert_eq!(ran.iter().filter(|&&tag| tag == 1).count(), 10);
    }

    /// Admission counts a client's share ahead of it: with a 350 ms longest wait, A's flood of
    /// 100 ms requests is refused after four, while B's are admitted until B's own wait is too long.
    #[tokio::test]
    async fn the_longest_wait_refuses_the_flood_not_its_neighbour() {
        use crate::backend::testkit::Recorder;
        let options =
            ExecutorOptions { max_queue_wait: Some(Duration::from_millis(350)), ..ExecutorOptions::with_capacity(32) };
        let backend =
            crate::backend::BackendHandle::spawn(Box::new(Recorder { order: Default::default(), gate: None }), options)
                .unwrap();
        plan_with(&backend, GraphKind::Renderer, 1e-3);
        let rays = Work::of(GraphKind::Renderer, 100.0);
        let mut flood = Vec::new();
        let refused = loop {
            match backend.admit(from(1), rays, 0) {
                Ok(ticket) => flood.push(ticket),
                Err(e) => break e,
            }
            assert!(flood.len() < 20, "the flood was never refused");
        };
        assert!(matches!(refused, BackendError::QueueWaitTooLong { .. }), "{refused}");
        assert_eq!(flood.len(), 4, "0 to 300 ms ahead of A's four");
        // B's first waits behind A's first (100 ms), its second behind A's first two and B's
        // first (300 ms), its third behind five (500 ms): refused, as a flood of B's would be.
        for _ in 0..2 {
            flood.push(backend.admit(from(2), rays, 0).expect("the quiet client's request"));
        }
        assert!(matches!(backend.admit(from(2), rays, 0), Err(BackendError::QueueWaitTooLong { .. })));
        assert!(matches!(backend.admit(from(1), rays, 0), Err(BackendError::QueueWaitTooLong { .. })));
    }
}
