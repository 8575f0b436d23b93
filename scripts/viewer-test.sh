#!/usr/bin/env bash
# The viewer's camera conventions against the rules' fixtures (scripts/browser-test/camera.test.mjs,
# node --test), then the browser viewer (GET /) in a real browser: builds the server, serves a bundle with
# a bearer token on a free port, and drives Debian's Chromium headless through
# scripts/browser-test/viewer-test.mjs (Node's playwright-core): the token prompt, the first
# render and its finer sizes, depth/opacity, the PNG download, a mouse drag to a new pose, a
# second drag that aborts a render in flight (checked in the server's log: its remaining chunks
# never run), keyboard snapping, captures, the model picker (a copy of the bundle is served as a
# second model), and that every request stays on the server. Installs Chromium (apt) and the npm package when they are missing. Exits non-zero on
# failure. Needs Node.js >= 20.19.
#
#   OUT=DIR          screenshots, the server's log (default target/viewer-test)
#   CHROMIUM=PATH    the browser (default /usr/bin/chromium)
#   BUNDLE=DIR       the bundle served (default: the parity fixtures' small random-weight bundle:
#                    the page's mechanics do not depend on the weights, and the paper-size default
#                    takes minutes per view on two cores)
#   PROFILE=release  build and run the release server (default debug: the graphs run in ONNX
#                    Runtime either way)
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "${repo}"
export OUT=${OUT:-${repo}/target/viewer-test}
export CHROMIUM=${CHROMIUM:-/usr/bin/chromium}
export BUNDLE=${BUNDLE:-${repo}/tests/fixtures/parity/bundle}
mkdir -p "${OUT}"
rm -f "${OUT}/failure.png"

if [[ ! -x ${CHROMIUM} ]]; then
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium > /dev/null
fi
command -v node > /dev/null || { echo "viewer-test: Node.js >= 20.19 is needed (node not found)" >&2; exit 1; }
node --test scripts/browser-test/camera.test.mjs
(cd scripts/browser-test && npm ci --no-audit --no-fund --loglevel=error)

# shellcheck source=scripts/_server.sh
source scripts/_server.sh
scripts/fetch-onnxruntime.sh
build_binaries

# The token makes the page prove its token field; the executor's debug lines (one per graph run,
# with the request id the page sent) let the test see which work of an aborted request ran.
export VIEWER_TOKEN=viewer-test-token
export SCNERF_AUTH_TOKENS=${VIEWER_TOKEN}
export RUST_LOG=info,ort=warn,scnerf_server::backend=debug
# A second model (a copy of the bundle, named by its folder) gives the page's model picker a choice.
rm -rf "${OUT}/models" && mkdir -p "${OUT}/models" && cp -r "${BUNDLE}" "${OUT}/models/second"
SERVER_ARGS="--log-format json --bundle ${OUT}/models/second" start_server
echo "viewer-test: server at http://${ADDR}/ (log: ${OUT}/server.log)"

started=${SECONDS}
VIEWER_URL="http://${ADDR}/" SERVER_LOG="${OUT}/server.log" node scripts/browser-test/viewer-test.mjs
echo "viewer-test: passed in $((SECONDS - started)) s in the browser; screenshots in ${OUT}"
