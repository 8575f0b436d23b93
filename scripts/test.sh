#!/usr/bin/env bash
# Every test of the project: the lint gate (ruff, clippy, rustfmt), the Rust workspace (unit, HTTP,
# parity against the committed fixtures, end-to-end), scenes across two replicas behind Debian's
# nginx (scripts/proxy-test.sh), the hostile clients' short form (loadtest/attacks.sh), the
# exporter's pytest suite, the benchmark's, the Python client installed into a fresh venv against
# the real server (scripts/python-client-test.sh), the viewer in headless Chromium
# (scripts/viewer-test.sh) and the container files' static checks (docker/lint.sh). The scripts
# install what they miss with apt-get (nginx, Chromium), npm and pip, and fail when they cannot
# (SCNERF_ALLOW_SKIP=1 lets the proxy test skip on a machine without nginx). Needs crates.io, PyPI,
# npm and Debian's packages on the first run only.
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "${repo}"
scripts/fetch-onnxruntime.sh
scripts/setup-python.sh
python3 scripts/check-modules.py
.venv/bin/ruff check exporter bench scripts loadtest client-python
.venv/bin/ruff format --check exporter bench scripts loadtest client-python
cargo test -j2 --workspace --locked
cargo clippy --workspace --all-targets --locked -- -D warnings
cargo fmt --all --check
scripts/proxy-test.sh
loadtest/attacks.sh
.venv/bin/python -m pytest -q -p no:cacheprovider exporter/tests
.venv/bin/python -m pytest -q -p no:cacheprovider bench/tests
scripts/python-client-test.sh
scripts/viewer-test.sh
docker/lint.sh
