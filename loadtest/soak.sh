#!/usr/bin/env bash
# Soak test at a steady overload: renders of a cached scene in views of mixed sizes (SIZES) for
# SOAK_SECS (default 1800 = 30 min), open loop at LOAD (default 2) x the service rate measured
# first in MEASURE_SECS of closed-loop renders (1 worker), each with a DEADLINE_MS deadline,
# while the server's RSS is sampled every RSS_EVERY s. Passes when only 200 and the overload
# answers (429, 503, 504) come back and the RSS grew by at most MAX_GROWTH_PCT (default 5 %)
# between the end of the first fifth of the run (warm-up: ONNX Runtime's arena, allocator
# pools) and the end. Reports: target/loadtest/soak-rate.json, soak.json (with the RSS series).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/../scripts/_server.sh"
SOAK_SECS=${SOAK_SECS:-1800}
MEASURE_SECS=${MEASURE_SECS:-60}
SIZES=${SIZES:-32,64,96}
LOAD=${LOAD:-2}
DEADLINE_MS=${DEADLINE_MS:-10000}
RSS_EVERY=${RSS_EVERY:-30}
MAX_GROWTH_PCT=${MAX_GROWTH_PCT:-5}

build_binaries
start_server
common=(--addr "${ADDR}" --server-pid "${SERVER_PID}" --size "${SIZES}" --json)
"${BIN_DIR}/loadgen" "${common[@]}" --concurrency 1 --duration-secs "${MEASURE_SECS}" --expect 200 \
  | tee "${OUT}/soak-rate.json"
rate=$(python3 -c 'import json,sys; print(float(sys.argv[2]) * json.load(open(sys.argv[1]))["report"]["throughput_rps"])' \
  "${OUT}/soak-rate.json" "${LOAD}")
echo "soak: ${rate} requests/s (${LOAD} x the measured rate) for ${SOAK_SECS} s" >&2
"${BIN_DIR}/loadgen" "${common[@]}" --rate "${rate}" --deadline-ms "${DEADLINE_MS}" --duration-secs "${SOAK_SECS}" \
  --rss-every-secs "${RSS_EVERY}" --expect 200,429,503,504 | tee "${OUT}/soak.json"
python3 - "${OUT}/soak.json" "${MAX_GROWTH_PCT}" <<'PY'
import json, sys
report = json.load(open(sys.argv[1]))
series = [kib / 1024 for _, kib in report["rss_series_kib"]]
warm, end = series[len(series) // 5], series[-1]
growth = 100 * (end - warm) / warm
r = report["report"]
print(f"statuses {r['statuses']}; goodput {r['goodput_rps']} views/s; latency of 200s p50/p95/p99 "
      f"{r['latency_ok_ms']['p50']}/{r['latency_ok_ms']['p95']}/{r['latency_ok_ms']['p99']} ms", file=sys.stderr)
print(f"RSS MiB: start {series[0]:.0f}, after warm-up {warm:.0f}, end {end:.0f}, max {max(series):.0f}; "
      f"growth after warm-up {growth:+.2f} % (limit {sys.argv[2]} %)", file=sys.stderr)
sys.exit(0 if growth <= float(sys.argv[2]) else 1)
PY
