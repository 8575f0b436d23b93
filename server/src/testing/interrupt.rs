//! The fake runner's terminate flag: its sleep ends when the executor's watchdog interrupts it,
//! as an ONNX Runtime run ends when its run options' flag is set.

use std::sync::{Condvar, Mutex};
use std::time::Duration;

use crate::backend::Interrupt;

#[derive(Default)]
pub struct FakeInterrupt {
    set: Mutex<bool>,
    changed: Condvar,
}

impl FakeInterrupt {
    /// Sleeps `delay` or until the flag is set; whether it is set.
    pub(super) fn sleep(&self, delay: Duration) -> bool {
        let set = self.set.lock().unwrap_or_else(|p| p.into_inner());
        let (set, _) = self.changed.wait_timeout_while(set, delay, |set| !*set).unwrap_or_else(|p| p.into_inner());
        *set
    }
}

impl Interrupt for FakeInterrupt {
    fn interrupt(&self) {
        *self.set.lock().unwrap_or_else(|p| p.into_inner()) = true;
        self.changed.notify_all();
    }

    fn clear(&self) {
        *self.set.lock().unwrap_or_else(|p| p.into_inner()) = false;
    }
}
