#!/bin/bash
# Container HEALTHCHECK: GET /healthz (or the path given as $1, e.g. /readyz) over bash's /dev/tcp
# (no curl in the slim image). Exit 0 when the server answers 200, 1 otherwise. Bash builtins only.
# The port (and host, unless it is a wildcard) comes from SCNERF_ADDR, as the server's does.
path=${1:-/healthz}
addr=${SCNERF_ADDR:-0.0.0.0:8080}
port=${addr##*:}
host=${addr%:*}
host=${host#[}
host=${host%]}
case ${host} in
  "" | 0.0.0.0 | "::") host=127.0.0.1 ;;
esac
exec 3<>"/dev/tcp/${host}/${port}" || exit 1
printf 'GET %s HTTP/1.0\r\nHost: %s\r\nConnection: close\r\n\r\n' "${path}" "${host}" >&3 || exit 1
IFS= read -r -t 4 status <&3 || exit 1
exec 3>&-
case ${status} in
  "HTTP/1."?" 200"*) exit 0 ;;
  *) echo "${path}: ${status:-no answer}" >&2; exit 1 ;;
esac
