#!/usr/bin/env bash
# The Python client (client-python/, `scnerf_client`) as a user gets it: `pip install` into a
# virtual environment of its own (numpy, Pillow and requests from PyPI, nothing of the exporter's),
# then its tests against the real server of this checkout (built here; the parity fixtures' small
# bundle). The environment is made once and kept; each run installs the client anew into it.
#   VENV=DIR   where the environment goes (default target/python-client-venv)
#   FRESH=1    empty it first
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "${repo}"
venv=${VENV:-${repo}/target/python-client-venv}
python=${PYTHON:-python3}
scripts/fetch-onnxruntime.sh
cargo build -j2 --locked -p scnerf-server
[[ ${FRESH:-0} == 1 ]] && rm -rf "${venv}"
if [[ ! -x ${venv}/bin/python ]]; then
  "${python}" -m venv "${venv}"
  "${venv}/bin/python" -m pip install --quiet --upgrade pip
fi
# --force-reinstall --no-deps: this checkout's client, whatever version number the last one had.
"${venv}/bin/python" -m pip install --quiet "${repo}/client-python[test]"
"${venv}/bin/python" -m pip install --quiet --force-reinstall --no-deps "${repo}/client-python"
# from outside the repository: the installed package, not the source folder, is imported
cd "${venv}"
SCNERF_SERVER_BIN=${repo}/target/debug/scnerf-server "${venv}/bin/python" -m pytest -q -p no:cacheprovider \
  "${repo}/client-python/tests"
