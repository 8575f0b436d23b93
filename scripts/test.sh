#!/usr/bin/env bash
# The project's tests, in two tiers.
#
#   scripts/test.sh          the fast tier, which CI runs: the lint gate (module rules, ruff,
#                            rustfmt, and clippy on every target as the tests are built), the Rust
#                            workspace (unit, HTTP, parity against the committed fixtures,
#                            end-to-end on small bundles, the default bundle on the committed
#                            example), scenes across two replicas behind Debian's nginx
#                            (scripts/proxy-test.sh), the hostile clients' short form
#                            (loadtest/attacks.sh), the exporter's pytest suite less its `slow`
#                            tests, the benchmark's, the Python client installed into its own venv
#                            against the real server (scripts/python-client-test.sh), the viewer in
#                            headless Chromium (scripts/viewer-test.sh) and the container files'
#                            static checks (docker/lint.sh).
#   scripts/test.sh --full   all of that, plus the paper-size and long checks: pytest's `slow`
#                            tests (real scenes at the paper's protocol, refine for minutes) and the
#                            Rust tests built with `cfg(full_tier)` (lego through the server, the
#                            lego orbit through `scnerf render`). A change to the model, sampling or
#                            the bundle format needs this tier to pass.
#
# Each stage prints how long it took; a table of all of them closes the run, and pytest lists its
# 15 slowest tests. The scripts install what they miss with apt-get (nginx, Chromium), npm and pip,
# and fail when they cannot (SCNERF_ALLOW_SKIP=1 lets the proxy test skip on a machine without
# nginx). Needs crates.io, PyPI, npm and Debian's packages on the first run only. Tests that need
# the scenes of ../shared skip, saying so, without it.
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "${repo}"

tier=fast
case ${1:-} in
  "") ;;
  --full) tier=full ;;
  *) echo "usage: scripts/test.sh [--full]" >&2; exit 2 ;;
esac
# Read by the build scripts of the crates with full-tier tests (tests/test_cfg.rs).
export SCNERF_TEST_TIER=${tier}
pytest_tier=(-m "not slow")
[[ ${tier} == full ]] && pytest_tier=()

timings=()
suite_started=${SECONDS}
stage() {
  local name=$1 started=${SECONDS}
  shift
  current_stage=${name}
  echo "==> ${name}"
  "$@"
  timings+=("$(printf '%5d s  %s' $((SECONDS - started)) "${name}")")
  echo "<== ${name}: $((SECONDS - started)) s"
}
report() {
  local status=$?
  if [[ -n ${python_setup_pid:-} ]]; then kill "${python_setup_pid}" 2> /dev/null || true; fi
  echo "== scripts/test.sh (${tier} tier): stage times"
  printf '%s\n' "${timings[@]}"
  printf '%5d s  in all%s\n' $((SECONDS - suite_started)) \
    "$([[ ${status} -eq 0 ]] || echo ", failed with status ${status} in: ${current_stage:-setup}")"
}
trap report EXIT

pytest() {
  .venv/bin/python -m pytest -q -p no:cacheprovider --durations=15 "$@"
}
python_lint() {
  python3 scripts/check-modules.py
  .venv/bin/ruff check exporter bench scripts loadtest client-python
  .venv/bin/ruff format --check exporter bench scripts loadtest client-python
}
# The Python environment installs (from pip's cache, after the first run: mostly unpacking torch)
# while the Rust workspace builds, which keeps both cores busy.
python_setup_log=target/test-logs/setup-python.log
start_python_setup() {
  mkdir -p target/test-logs
  scripts/setup-python.sh > "${python_setup_log}" 2>&1 &
  python_setup_pid=$!
}
wait_for_python_setup() {
  wait "${python_setup_pid}" || { cat "${python_setup_log}" >&2; return 1; }
  tail -n 1 "${python_setup_log}"
}

# Clippy lints the workspace's crates as they are compiled for the tests (clippy-driver is rustc
# with clippy's lints): one build instead of a test build and a second, clippy's own. Every cargo
# command below, the scripts' included, builds with it, so none rebuilds what another built.
RUSTC_WORKSPACE_WRAPPER=$(rustup which clippy-driver) || { echo "scripts/test.sh: clippy is missing (rustup component add clippy)" >&2; exit 1; }
export RUSTC_WORKSPACE_WRAPPER CLIPPY_ARGS="-D__CLIPPY_HACKERY__warnings__CLIPPY_HACKERY__"

stage "ONNX Runtime" scripts/fetch-onnxruntime.sh
start_python_setup
stage "rustfmt" cargo fmt --all --check
stage "rust workspace: build (clippy -D warnings) and test" cargo test -j2 --workspace --locked
stage "python environment (installed during the Rust stages)" wait_for_python_setup
stage "module rules, ruff" python_lint
stage "replicas behind nginx" scripts/proxy-test.sh
stage "hostile clients (short)" loadtest/attacks.sh
stage "exporter pytest" pytest "${pytest_tier[@]}" exporter/tests
stage "bench pytest" pytest bench/tests
stage "python client" scripts/python-client-test.sh
stage "viewer in chromium" scripts/viewer-test.sh
stage "container files" docker/lint.sh
