//! The time the HTTP layer passes to the cache: the system's monotonic clock, or in tests one that
//! moves only when told, so that expiry is tested without waiting for it.

use std::time::Instant;

#[cfg(any(test, feature = "testing"))]
use std::{
    sync::{Arc, Mutex},
    time::Duration,
};

#[derive(Clone, Default)]
pub enum Clock {
    #[default]
    System,
    #[cfg(any(test, feature = "testing"))]
    Manual(Arc<ManualClock>),
}

impl Clock {
    pub fn now(&self) -> Instant {
        match self {
            Clock::System => Instant::now(),
            #[cfg(any(test, feature = "testing"))]
            Clock::Manual(clock) => clock.now(),
        }
    }
}

impl std::fmt::Debug for Clock {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Clock::System => "Clock::System",
            #[cfg(any(test, feature = "testing"))]
            Clock::Manual(_) => "Clock::Manual",
        })
    }
}

/// A clock that stands still until `advance`d.
#[cfg(any(test, feature = "testing"))]
pub struct ManualClock {
    start: Instant,
    elapsed: Mutex<Duration>,
}

#[cfg(any(test, feature = "testing"))]
impl ManualClock {
    /// A manual clock, and the `Clock` that reads it.
    pub fn new() -> (Arc<ManualClock>, Clock) {
        let clock = Arc::new(ManualClock { start: Instant::now(), elapsed: Mutex::default() });
        (clock.clone(), Clock::Manual(clock))
    }

    pub fn advance(&self, by: Duration) {
        *self.elapsed.lock().unwrap_or_else(|p| p.into_inner()) += by;
    }

    fn now(&self) -> Instant {
        self.start + *self.elapsed.lock().unwrap_or_else(|p| p.into_inner())
    }
}
