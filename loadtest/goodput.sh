#!/usr/bin/env bash
# Goodput under overload: views finished within their deadline per second, at 1x, 2x and 4x
# the measured service rate (LOADS), for one server binary. Renders of a cached scene in views
# of mixed sizes (SIZES), each with an x-scnerf-deadline-ms of DEADLINE_MS, open loop for
# DURATION s per load after MEASURE_SECS of closed-loop renders (1 worker) that measure the
# service rate. SERVER_BIN=PATH measures another build of the server (e.g. an older one) with
# the same load generator. Reports: target/loadtest/goodput-{rate,Lx}.json and a table on stderr.
#   PROFILE=release BUNDLE=bundles/default loadtest/goodput.sh
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/../scripts/_server.sh"
DURATION=${DURATION:-60}
MEASURE_SECS=${MEASURE_SECS:-30}
SIZES=${SIZES:-32,64,96}
LOADS=${LOADS:-1 2 4}
DEADLINE_MS=${DEADLINE_MS:-5000}

build_binaries
start_server
common=(--addr "${ADDR}" --server-pid "${SERVER_PID}" --size "${SIZES}" --deadline-ms "${DEADLINE_MS}" --json)
"${BIN_DIR}/loadgen" "${common[@]}" --concurrency 1 --duration-secs "${MEASURE_SECS}" | tee "${OUT}/goodput-rate.json"
rate=$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["report"]["throughput_rps"])' "${OUT}/goodput-rate.json")
for load in ${LOADS}; do
  offered=$(python3 -c "print(${load} * ${rate})")
  echo "offered ${offered} requests/s (${load}x) for ${DURATION} s" >&2
  "${BIN_DIR}/loadgen" "${common[@]}" --rate "${offered}" --duration-secs "${DURATION}" | tee "${OUT}/goodput-${load}x.json"
done
python3 - "${OUT}" "${rate}" ${LOADS} <<'PY'
import json, sys
out, rate, loads = sys.argv[1], float(sys.argv[2]), sys.argv[3:]
print(f"service rate {rate} views/s; deadline {json.load(open(f'{out}/goodput-rate.json'))['deadline_ms']} ms", file=sys.stderr)
print("| load | offered req/s | goodput views/s | statuses | p99 of 200s ms |", file=sys.stderr)
for load in loads:
    r = json.load(open(f"{out}/goodput-{load}x.json"))
    rep = r["report"]
    print(f"| {load}x | {r['mode']['open_loop']['rate_rps']:.3f} | {rep['goodput_rps']} | {rep['statuses']} | "
          f"{rep['latency_ok_ms']['p99']} |", file=sys.stderr)
PY
