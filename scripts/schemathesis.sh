#!/usr/bin/env bash
# Property-based API testing with schemathesis (PyPI) against the server's own /openapi.json:
# generated valid and invalid requests for every operation, checked for server errors (no 5xx),
# and for conformance of statuses, content types, headers and bodies to the document.
# Installs schemathesis into .venv on first use. The server runs with a bearer token (sent with
# every request) so that the protected operations are exercised. Reports: target/loadtest/.
#   MAX_EXAMPLES (25): test cases per operation; CHECKS (all); SEED (0); see also _server.sh;
#   EXCLUDE_CHECKS (positive_data_acceptance): that check expects every schema-valid request to
#   succeed, but validity here goes beyond what a schema can say (images must decode to the
#   camera's size, poses must be rotations, near < far), so schema-valid requests get 400/422.
# scripts/schemathesis_hooks.py makes half the JSON scene creations valid, so that the stateful
# phase creates scenes and follows the links to render and delete them.
# The `x-scnerf-deadline-ms` header is pinned to 120 s: a client asking for a 1 ms deadline gets
# the documented 504, which is not a server error; pinned, any 5xx is a real failure.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/_server.sh"
MAX_EXAMPLES=${MAX_EXAMPLES:-25}
CHECKS=${CHECKS:-all}
EXCLUDE_CHECKS=${EXCLUDE_CHECKS:-positive_data_acceptance}
SEED=${SEED:-0}
TOKEN=schemathesis-$$-token

venv=${repo}/.venv
[[ -x ${venv}/bin/python ]] || python3 -m venv "${venv}"
[[ -x ${venv}/bin/schemathesis ]] || "${venv}/bin/python" -m pip install -q schemathesis

build_binaries
SERVER_ARGS="${SERVER_ARGS:-} --auth-token ${TOKEN} --request-timeout-secs 120"
start_server
config=${OUT}/schemathesis.toml
cat >"${config}" <<'TOML'
[parameters]
"header.x-scnerf-deadline-ms" = "120000"
TOML
# Valid scenes for POST /v1/scenes, so that the stateful phase follows its links (see the file).
export SCHEMATHESIS_HOOKS=schemathesis_hooks PYTHONPATH="${repo}/scripts${PYTHONPATH:+:${PYTHONPATH}}"
"${venv}/bin/schemathesis" --config-file "${config}" run "http://${ADDR}/openapi.json" \
  --header "Authorization: Bearer ${TOKEN}" \
  --checks "${CHECKS}" ${EXCLUDE_CHECKS:+--exclude-checks "${EXCLUDE_CHECKS}"} \
  --max-examples "${MAX_EXAMPLES}" --seed "${SEED}" --workers 1 \
  --request-timeout 180 --no-color \
  --report junit,ndjson --report-dir "${OUT}/schemathesis"
