#!/usr/bin/env bash
# Fresh machine -> a rendered view: fetch ONNX Runtime, build the server, serve the default
# bundle, POST the committed example (three photos of a procedural tabletop + a target camera) with
# curl, and say where the PNG went. Then keep the server up and print the browser viewer's URL
# (the same example, docs/viewer.md) until Ctrl-C. Only Rust (rustup), curl and python3 are needed.
#
#   scripts/quickstart.sh [--exit]   --exit (or QUICKSTART_EXIT=1): stop the server and exit after
#                                    the render, for scripts and CI
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "${repo}"
exit_after_render=${QUICKSTART_EXIT:-0}
for arg in "$@"; do
  case ${arg} in
    --exit) exit_after_render=1 ;;
    *) echo "usage: scripts/quickstart.sh [--exit]" >&2; exit 2 ;;
  esac
done
addr=${SCNERF_ADDR:-127.0.0.1:8080}
example=${EXAMPLE:-examples/tabletop}
out=${OUT:-${repo}/target/quickstart}
mkdir -p "${out}"

scripts/fetch-onnxruntime.sh
cargo build --release -j2 -p scnerf-server --locked

target/release/scnerf-server --addr "${addr}" --viewer-example "${example}" > "${out}/server.log" 2>&1 &
server=$!
trap 'kill ${server} 2>/dev/null; wait ${server} 2>/dev/null || true' EXIT
for _ in $(seq 1 600); do
  curl -fsS "http://${addr}/readyz" > /dev/null 2>&1 && break
  kill -0 ${server} 2>/dev/null || { cat "${out}/server.log" >&2; exit 1; }
  sleep 0.5
done
curl -fsS "http://${addr}/v1/model" > "${out}/model.json"

curl -fsS -o "${out}/view.png" \
  -F request=@${example}/request.json \
  -F source_0=@${example}/source_0.png -F source_1=@${example}/source_1.png -F source_2=@${example}/source_2.png \
  -H 'Accept: image/png' "http://${addr}/v1/render"
echo "rendered ${example} with $(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["model_id"])' "${out}/model.json")"
echo "wrote ${out}/view.png (ground truth: ${example}/target_truth.png)"
[[ ${exit_after_render} == 1 ]] && exit 0

echo "viewer: http://${addr}/"
echo "the server keeps running (log: ${out}/server.log); Ctrl-C stops it"
wait ${server}
