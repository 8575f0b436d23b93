#!/usr/bin/env bash
# Soak test: SOAK_SECS (default 1800 = 30 min) of closed-loop renders of a cached scene
# (CONCURRENCY workers, SIZE x SIZE targets) while the server's RSS is sampled every
# RSS_EVERY s. Passes when every status is 200 and the RSS grew by at most MAX_GROWTH_MIB
# (default 64) between the end of the first fifth of the run (warm-up: ONNX Runtime's arena,
# allocator pools) and the end. Report: target/loadtest/soak.json (with the RSS series).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/_server.sh"
SOAK_SECS=${SOAK_SECS:-1800}
SIZE=${SIZE:-64}
CONCURRENCY=${CONCURRENCY:-2}
RSS_EVERY=${RSS_EVERY:-30}
MAX_GROWTH_MIB=${MAX_GROWTH_MIB:-64}

build_binaries
start_server
"${BIN_DIR}/loadgen" --addr "${ADDR}" --server-pid "${SERVER_PID}" --size "${SIZE}" --concurrency "${CONCURRENCY}" \
  --duration-secs "${SOAK_SECS}" --rss-every-secs "${RSS_EVERY}" --expect 200 --json | tee "${OUT}/soak.json"
python3 - "${OUT}/soak.json" "${MAX_GROWTH_MIB}" <<'PY'
import json, sys
report = json.load(open(sys.argv[1]))
growth = report["rss_growth_after_warmup_kib"] / 1024
series = [kib / 1024 for _, kib in report["rss_series_kib"]]
print(f"RSS MiB: start {series[0]:.0f}, after warm-up {series[len(series) // 5]:.0f}, end {series[-1]:.0f}, "
      f"max {max(series):.0f}; growth after warm-up {growth:+.1f} MiB (limit {sys.argv[2]})", file=sys.stderr)
sys.exit(0 if growth <= float(sys.argv[2]) else 1)
PY
