#!/usr/bin/env bash
# Short load test of the cached-scene endpoint over loopback, with SIZE x SIZE targets:
#  1. closed loop with CONCURRENCY workers for DURATION s: the sustainable throughput;
#  2. open loop at 4x that rate for DURATION s: only 200/429/503 may come back, and afterwards
#     the server must drain its queue and render again (loadgen --recover).
# Reports (JSON) land in target/loadtest/. Environment: see scripts/_server.sh, and
#   DURATION (60), SIZE (64), CONCURRENCY (2), OVERLOAD (4).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/../scripts/_server.sh"
DURATION=${DURATION:-60}
SIZE=${SIZE:-64}
CONCURRENCY=${CONCURRENCY:-2}
OVERLOAD=${OVERLOAD:-4}

build_binaries
start_server
common=(--addr "${ADDR}" --server-pid "${SERVER_PID}" --size "${SIZE}" --duration-secs "${DURATION}" --json)

echo "closed loop: ${CONCURRENCY} workers, ${DURATION} s, ${SIZE}x${SIZE}" >&2
"${BIN_DIR}/loadgen" "${common[@]}" --concurrency "${CONCURRENCY}" --expect 200 | tee "${OUT}/closed.json"
rate=$(python3 -c 'import json,sys; print(max(0.1, float(sys.argv[2]) * json.load(open(sys.argv[1]))["report"]["throughput_rps"]))' \
  "${OUT}/closed.json" "${OVERLOAD}")

echo "open loop: ${rate} requests/s (${OVERLOAD}x), ${DURATION} s" >&2
"${BIN_DIR}/loadgen" "${common[@]}" --rate "${rate}" --expect 200,429,503 --recover | tee "${OUT}/open.json"
echo "reports: ${OUT}/closed.json ${OUT}/open.json" >&2
