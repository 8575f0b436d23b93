#!/usr/bin/env bash
# Soak with mixed traffic (loadtest/attacks.py --soak-secs): renders of a cached scene without
# pause, and in turn each of the probe's hostile clients and a capture uploaded, rendered and
# deleted, for SOAK_SECS (default 1800); passes when every attack got its answer and the server's
# RSS outside its scene cache grew by at most MAX_GROWTH_PCT (default 5 %) after the first fifth
# (warm-up). Scenes the hostile clients upload stay cached until their TTL: SCENE_TTL_SECS (60)
# keeps it well inside the warm-up, so that what grows after it is a leak, not the cache filling.
# Short-form sizes for the hostile clients, so that the soak measures leaks rather than the
# machine's memory. Report: target/loadtest/soak-mixed.json. Environment: see scripts/_server.sh,
# and SOAK_SECS, MAX_GROWTH_PCT, MEMORY_BUDGET_MB (3000, with a 512 MiB scene cache: room for the
# capture rounds beside the renders), SCENE_TTL_SECS (60), STALL_SECS (3).
#   PROFILE=release BUNDLE=bundles/default loadtest/soak-mixed.sh
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/../scripts/_server.sh"
SOAK_SECS=${SOAK_SECS:-1800}
MAX_GROWTH_PCT=${MAX_GROWTH_PCT:-5}
MEMORY_BUDGET_MB=${MEMORY_BUDGET_MB:-3000}
STALL_SECS=${STALL_SECS:-3}
SCENE_TTL_SECS=${SCENE_TTL_SECS:-60}
SERVER_ARGS="--memory-budget-mb ${MEMORY_BUDGET_MB} --scene-cache-mb 512 --scene-ttl-secs ${SCENE_TTL_SECS} --body-stall-secs ${STALL_SECS} ${SERVER_ARGS:-}"
build_binaries
start_server
"${repo}/.venv/bin/python" "${repo}/loadtest/attacks.py" --addr "${ADDR}" --pid "${SERVER_PID}" --scale short \
  --budget-mb "${MEMORY_BUDGET_MB}" --stall-secs "${STALL_SECS}" --soak-secs "${SOAK_SECS}" \
  --max-growth-pct "${MAX_GROWTH_PCT}" | tee "${OUT}/soak-mixed.json"
