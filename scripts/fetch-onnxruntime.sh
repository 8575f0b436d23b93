#!/usr/bin/env bash
# Fetch the ONNX Runtime shared library the server loads at run time (ort `load-dynamic`).
#
# We take libonnxruntime.so from the official PyPI wheel of onnxruntime 1.31.1 (CPU build,
# manylinux x86_64): the wheel is a plain zip, so no pip and no Python packages are needed.
# The wheel's sha256 is pinned below; a mismatch aborts. The library lands in
# third_party/onnxruntime/ (git-ignored), where scnerf-server looks for it by default.
#
# Usage: scripts/fetch-onnxruntime.sh [DEST_DIR]     (default: <repo>/third_party/onnxruntime)
set -euo pipefail

VERSION=1.31.1
WHEEL=onnxruntime-${VERSION}-cp311-cp311-manylinux_2_28_x86_64.whl
URL=https://files.pythonhosted.org/packages/b4/1d/0f85ee31a3d93f2243a5cc29252becf858f53ac5cfa6c9c15d9ffe107eea/${WHEEL}
SHA256=5752bd508126ae7c49894d3b9d2e83f0c3d487319246d04c444b393308d7ad7f
MEMBER=onnxruntime/capi/libonnxruntime.so.${VERSION}

repo_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
dest=${1:-${repo_root}/third_party/onnxruntime}
lib=${dest}/libonnxruntime.so.${VERSION}

case "$(uname -s)-$(uname -m)" in
  Linux-x86_64) ;;
  *) echo "fetch-onnxruntime: only Linux x86_64 is supported by this script; point SCNERF_ORT_DYLIB at your own libonnxruntime ${VERSION}" >&2; exit 1 ;;
esac

if [[ -f ${lib} && -f ${dest}/.wheel-sha256 && $(cat "${dest}/.wheel-sha256") == "${SHA256}" ]]; then
  echo "onnxruntime ${VERSION} already present: ${lib}"
  exit 0
fi

mkdir -p "${dest}"
tmp=$(mktemp -d)
trap 'rm -rf "${tmp}"' EXIT

echo "downloading ${WHEEL} ..."
curl --fail --location --silent --show-error --retry 3 -o "${tmp}/${WHEEL}" "${URL}"

actual=$(sha256sum "${tmp}/${WHEEL}" | cut -d' ' -f1)
if [[ ${actual} != "${SHA256}" ]]; then
  echo "fetch-onnxruntime: sha256 mismatch for ${WHEEL}: expected ${SHA256}, got ${actual}" >&2
  exit 1
fi

# Extract just the one library with the standard library's zipfile (unzip may be absent).
python3 - "${tmp}/${WHEEL}" "${MEMBER}" "${tmp}/lib.so" <<'PY'
import shutil, sys, zipfile
wheel, member, out = sys.argv[1:]
with zipfile.ZipFile(wheel) as z, z.open(member) as src, open(out, "wb") as dst:
    shutil.copyfileobj(src, dst)
PY
mv "${tmp}/lib.so" "${lib}"
ln -sf "libonnxruntime.so.${VERSION}" "${dest}/libonnxruntime.so"
echo "${SHA256}" > "${dest}/.wheel-sha256"
echo "onnxruntime ${VERSION} installed: ${lib}"
