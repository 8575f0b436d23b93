#!/usr/bin/env bash
# Two server binaries, the same bundle and request, in interleaved rounds (A B B A), so that the
# machine's drift falls on both alike. Prints each round's client wall times; the servers' own
# stage timings are in OUT/a.log and OUT/b.log ("rendered timings=...").
#
#   bench/ab-servers.sh OLD_BINARY NEW_BINARY
#   BUNDLE=DIR (default: the parity fixtures' bundle)  EXAMPLE=DIR (default: examples/tabletop)
#   ROUNDS=N (default 8)  OUT=DIR (default target/ab-servers)
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "${repo}"
[[ $# == 2 ]] || { echo "usage: bench/ab-servers.sh OLD_BINARY NEW_BINARY" >&2; exit 2; }
bundle=${BUNDLE:-tests/fixtures/parity/bundle}
example=${EXAMPLE:-examples/tabletop}
out=${OUT:-target/ab-servers}
ort=${SCNERF_ORT_DYLIB:-${repo}/third_party/onnxruntime/libonnxruntime.so.1.31.1}
mkdir -p "${out}"
"$1" --bundle "${bundle}" --addr 127.0.0.1:18081 --threads 2 --ort-dylib "${ort}" > "${out}/a.log" 2>&1 &
a=$!
"$2" --bundle "${bundle}" --addr 127.0.0.1:18082 --threads 2 --ort-dylib "${ort}" > "${out}/b.log" 2>&1 &
b=$!
trap 'kill ${a} ${b} 2>/dev/null' EXIT
for port in 18081 18082; do
  for _ in $(seq 1 240); do curl -fsS "http://127.0.0.1:${port}/readyz" > /dev/null 2>&1 && break; sleep 0.5; done
done
render() {
  curl -fsS -o /dev/null -w '%{time_total}' -F "request=@${example}/request.json" \
    -F "source_0=@${example}/source_0.png" -F "source_1=@${example}/source_1.png" \
    -F "source_2=@${example}/source_2.png" "http://127.0.0.1:$1/v1/render"
}
echo "warm-up: A $(render 18081) B $(render 18082)"
for i in $(seq 1 "${ROUNDS:-8}"); do
  a1=$(render 18081); b1=$(render 18082); b2=$(render 18082); a2=$(render 18081)
  echo "round ${i}: A ${a1} ${a2} B ${b1} ${b2}"
done
