#!/usr/bin/env bash
# Two server binaries, the same bundle and request, in interleaved rounds (A B B A), so that the
# machine's drift falls on both alike. Prints each round's client wall times; the servers' own
# stage timings are in OUT/a/server.log and OUT/b/server.log ("rendered timings=...").
#
#   bench/ab-servers.sh OLD_BINARY NEW_BINARY
#   BUNDLE=DIR (default: the parity fixtures' bundle)  EXAMPLE=DIR (default: examples/tabletop)
#   ROUNDS=N (default 8)  OUT=DIR (default target/ab-servers)
set -euo pipefail
[[ $# == 2 ]] || { echo "usage: bench/ab-servers.sh OLD_BINARY NEW_BINARY" >&2; exit 2; }
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "${repo}"
example=${EXAMPLE:-examples/tabletop}
out=${OUT:-${repo}/target/ab-servers}
ort=${SCNERF_ORT_DYLIB:-${repo}/third_party/onnxruntime/libonnxruntime.so.1.31.1}
SERVER_ARGS="--threads 2 --ort-dylib ${ort}"
# shellcheck source=scripts/_server.sh
source scripts/_server.sh
mkdir -p "${out}/a" "${out}/b"

SERVER=$1 OUT=${out}/a start_server
a_addr=${ADDR} a_pid=${SERVER_PID}
SERVER=$2 OUT=${out}/b start_server
b_addr=${ADDR}
trap 'kill ${a_pid} 2>/dev/null; stop_server' EXIT

render() {
  curl -fsS -o /dev/null -w '%{time_total}' -F "request=@${example}/request.json" \
    -F "source_0=@${example}/source_0.png" -F "source_1=@${example}/source_1.png" \
    -F "source_2=@${example}/source_2.png" "http://$1/v1/render"
}
echo "warm-up: A $(render "${a_addr}") B $(render "${b_addr}")"
for i in $(seq 1 "${ROUNDS:-8}"); do
  a1=$(render "${a_addr}"); b1=$(render "${b_addr}"); b2=$(render "${b_addr}"); a2=$(render "${a_addr}")
  echo "round ${i}: A ${a1} ${a2} B ${b1} ${b2}"
done
