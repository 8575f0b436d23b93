#!/bin/bash
# Entrypoint of the `loadgen` image (docker/compose.yaml). The project's load generator takes the
# server as --addr IP:PORT, so this resolves a host name (the compose service `server`) first, adds
# the example scene as the default --case, and, when it shares the server's PID namespace
# (compose `pid: service:server`), passes the server's pid so the report includes its peak RSS.
# Every argument is passed on to loadgen (`loadgen --help` for the list).
#   SCNERF_LOADGEN_TARGET  HOST:PORT of the server (default server:8080)
#   SCNERF_LOADGEN_CASE    request.json + source_0..2.png (default /opt/scnerf/examples/tabletop)
set -euo pipefail

args=()
if [[ " $* " != *" --addr "* ]]; then
  target=${SCNERF_LOADGEN_TARGET:-server:8080}
  host=${target%:*}
  port=${target##*:}
  ip=
  for _ in $(seq 30); do
    read -r ip _ < <(getent ahostsv4 "${host}" || true) || true
    [[ -n ${ip} ]] && break
    sleep 1
  done
  if [[ -z ${ip} ]]; then
    echo "loadgen.sh: cannot resolve ${host}" >&2
    exit 2
  fi
  args+=(--addr "${ip}:${port}")
fi
if [[ " $* " != *" --case "* ]]; then
  args+=(--case "${SCNERF_LOADGEN_CASE:-/opt/scnerf/examples/tabletop}")
fi
if [[ " $* " != *" --server-pid "* ]]; then
  for comm in /proc/[0-9]*/comm; do
    if [[ $(cat "${comm}" 2>/dev/null) == scnerf-server ]]; then
      pid=${comm#/proc/}
      args+=(--server-pid "${pid%/comm}")
      break
    fi
  done
fi
echo "loadgen ${args[*]} $*" >&2
exec /usr/local/bin/loadgen "${args[@]}" "$@"
