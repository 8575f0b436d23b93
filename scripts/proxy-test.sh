#!/usr/bin/env bash
# Scenes across replicas, with the real pieces: Debian's nginx (installed with apt-get when it is
# missing) configured from docker/nginx/scnerf.conf.template (the file docker/compose.yaml uses)
# in front of two scnerf-server processes on loopback ports, serving the small parity bundle.
#   1. 20 named scenes (PUT /v1/scenes/{id}, a 5-view capture: tests/fixtures/datasets/blender)
#      and one unnamed (POST /v1/scenes: nginx names it) through nginx;
#   2. every scene rendered RENDERS times through nginx: each render answered by the replica that
#      took the upload (nginx's X-Scnerf-Replica header), and each replica's /metrics shows as
#      many scenes as it took, a cache hit for every render of them and 0 misses;
#   3. one replica killed: renders of its scenes answer 404 scene_not_found with the hint
#      `reupload` (nginx falls over to the other replica); the other replica's scenes still
#      render; a re-upload under the same id makes the scene render again.
# Exits non-zero on failure, and when nginx is missing and cannot be installed (no root, no
# apt-get): CI must not pass without the replicas tested. SCNERF_ALLOW_SKIP=1 is the local opt-out:
# then a missing nginx prints "proxy-test: SKIPPED ..." and exits 0.
#
#   OUT=DIR        nginx configuration and logs, server logs (default target/proxy-test)
#   BUNDLE=DIR     the bundle served (default: the parity fixtures' small bundle)
#   RENDERS=N      renders per scene (default 3)
#   PROFILE=release  build and run the release server (default debug)
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "${repo}"
OUT=${OUT:-${repo}/target/proxy-test}
BUNDLE=${BUNDLE:-${repo}/tests/fixtures/parity/bundle}
RENDERS=${RENDERS:-3}
PROFILE=${PROFILE:-debug}
CAPTURE=${repo}/tests/fixtures/datasets/blender
SCENES=20
started=${SECONDS}

say() { echo "proxy-test: $*"; }
fail() {
  echo "proxy-test: FAILED: $*" >&2
  exit 1
}

why_missing="needs root and apt-get"
if ! command -v nginx > /dev/null && [[ ! -x /usr/sbin/nginx ]]; then
  if [[ $(id -u) == 0 ]] && command -v apt-get > /dev/null; then
    say "installing Debian's nginx"
    apt_log=$(mktemp)
    apt-get update -qq > "${apt_log}" 2>&1 || true
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends nginx-light >> "${apt_log}" 2>&1 \
      || DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends nginx >> "${apt_log}" 2>&1 \
      || true
    # apt's own words (a held dpkg lock, an unreachable mirror) say why better than a guess.
    why_missing="apt-get: $({ grep -E '^(E|W):' "${apt_log}" || true; } | tail -n 2 | tr '\n' ' ')"
    rm -f "${apt_log}"
  fi
fi
NGINX=$(command -v nginx || echo /usr/sbin/nginx)
if [[ ! -x ${NGINX} ]]; then
  if [[ ${SCNERF_ALLOW_SKIP:-0} == 1 ]]; then
    say "SKIPPED: nginx is not installed and cannot be installed here (SCNERF_ALLOW_SKIP=1)"
    exit 0
  fi
  fail "nginx is not installed and cannot be installed here (${why_missing}); SCNERF_ALLOW_SKIP=1 skips"
fi

scripts/fetch-onnxruntime.sh > /dev/null
flags=(-j2 -p scnerf-server -p scnerf-client --bins)
[[ ${PROFILE} == release ]] && flags+=(--release)
cargo build -q "${flags[@]}"
bin=${repo}/target/${PROFILE}

rm -rf "${OUT}"
mkdir -p "${OUT}/nginx" "${OUT}/responses"
pids=()
cleanup() {
  if [[ -f ${OUT}/nginx/nginx.pid ]]; then
    kill -QUIT "$(cat "${OUT}/nginx/nginx.pid")" 2> /dev/null || true
  fi
  for pid in "${pids[@]}"; do
    kill -TERM "${pid}" 2> /dev/null || true
  done
  wait 2> /dev/null || true
}
trap cleanup EXIT

# --- two replicas ---------------------------------------------------------------------------
replicas=()
for i in 1 2; do
  SCNERF_MAX_REQUESTS_PER_CLIENT=0 SCNERF_MAX_CONNECTIONS_PER_CLIENT=0 "${bin}/scnerf-server" --bundle "${BUNDLE}" --addr 127.0.0.1:0 \
    > "${OUT}/server-${i}.stdout" 2> "${OUT}/server-${i}.log" &
  pids+=($!)
done
for i in 1 2; do
  addr=
  for _ in $(seq 600); do
    addr=$(sed -n 's|^listening on http://||p' "${OUT}/server-${i}.stdout")
    [[ -n ${addr} ]] && break
    kill -0 "${pids[i - 1]}" 2> /dev/null || fail "replica ${i} exited: $(tail -3 "${OUT}/server-${i}.log")"
    sleep 0.1
  done
  [[ -n ${addr} ]] || fail "replica ${i} did not listen"
  replicas+=("${addr}")
done
for addr in "${replicas[@]}"; do
  for _ in $(seq 1200); do
    curl -fsS "http://${addr}/readyz" > /dev/null 2>&1 && break
    sleep 0.25
  done
  curl -fsS "http://${addr}/readyz" > /dev/null || fail "replica ${addr} not ready"
done
say "replicas at ${replicas[*]}"

# --- nginx, from the compose file's template --------------------------------------------------
port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
sed -e "s|\${SCNERF_PROXY_LISTEN}|127.0.0.1:${port}|" -e "s|\${SCNERF_REPLICA_1}|${replicas[0]}|" \
  -e "s|\${SCNERF_REPLICA_2}|${replicas[1]}|" docker/nginx/scnerf.conf.template > "${OUT}/nginx/scnerf.conf"
# shellcheck disable=SC2016 # a literal ${SCNERF_ left over
if grep -qF '${SCNERF_' "${OUT}/nginx/scnerf.conf"; then fail "unsubstituted variable in ${OUT}/nginx/scnerf.conf"; fi
n=${OUT}/nginx
cat > "${n}/nginx.conf" << EOF
worker_processes 1;
pid ${n}/nginx.pid;
error_log ${n}/error.log warn;
events { worker_connections 256; }
http {
    access_log ${n}/access.log;
    client_body_temp_path ${n}/body;
    proxy_temp_path ${n}/proxy;
    fastcgi_temp_path ${n}/fastcgi;
    uwsgi_temp_path ${n}/uwsgi;
    scgi_temp_path ${n}/scgi;
    include ${n}/scnerf.conf;
}
EOF
chmod 755 "${OUT}" "${n}"
"${NGINX}" -t -q -c "${n}/nginx.conf" -p "${n}" 2> "${n}/check.log" || fail "nginx -t: $(cat "${n}/check.log")"
"${NGINX}" -c "${n}/nginx.conf" -p "${n}" 2>> "${n}/error.log"
proxy=127.0.0.1:${port}
for _ in $(seq 100); do
  curl -fsS "http://${proxy}/healthz" > /dev/null 2>&1 && break
  sleep 0.1
done
say "nginx $("${NGINX}" -v 2>&1 | sed 's|.*/||') at ${proxy}"

# --- the capture: the scene request and a render request, from the client's reader ----------
"${bin}/scnerf" info --json "${CAPTURE}" 2> /dev/null > "${OUT}/capture.json"
python3 - "${OUT}" << 'EOF'
import json, sys
out = sys.argv[1]
capture = json.load(open(f"{out}/capture.json"))
views = capture["views"]
scene = {"sources": [{"camera": v["camera"]} for v in views], "near": capture["near"],
         "far": capture["far"], "background": capture["background"]}
json.dump(scene, open(f"{out}/scene.json", "w"))
json.dump({"target": views[1]["camera"], "outputs": ["rgb"]}, open(f"{out}/render.json", "w"))
with open(f"{out}/images.txt", "w") as f:
    f.writelines(v["image"] + "\n" for v in views)
EOF
mapfile -t images < "${OUT}/images.txt"
parts=(-F "request=@${OUT}/scene.json;type=application/json")
for i in "${!images[@]}"; do
  parts+=(-F "source_${i}=@${images[i]}")
done

# request METHOD PATH [curl args...]: sets STATUS, REPLICA (who answered) and BODY (a file)
calls=0
request() {
  local method=$1 path=$2
  shift 2
  calls=$((calls + 1))
  BODY=${OUT}/responses/${calls}.body
  STATUS=$(curl -sS -X "${method}" -o "${BODY}" -D "${OUT}/responses/${calls}.head" -w '%{http_code}' "$@" \
    "http://${proxy}${path}")
  REPLICA=$(sed -n 's/^[Xx]-[Ss]cnerf-[Rr]eplica: *\([^[:space:]]*\).*/\1/p' "${OUT}/responses/${calls}.head")
}
render() {
  request POST "/v1/scenes/$1/render" -H 'content-type: application/json' -H 'accept: image/png' \
    --data-binary "@${OUT}/render.json"
}
metric() { # metric REPLICA NAME
  curl -fsS "http://$1/metrics" | sed -n "s/^$2 \([0-9.e+]*\)$/\1/p"
}

# --- 1. uploads ----------------------------------------------------------------------------------
t=${SECONDS}
declare -A home
names=()
for s in $(seq -w 1 ${SCENES}); do
  id=scene-${s}
  request PUT "/v1/scenes/${id}" "${parts[@]}"
  [[ ${STATUS} == 201 ]] || fail "PUT ${id}: ${STATUS} $(cat "${BODY}")"
  [[ -n ${REPLICA} ]] || fail "PUT ${id}: no X-Scnerf-Replica header"
  home[${id}]=${REPLICA}
  names+=("${id}")
done
request POST /v1/scenes "${parts[@]}"
[[ ${STATUS} == 201 ]] || fail "POST /v1/scenes: ${STATUS} $(cat "${BODY}")"
id=$(python3 -c 'import json, sys; print(json.load(open(sys.argv[1]))["scene_id"])' "${BODY}")
home[${id}]=${REPLICA}
names+=("${id}")
declare -A held
for addr in "${replicas[@]}"; do held[${addr}]=0; done
for id in "${names[@]}"; do held[${home[${id}]}]=$((held[${home[${id}]}] + 1)); done
say "uploaded ${#names[@]} scenes ($((SECONDS - t)) s): ${held[${replicas[0]}]} on ${replicas[0]}, ${held[${replicas[1]}]} on ${replicas[1]}"
for addr in "${replicas[@]}"; do
  ((held[${addr}] > 0)) || fail "no scene on ${addr}: the hash does not spread scenes"
done

# --- 2. renders reach the scene's replica ----------------------------------------------------------
t=${SECONDS}
for _ in $(seq "${RENDERS}"); do
  for id in "${names[@]}"; do
    render "${id}"
    [[ ${STATUS} == 200 ]] || fail "render ${id}: ${STATUS} $(cat "${BODY}")"
    [[ ${REPLICA} == "${home[${id}]}" ]] || fail "render ${id} reached ${REPLICA}, the scene is on ${home[${id}]}"
  done
done
say "$((RENDERS * ${#names[@]})) renders, each on its scene's replica ($((SECONDS - t)) s)"
for addr in "${replicas[@]}"; do
  entries=$(metric "${addr}" scnerf_scene_cache_entries)
  hits=$(metric "${addr}" scnerf_scene_cache_hits_total)
  misses=$(metric "${addr}" scnerf_scene_cache_misses_total)
  say "${addr} /metrics: scene_cache_entries ${entries}, hits ${hits}, misses ${misses}"
  [[ ${entries} == "${held[${addr}]}" ]] || fail "${addr} holds ${entries} scenes, took ${held[${addr}]}"
  [[ ${hits} == "$((RENDERS * held[${addr}]))" ]] || fail "${addr}: ${hits} hits for $((RENDERS * held[${addr}])) renders"
  [[ ${misses} == 0 ]] || fail "${addr}: ${misses} scene misses"
done

# --- 3. a replica gone ------------------------------------------------------------------------------
gone=${replicas[0]} alive=${replicas[1]}
kill -KILL "${pids[0]}"
wait "${pids[0]}" 2> /dev/null || true
say "killed the replica at ${gone}"
lost=0 kept=0
for id in "${names[@]}"; do
  render "${id}"
  if [[ ${home[${id}]} == "${gone}" ]]; then
    [[ ${STATUS} == 404 ]] || fail "render ${id} (its replica is gone): ${STATUS} $(cat "${BODY}")"
    python3 - "${BODY}" << 'EOF' || fail "render ${id}: not scene_not_found with hint reupload: $(cat "${BODY}")"
import json, sys
error = json.load(open(sys.argv[1]))["error"]
sys.exit(0 if (error["code"], error.get("hint")) == ("scene_not_found", "reupload") else 1)
EOF
    lost=$((lost + 1))
  else
    [[ ${STATUS} == 200 && ${REPLICA} == "${alive}" ]] || fail "render ${id} on the live replica: ${STATUS} ${REPLICA}"
    kept=$((kept + 1))
  fi
done
say "${lost} scenes of the killed replica: 404 scene_not_found, hint reupload; ${kept} of the other: still rendered"
for id in "${names[@]}"; do
  if [[ ${home[${id}]} == "${gone}" && ${id} == scene-* ]]; then
    request PUT "/v1/scenes/${id}" "${parts[@]}"
    [[ ${STATUS} == 201 && ${REPLICA} == *"${alive}"* ]] || fail "re-upload of ${id}: ${STATUS} on ${REPLICA}"
    render "${id}"
    [[ ${STATUS} == 200 ]] || fail "render ${id} after its re-upload: ${STATUS} $(cat "${BODY}")"
    say "re-uploaded ${id}: 201 on ${alive}, renders again"
    break
  fi
done
say "passed in $((SECONDS - started)) s (${calls} requests through nginx)"
