#!/usr/bin/env bash
# The robustness probe's hostile clients (loadtest/attacks.py) against a fresh server. Short form
# by default (CI: the parity-fixture bundle, a debug build, small sizes, a small memory budget);
# SCALE=full with PROFILE=release BUNDLE=bundles/default for the probe's own sizes. The server's
# peak resident set must stay under MEMORY_BUDGET_MB. Environment: see scripts/_server.sh, and
#   SCALE (short), MEMORY_BUDGET_MB (short: 1200 with a 256 MiB scene cache; full: 3000 and the
#   default cache), STALL_SECS (short: 3, full: 10).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/../scripts/_server.sh"
SCALE=${SCALE:-short}
if [[ ${SCALE} == full ]]; then
  MEMORY_BUDGET_MB=${MEMORY_BUDGET_MB:-3000}
  STALL_SECS=${STALL_SECS:-10}
else
  MEMORY_BUDGET_MB=${MEMORY_BUDGET_MB:-1200}
  SERVER_ARGS="--scene-cache-mb 256 ${SERVER_ARGS:-}"
  STALL_SECS=${STALL_SECS:-3}
fi
SERVER_ARGS="--memory-budget-mb ${MEMORY_BUDGET_MB} --body-stall-secs ${STALL_SECS} ${SERVER_ARGS:-}"
build_binaries
start_server
"${repo}/.venv/bin/python" "${repo}/loadtest/attacks.py" --addr "${ADDR}" --pid "${SERVER_PID}" --scale "${SCALE}" \
  --budget-mb "${MEMORY_BUDGET_MB}" --stall-secs "${STALL_SECS}" "$@" | tee "${OUT}/attacks-${SCALE}.jsonl"
