#!/usr/bin/env bash
# Prints the path of the pinned kind binary, building it first when it is missing.
#
# kind is a Go module, so it is built from the Go module proxy with the local Go
# toolchain (no binary download) into ~/.cache/roost/kind/<version>/kind; a kind
# already on PATH is used only when it is exactly the pinned version.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
# shellcheck source-path=SCRIPTDIR source=versions.env
source "$here/versions.env"

if command -v kind >/dev/null 2>&1 && kind version 2>/dev/null | grep -q "^kind ${KIND_VERSION} "; then
  command -v kind
  exit 0
fi
cache="${ROOST_CACHE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/roost}/kind/${KIND_VERSION}"
if [[ ! -x "$cache/kind" ]]; then
  if ! command -v go >/dev/null 2>&1; then
    echo "install-kind: kind ${KIND_VERSION} is not installed and there is no Go toolchain to build it" >&2
    exit 3
  fi
  echo "install-kind: building sigs.k8s.io/kind@${KIND_VERSION} into $cache" >&2
  mkdir -p "$cache"
  GOTOOLCHAIN=local CGO_ENABLED=0 GOFLAGS=-trimpath GOBIN="$cache" \
    go install "sigs.k8s.io/kind@${KIND_VERSION}" >&2
fi
echo "$cache/kind"
