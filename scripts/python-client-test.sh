#!/usr/bin/env bash
# The Python client (client-python/, `scnerf_client`) as a user gets it: `pip install` into a fresh
# virtual environment (numpy, Pillow and requests from PyPI, nothing of the exporter's), then its
# tests against the real server of this checkout (built here; the parity fixtures' small bundle).
#   VENV=DIR   where the fresh environment goes (default target/python-client-venv; emptied first)
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "${repo}"
venv=${VENV:-${repo}/target/python-client-venv}
python=${PYTHON:-python3}
scripts/fetch-onnxruntime.sh
cargo build -j2 --locked -p scnerf-server
rm -rf "${venv}"
"${python}" -m venv "${venv}"
"${venv}/bin/python" -m pip install --quiet --upgrade pip
"${venv}/bin/python" -m pip install --quiet "${repo}/client-python[test]"
# from outside the repository: the installed package, not the source folder, is imported
cd "${venv}"
SCNERF_SERVER_BIN=${repo}/target/debug/scnerf-server "${venv}/bin/python" -m pytest -q -p no:cacheprovider \
  "${repo}/client-python/tests"
