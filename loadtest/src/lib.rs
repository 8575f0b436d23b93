//! A bounded load generator for the scene-render endpoint (used by `src/main.rs`, the `loadgen`
//! binary, and its smoke test). Plain threads and the blocking HTTP/1.1 client of the end-to-end
//! tests' crate: nothing new to compile, and at the request rates a CPU renderer sustains,
//! threads are cheap enough.
//!
//! Two modes: closed loop (N workers, each sends its next request when the previous one is
//! answered: measures the sustainable throughput) and open loop (requests start at a fixed rate
//! whatever the answers: shows what overload does). Open loop never has more than
//! `max_in_flight` requests outstanding (that is what keeps the generator bounded); a start it
//! skips for that reason is counted, not hidden.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use scnerf_e2e::{auth_header, http_request, HttpResponse};

/// What one request of the load sends.
#[derive(Debug, Clone)]
pub struct Scenario {
    pub addr: SocketAddr,
    pub token: Option<String>,
    /// `/v1/scenes/{id}/render`.
    pub path: String,
    /// JSON `{"target", "outputs"}` bodies, sent in turn (views of mixed sizes).
    pub bodies: Vec<Vec<u8>>,
    /// Sent as `x-scnerf-deadline-ms`.
    pub deadline: Option<Duration>,
    pub timeout: Duration,
    /// Requests started, to take the bodies in turn.
    pub sent: Arc<AtomicUsize>,
}

#[derive(Debug, Clone, Copy)]
pub enum Mode {
    Closed { concurrency: usize },
    Open { rate: f64, max_in_flight: usize },
}

/// One request: when it started (since the run began), how long it took, and its status
/// (`None`: no HTTP answer: connection refused, reset or timed out).
#[derive(Debug, Clone, Copy)]
pub struct Sample {
    pub started: Duration,
    pub latency: Duration,
    pub status: Option<u16>,
}

impl Scenario {
    /// Sends the next body in turn.
    pub fn send(&self) -> std::io::Result<HttpResponse> {
        let body = &self.bodies[self.sent.fetch_add(1, Ordering::Relaxed) % self.bodies.len()];
        let auth = auth_header(&self.token);
        let deadline = self.deadline.map(|d| d.as_millis().to_string());
        let mut headers = vec![("content-type", "application/json")];
        if let Some(a) = &auth {
            headers.push(("authorization", a.as_str()));
        }
        if let Some(ms) = &deadline {
            headers.push(("x-scnerf-deadline-ms", ms.as_str()));
        }
        http_request(self.addr, "POST", &self.path, &headers, body, self.timeout)
    }

    fn sample(&self, run_start: Instant) -> Sample {
        let t0 = Instant::now();
        let status = self.send().ok().map(|r| r.status);
        Sample { started: t0 - run_start, latency: t0.elapsed(), status }
    }
}

/// The outcome of a run.
#[derive(Debug, Default)]
pub struct Outcome {
    pub samples: Vec<Sample>,
    /// Open loop: starts skipped because `max_in_flight` requests were outstanding.
    pub skipped: usize,
    pub elapsed: Duration,
}

/// Drives the scenario for `duration`, then waits for the requests still outstanding.
pub fn run(scenario: &Scenario, mode: Mode, duration: Duration) -> Outcome {
    let start = Instant::now();
    let samples = Arc::new(Mutex::new(Vec::new()));
    let skipped = match mode {
        Mode::Closed { concurrency } => {
            closed_loop(scenario, concurrency, start, duration, &samples);
            0
        }
        Mode::Open { rate, max_in_flight } => open_loop(scenario, rate, max_in_flight, start, duration, &samples),
    };
    let samples = std::mem::take(&mut *samples.lock().unwrap());
    Outcome { samples, skipped, elapsed: start.elapsed() }
}

fn closed_loop(
    scenario: &Scenario,
    concurrency: usize,
    start: Instant,
    duration: Duration,
    out: &Arc<Mutex<Vec<Sample>>>,
) {
    let workers: Vec<_> = (0..concurrency.max(1))
        .map(|_| {
            let (scenario, out) = (scenario.clone(), out.clone());
            std::thread::spawn(move || {
                while start.elapsed() < duration {
                    let s = scenario.sample(start);
                    out.lock().unwrap().push(s);
                }
            })
        })
        .collect();
    for w in workers {
        let _ = w.join();
    }
}

fn open_loop(
    scenario: &Scenario,
    rate: f64,
    max_in_flight: usize,
    start: Instant,
    duration: Duration,
    out: &Arc<Mutex<Vec<Sample>>>,
) -> usize {
    let interval = Duration::from_secs_f64(1.0 / rate.max(1e-3));
    let in_flight = Arc::new(AtomicUsize::new(0));
    let mut handles = Vec::new();
    let mut skipped = 0;
    let mut next = Duration::ZERO;
    while next < duration {
        if let Some(wait) = next.checked_sub(start.elapsed()) {
            std::thread::sleep(wait);
        }
        next += interval;
        if in_flight.load(Ordering::SeqCst) >= max_in_flight {
            skipped += 1;
            continue;
        }
        in_flight.fetch_add(1, Ordering::SeqCst);
        let (scenario, out, in_flight) = (scenario.clone(), out.clone(), in_flight.clone());
        handles.push(std::thread::spawn(move || {
            let s = scenario.sample(start);
            out.lock().unwrap().push(s);
            in_flight.fetch_sub(1, Ordering::SeqCst);
        }));
        handles.retain(|h| !h.is_finished());
    }
    for h in handles {
        let _ = h.join();
    }
    skipped
}

/// Latency percentile (nearest rank) of sorted durations.
pub fn percentile(sorted: &[Duration], p: f64) -> Option<Duration> {
    if sorted.is_empty() {
        return None;
    }
    let rank = ((p / 100.0) * sorted.len() as f64).ceil() as usize;
    Some(sorted[rank.clamp(1, sorted.len()) - 1])
}

/// Figures of a run.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Report {
    pub requests: usize,
    pub elapsed_s: f64,
    /// 200 answers per second.
    pub throughput_rps: f64,
    /// 200 answers within the deadline (when one was sent) per second: views finished in time.
    pub goodput_rps: f64,
    /// Status -> count; transport failures under "error".
    pub statuses: BTreeMap<String, usize>,
    pub skipped_starts: usize,
    pub latency_ok_ms: Percentiles,
    pub latency_all_ms: Percentiles,
}

#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct Percentiles {
    pub p50: Option<f64>,
    pub p95: Option<f64>,
    pub p99: Option<f64>,
    pub max: Option<f64>,
}

fn percentiles(mut latencies: Vec<Duration>) -> Percentiles {
    latencies.sort();
    let ms = |d: Option<Duration>| d.map(|d| (d.as_secs_f64() * 1e4).round() / 10.0);
    Percentiles {
        p50: ms(percentile(&latencies, 50.0)),
        p95: ms(percentile(&latencies, 95.0)),
        p99: ms(percentile(&latencies, 99.0)),
        max: ms(latencies.last().copied()),
    }
}

impl Report {
    pub fn new(outcome: &Outcome, deadline: Option<Duration>) -> Report {
        let mut statuses = BTreeMap::new();
        for s in &outcome.samples {
            let key = s.status.map_or("error".to_string(), |c| c.to_string());
            *statuses.entry(key).or_insert(0) += 1;
        }
        let ok: Vec<Duration> = outcome.samples.iter().filter(|s| s.status == Some(200)).map(|s| s.latency).collect();
        let elapsed = outcome.elapsed.as_secs_f64();
        let in_time = ok.iter().filter(|l| deadline.is_none_or(|d| **l <= d)).count();
        let per_sec = |n: usize| ((n as f64 / elapsed.max(1e-9)) * 1000.0).round() / 1000.0;
        Report {
            requests: outcome.samples.len(),
            elapsed_s: (elapsed * 100.0).round() / 100.0,
            throughput_rps: per_sec(ok.len()),
            goodput_rps: per_sec(in_time),
            statuses,
            skipped_starts: outcome.skipped,
            latency_ok_ms: percentiles(ok),
            latency_all_ms: percentiles(outcome.samples.iter().map(|s| s.latency).collect()),
        }
    }

    /// Statuses outside `allowed` (transport errors count as "error").
    pub fn unexpected(&self, allowed: &[u16]) -> Vec<String> {
        self.statuses.keys().filter(|k| !k.parse::<u16>().is_ok_and(|c| allowed.contains(&c))).cloned().collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_rank_percentiles() {
        let d: Vec<Duration> = (1..=100).map(Duration::from_millis).collect();
        assert_eq!(percentile(&d, 50.0), Some(Duration::from_millis(50)));
        assert_eq!(percentile(&d, 99.0), Some(Duration::from_millis(99)));
        assert_eq!(percentile(&d[..1], 95.0), Some(Duration::from_millis(1)));
        assert_eq!(percentile(&[], 50.0), None);
    }

    #[test]
    fn report_counts_statuses() {
        let s = |status| Sample { started: Duration::ZERO, latency: Duration::from_millis(10), status };
        let outcome =
            Outcome { samples: vec![s(Some(200)), s(Some(503)), s(None)], skipped: 2, elapsed: Duration::from_secs(1) };
        let r = Report::new(&outcome, None);
        assert_eq!(r.requests, 3);
        assert_eq!(r.throughput_rps, 1.0);
        assert_eq!(r.goodput_rps, 1.0);
        assert_eq!(Report::new(&outcome, Some(Duration::from_millis(5))).goodput_rps, 0.0);
        assert_eq!(r.statuses["error"], 1);
        assert_eq!(r.unexpected(&[200, 429, 503]), vec!["error".to_string()]);
    }
}
