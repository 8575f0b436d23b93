//! Load generator for scnerf-server: renders small views of one cached scene over loopback for a
//! fixed time and reports throughput, latency percentiles, status counts and the server's memory.
//!
//!   loadgen --addr 127.0.0.1:8080 --concurrency 2 --duration-secs 60 --server-pid $PID
//!   loadgen --addr 127.0.0.1:8080 --rate 4 --expect 200,429,503 --recover   # overload
//!
//! Exit status 1 when a status outside `--expect` comes back or the server does not recover.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use clap::Parser;
use scnerf_e2e::{http_request, memory_kib, repo_root, Case};
use scnerf_loadtest::{run, Mode, Report, Scenario};
use serde_json::json;

#[derive(Debug, Parser)]
#[command(name = "loadgen", about = "Load generator for scnerf-server's cached-scene renders")]
struct Args {
    /// Server address.
    #[arg(long, default_value = "127.0.0.1:8080")]
    addr: SocketAddr,
    /// Bearer token, if the server requires one.
    #[arg(long, env = "SCNERF_LOADGEN_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Case directory (request.json + source_0..2.png). Default: the first parity fixture.
    #[arg(long)]
    case: Option<PathBuf>,
    /// Target views are SIZE x SIZE pixels; a list (32,64,96) sends the sizes in turn.
    #[arg(long = "size", value_delimiter = ',', default_value = "64")]
    sizes: Vec<u32>,
    /// Send `x-scnerf-deadline-ms: N` and count the views finished within it (goodput).
    #[arg(long)]
    deadline_ms: Option<u64>,
    #[arg(long, default_value_t = 60)]
    duration_secs: u64,
    /// Closed loop with this many workers (the default mode, 1 worker).
    #[arg(long, conflicts_with = "rate")]
    concurrency: Option<usize>,
    /// Open loop: start this many requests per second whatever the answers.
    #[arg(long)]
    rate: Option<f64>,
    /// Open loop: most requests outstanding at once.
    #[arg(long, default_value_t = 64)]
    max_in_flight: usize,
    /// Per-request client timeout in seconds.
    #[arg(long, default_value_t = 600)]
    timeout_secs: u64,
    /// Server process id, for its peak RSS (VmHWM) and RSS (/proc/PID/status).
    #[arg(long)]
    server_pid: Option<u32>,
    /// Sample the server's RSS every N seconds during the run (soak tests).
    #[arg(long)]
    rss_every_secs: Option<u64>,
    /// Fail unless every status is one of these (transport errors always fail).
    #[arg(long, value_delimiter = ',')]
    expect: Vec<u16>,
    /// After the run: wait for the queue to drain, then require 3 renders in a row to succeed.
    #[arg(long)]
    recover: bool,
    /// Print the report as one JSON object.
    #[arg(long)]
    json: bool,
}

fn machine() -> serde_json::Value {
    let cpu = std::fs::read_to_string("/proc/cpuinfo").ok().and_then(|s| {
        s.lines().find_map(|l| l.strip_prefix("model name").map(|m| m.trim_start_matches([' ', '\t', ':']).to_string()))
    });
    let load = std::fs::read_to_string("/proc/loadavg")
        .ok()
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "));
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    json!({"cores": cores, "cpu": cpu, "loadavg_at_start": load})
}

/// Samples the server's RSS (KiB) every `every` until `stop`.
fn rss_sampler(pid: u32, every: Duration, stop: Instant) -> std::thread::JoinHandle<Vec<(f64, u64)>> {
    std::thread::spawn(move || {
        let start = Instant::now();
        let mut out = Vec::new();
        while Instant::now() < stop {
            if let Some((_, rss)) = memory_kib(pid) {
                out.push((start.elapsed().as_secs_f64().round(), rss));
            }
            std::thread::sleep(
                every.min(stop.saturating_duration_since(Instant::now())).max(Duration::from_millis(10)),
            );
        }
        if let Some((_, rss)) = memory_kib(pid) {
            out.push((start.elapsed().as_secs_f64().round(), rss));
        }
        out
    })
}

/// Waits until the server has no admitted requests, then sends 3 renders that must all be 200.
fn recover(scenario: &Scenario) -> Result<f64, String> {
    let start = Instant::now();
    loop {
        let m = http_request(scenario.addr, "GET", "/metrics", &[], b"", Duration::from_secs(10))
            .map_err(|e| e.to_string())?;
        if String::from_utf8_lossy(&m.body).lines().any(|l| l == "scnerf_inference_queue_requests 0") {
            break;
        }
        if start.elapsed() > Duration::from_secs(600) {
            return Err("the queue did not drain within 10 minutes".into());
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let drained = start.elapsed().as_secs_f64();
    for i in 0..3 {
        let r = scenario.send().map_err(|e| format!("recovery render {i}: {e}"))?;
        if r.status != 200 {
            return Err(format!("recovery render {i}: {} {}", r.status, String::from_utf8_lossy(&r.body)));
        }
    }
    Ok(drained)
}

fn main() {
    let args = Args::parse();
    let case_dir = args.case.clone().unwrap_or_else(|| repo_root().join("tests/fixtures/parity/cases/opencv_64x96"));
    let case = Case::load(&case_dir).unwrap_or_else(|e| fail(&format!("{}: {e}", case_dir.display())));
    let scene_id = case.create_scene(args.addr, &args.token).unwrap_or_else(|e| fail(&e));
    let scenario = Scenario {
        addr: args.addr,
        token: args.token.clone(),
        path: format!("/v1/scenes/{scene_id}/render"),
        bodies: args.sizes.iter().map(|&size| case.view_body(size)).collect(),
        deadline: args.deadline_ms.map(Duration::from_millis),
        timeout: Duration::from_secs(args.timeout_secs),
        sent: Arc::default(),
    };
    let mode = match (args.rate, args.concurrency) {
        (Some(rate), _) => Mode::Open { rate, max_in_flight: args.max_in_flight },
        (None, c) => Mode::Closed { concurrency: c.unwrap_or(1) },
    };
    let duration = Duration::from_secs(args.duration_secs);
    let memory_before = args.server_pid.and_then(memory_kib);
    let sampler = args
        .server_pid
        .zip(args.rss_every_secs)
        .map(|(pid, every)| rss_sampler(pid, Duration::from_secs(every.max(1)), Instant::now() + duration));
    let machine = machine();

    let outcome = run(&scenario, mode, duration);
    let report = Report::new(&outcome, scenario.deadline);
    let memory_after = args.server_pid.and_then(memory_kib);
    let rss_series = sampler.and_then(|s| s.join().ok());
    let recovery = args.recover.then(|| recover(&scenario));
    let unexpected = if args.expect.is_empty() { Vec::new() } else { report.unexpected(&args.expect) };

    let mode_json = match mode {
        Mode::Closed { concurrency } => json!({"closed_loop": {"concurrency": concurrency}}),
        Mode::Open { rate, max_in_flight } => json!({"open_loop": {"rate_rps": rate, "max_in_flight": max_in_flight}}),
    };
    let mut out = json!({
        "mode": mode_json,
        "targets": args.sizes.iter().map(|s| format!("{s}x{s}")).collect::<Vec<_>>(),
        "deadline_ms": args.deadline_ms,
        "duration_s": args.duration_secs,
        "report": report,
        "server_memory_kib": {
            "before": memory_before.map(|(hwm, rss)| json!({"peak_rss": hwm, "rss": rss})),
            "after": memory_after.map(|(hwm, rss)| json!({"peak_rss": hwm, "rss": rss})),
        },
        "machine": machine,
    });
    if let Some(series) = &rss_series {
        out["rss_series_kib"] = json!(series);
        // Growth after the first fifth of the run (warm-up: arenas, caches).
        if let (Some(warm), Some(last)) = (series.get(series.len() / 5), series.last()) {
            out["rss_growth_after_warmup_kib"] = json!(last.1 as i64 - warm.1 as i64);
        }
    }
    if let Some(r) = &recovery {
        out["recovery"] = match r {
            Ok(drained_s) => json!({"ok": true, "queue_drained_after_s": drained_s}),
            Err(e) => json!({"ok": false, "error": e}),
        };
    }
    if !unexpected.is_empty() {
        out["unexpected_statuses"] = json!(unexpected);
    }
    if args.json {
        println!("{out}");
    } else {
        println!("{}", serde_json::to_string_pretty(&out).unwrap_or_default());
    }
    if !unexpected.is_empty() || recovery.is_some_and(|r| r.is_err()) {
        std::process::exit(1);
    }
}

fn fail(message: &str) -> ! {
    eprintln!("loadgen: {message}");
    std::process::exit(2);
}
