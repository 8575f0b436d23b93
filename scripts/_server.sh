# Shared by loadtest/*.sh, schemathesis.sh and viewer-test.sh (source it): build, start and stop a
# scnerf-server on a free loopback port.
#
#   PROFILE=debug|release   binaries to build and run (default debug: the graphs run in ONNX
#                           Runtime either way; release only speeds up the Rust side)
#   BUNDLE=DIR              bundle to serve (default: the committed parity-fixture bundle)
#   SERVER_ARGS="..."       extra server flags
#   SERVER_BIN=PATH         run this server binary instead of the one built here

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
PROFILE=${PROFILE:-debug}
BUNDLE=${BUNDLE:-${repo}/tests/fixtures/parity/bundle}
OUT=${OUT:-${repo}/target/loadtest}
mkdir -p "${OUT}"

build_binaries() {
  local flags=(-j2 -p scnerf-server -p scnerf-loadtest --bins)
  [[ ${PROFILE} == release ]] && flags+=(--release)
  (cd "${repo}" && cargo build "${flags[@]}")
  BIN_DIR=${repo}/target/${PROFILE}
  SERVER=${SERVER_BIN:-${BIN_DIR}/scnerf-server}
}

# Starts the server; sets SERVER_PID and ADDR; waits for /readyz.
start_server() {
  local log=${OUT}/server.log
  # shellcheck disable=SC2086
  "${SERVER}" --bundle "${BUNDLE}" --addr 127.0.0.1:0 ${SERVER_ARGS:-} >"${OUT}/server.stdout" 2>"${log}" &
  SERVER_PID=$!
  trap stop_server EXIT
  for _ in $(seq 600); do
    ADDR=$(sed -n 's|^listening on http://||p' "${OUT}/server.stdout" 2>/dev/null || true)
    [[ -n ${ADDR} ]] && break
    kill -0 "${SERVER_PID}" 2>/dev/null || { cat "${log}" >&2; echo "server exited" >&2; exit 1; }
    sleep 0.1
  done
  for _ in $(seq 1200); do
    curl -fsS "http://${ADDR}/readyz" >/dev/null 2>&1 && return 0
    sleep 0.25
  done
  echo "server not ready" >&2
  exit 1
}

stop_server() {
  if [[ -n ${SERVER_PID:-} ]] && kill -0 "${SERVER_PID}" 2>/dev/null; then
    kill -TERM "${SERVER_PID}"
    wait "${SERVER_PID}" || true
  fi
}
