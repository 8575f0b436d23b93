//! Smoke test of the load generator against the real binary (parity bundle, tiny 16x16 views):
//! a closed-loop run reports throughput, percentiles and the server's peak RSS; an open-loop run
//! far above what the server sustains gets only 200/503 and the server recovers.

use std::process::Command;
use std::time::Duration;

use scnerf_e2e::{repo_root, server_binary, ServerProcess};
use serde_json::Value;

fn loadgen(args: &[&str]) -> (bool, Value) {
    let out = Command::new(env!("CARGO_BIN_EXE_loadgen")).args(args).arg("--json").output().expect("run loadgen");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let report = serde_json::from_str(stdout.trim()).unwrap_or_else(|e| {
        panic!("loadgen output is not JSON ({e}): {stdout}\n{}", String::from_utf8_lossy(&out.stderr))
    });
    (out.status.success(), report)
}

#[test]
fn loadgen_reports_and_overload_yields_only_200_or_503() {
    let bundle = repo_root().join("tests/fixtures/parity/bundle");
    // Full sampling: the service rate the overload below was sized for.
    let args = ["--bundle", bundle.to_str().unwrap(), "--skip-warmup", "--queue-capacity", "2", "--sampling", "full"];
    let mut server = ServerProcess::start(&server_binary(), &args);
    server.wait_ready(Duration::from_secs(120));
    let addr = server.addr.to_string();
    let pid = server.child.id().to_string();

    let common = ["--addr", &addr, "--server-pid", &pid, "--size", "16", "--duration-secs", "3"];
    let (ok, closed) = loadgen(&[&common[..], &["--concurrency", "1", "--expect", "200"]].concat());
    assert!(ok, "{closed:#}");
    let report = &closed["report"];
    assert!(report["throughput_rps"].as_f64().unwrap() > 0.0, "{closed:#}");
    assert!(report["latency_ok_ms"]["p50"].as_f64().unwrap() > 0.0);
    assert!(report["latency_ok_ms"]["p99"].as_f64().unwrap() >= report["latency_ok_ms"]["p50"].as_f64().unwrap());
    assert!(closed["server_memory_kib"]["after"]["peak_rss"].as_u64().unwrap() > 0);

    let (ok, open) = loadgen(&[&common[..], &["--rate", "40", "--expect", "200,429,503", "--recover"]].concat());
    assert!(ok, "{open:#}");
    assert_eq!(open["recovery"]["ok"], true, "{open:#}");
    let statuses = open["report"]["statuses"].as_object().unwrap();
    assert!(statuses.contains_key("503"), "40 requests/s on a queue of 2 must shed load: {open:#}");
    eprintln!("closed loop: {}\nopen loop: {}", closed["report"], open["report"]);
}
