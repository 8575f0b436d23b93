#!/usr/bin/env bash
# The exporter's Python environment in <repo>/.venv: torch (CPU is enough; PyPI's wheel also
# carries CUDA), onnx, onnxruntime, numpy, pytest, and the project's Python client
# (client-python/, which the exporter and the benchmark drive the server with). Idempotent: a
# second run only re-checks.
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
python=${PYTHON:-python3}
[[ -x ${repo}/.venv/bin/python ]] || "${python}" -m venv "${repo}/.venv"
"${repo}/.venv/bin/python" -m pip install --quiet --upgrade pip
"${repo}/.venv/bin/python" -m pip install --quiet -e "${repo}/client-python" -e "${repo}/exporter[test]"
echo "python environment ready: ${repo}/.venv"
