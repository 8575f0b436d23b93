//! Fakes and helpers shared by the executor's unit tests.

use std::sync::{mpsc, Arc, Mutex};
use std::time::{Duration, Instant};

use super::budget::MemoryBudget;
use super::executor::{BackendHandle, ExecutorOptions};
use super::rates::{Rate, Rates, Work};
use super::{BackendError, GraphRunner, NamedTensors};
use crate::bundle::GraphKind;

/// Records the tag (first input value) of every job it runs and sleeps that many
/// milliseconds; the first job waits for a signal so that a test can fill the queue before
/// anything runs.
pub struct Recorder {
    pub order: Arc<Mutex<Vec<u32>>>,
    pub gate: Option<mpsc::Receiver<()>>,
}

impl GraphRunner for Recorder {
    fn run(&mut self, _graph: GraphKind, inputs: &NamedTensors) -> Result<NamedTensors, BackendError> {
        if let Some(gate) = self.gate.take() {
            let _ = gate.recv();
        }
        let tag = tag_of(inputs);
        self.order.lock().unwrap().push(tag);
        std::thread::sleep(Duration::from_millis(u64::from(tag)));
        Ok(vec![])
    }
}

pub fn tagged(tag: u32) -> NamedTensors {
    vec![("tag".into(), ndarray::arr1(&[tag as f32]).into_shared().into_dyn())]
}

pub fn tag_of(inputs: &NamedTensors) -> u32 {
    inputs[0].1.first().copied().unwrap_or_default() as u32
}

pub fn recorder() -> (BackendHandle, Arc<Mutex<Vec<u32>>>, mpsc::Sender<()>) {
    recorder_with(4)
}

/// [`recorder`] admitting `capacity` requests at once.
pub fn recorder_with(capacity: usize) -> (BackendHandle, Arc<Mutex<Vec<u32>>>, mpsc::Sender<()>) {
    let order = Arc::new(Mutex::new(Vec::new()));
    let (open, gate) = mpsc::channel();
    let backend = BackendHandle::spawn(
        Box::new(Recorder { order: order.clone(), gate: Some(gate) }),
        ExecutorOptions::with_capacity(capacity),
    )
    .unwrap();
    (backend, order, open)
}

/// An executor whose requests may hold `total` bytes of estimates, after `reserved`.
pub fn budgeted(total: u64, reserved: u64) -> (BackendHandle, mpsc::Sender<()>) {
    let (open, gate) = mpsc::channel();
    let recorder = Recorder { order: Arc::default(), gate: Some(gate) };
    let options = ExecutorOptions { memory: MemoryBudget { total, reserved }, ..ExecutorOptions::with_capacity(8) };
    (BackendHandle::spawn(Box::new(recorder), options).unwrap(), open)
}

pub fn in_secs(secs: u64) -> Instant {
    Instant::now() + Duration::from_secs(secs)
}

pub fn far() -> Instant {
    in_secs(60)
}

pub const NONE: Work = Work([0.0; GraphKind::ALL.len()]);

/// Sets the rates admission plans with, as if measured without any scatter: admission's
/// arithmetic checked apart from the timing of the machine that runs the test.
pub fn plan_with(backend: &BackendHandle, graph: GraphKind, secs_per_unit: f64) {
    let mut q = backend.shared.lock();
    let mut rates = q.rates.of(backend.model);
    rates.0[graph.index()] = Some(Rate { secs: secs_per_unit, units: 1.0, deviation: 0.0 });
    q.rates.set(backend.model, rates);
}

/// Rates of renderer runs of 20 units whose times scatter: 0.25 or 1.75 ms a unit.
pub fn scattered_rates() -> Rates {
    let mut rates = Rates::default();
    for took in [0.005, 0.035, 0.005, 0.035, 0.005, 0.035] {
        rates.record(GraphKind::Renderer, 20.0, took);
    }
    rates
}
