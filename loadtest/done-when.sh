#!/usr/bin/env bash
# The fourth robustness probe's conditions of done against the release binary
# (loadtest/done_when.py: one JSON line per check, exit 1 when one fails). Environment:
#   SERVER_BIN (default target/release/scnerf-server, built here), OUT (target/loadtest),
#   PYTHON (the repository's .venv).
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
OUT=${OUT:-${repo}/target/loadtest}
if [[ -z ${SERVER_BIN:-} ]]; then
  (cd "${repo}" && cargo build --release -j2 -p scnerf-server)
  SERVER_BIN=${repo}/target/release/scnerf-server
fi
mkdir -p "${OUT}"
"${PYTHON:-${repo}/.venv/bin/python}" "${repo}/loadtest/done_when.py" --binary "${SERVER_BIN}" --out "${OUT}" "$@" \
  | tee "${OUT}/done-when.jsonl"
