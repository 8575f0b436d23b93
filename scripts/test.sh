#!/usr/bin/env bash
# Every test of the project: the Python lint (ruff, configured in ruff.toml), the Rust workspace
# (unit, HTTP, parity against the committed fixtures, end-to-end), the exporter's pytest suite and
# the benchmark's, and scenes across two replicas behind Debian's nginx (scripts/proxy-test.sh:
# 20-30 s; installs nginx with apt-get when missing, says SKIPPED when it cannot). Needs network
# access to crates.io and PyPI on the first run only.
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "${repo}"
scripts/fetch-onnxruntime.sh
scripts/setup-python.sh
.venv/bin/ruff check exporter bench scripts
.venv/bin/ruff format --check exporter bench scripts
cargo test -j2 --workspace --locked
cargo clippy --workspace --all-targets --locked -- -D warnings
cargo fmt --all --check
scripts/proxy-test.sh
.venv/bin/python -m pytest -q -p no:cacheprovider exporter/tests
.venv/bin/python -m pytest -q -p no:cacheprovider bench/tests
