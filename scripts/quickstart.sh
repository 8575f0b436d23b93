#!/usr/bin/env bash
# Fresh machine -> a rendered view: fetch ONNX Runtime, build the server, serve the default
# bundle, POST the committed example (three views of a procedural scene + a target camera) with
# curl, and say where the PNG went. Only Rust (rustup), curl and python3 are needed.
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "${repo}"
addr=${SCNERF_ADDR:-127.0.0.1:8080}
example=${EXAMPLE:-examples/tabletop}
out=${OUT:-${repo}/target/quickstart}
mkdir -p "${out}"

scripts/fetch-onnxruntime.sh
cargo build --release -j2 -p scnerf-server --locked

target/release/scnerf-server --addr "${addr}" > "${out}/server.log" 2>&1 &
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
