#!/usr/bin/env bash
# `make images`: build Roost's operator and agent images with buildah (no container
# engine or daemon needed) and export them as OCI archives:
#
#   ~/.cache/roost/images/roost-operator.oci.tar   (image localhost/roost-operator:<version>)
#   ~/.cache/roost/images/roost-agent.oci.tar      (image localhost/roost-agent:<version>)
#
# The archives carry the full name (localhost/, as podman and buildah name local images):
# `ctr images import` keeps a name as the archive gives it, and the kubelet looks a name
# without a registry up under docker.io/library/, where an imported `roost-agent:<version>`
# is not found.
#
# Steps: install the Debian tools when missing (buildah, podman, runc, mmdebstrap; a C
# compiler and Python's headers for the compiled modules); build the base
# (ROOST_IMAGE_BASE, default `local`: Debian's python3 via docker/build-base.sh; any image
# reference uses that image instead); `pip wheel` Roost (its per-message path compiled by
# mypyc: setup.py) and its dependencies on the host; `buildah bud` both targets of
# docker/Dockerfile; `buildah push` each into an OCI archive.
#
# Cached: the archives are rebuilt only when Roost's sources, pyproject.toml, setup.py,
# the docker/ files or the base change (a key over them is stored beside the archives); a
# warm run only compares that key. The image store is $cache/images/storage, never the
# machine's.
#
#   docker/build-images.sh                 build when stale; print the archives' directory
#   docker/build-images.sh --print         print the archives' directory only
#   docker/build-images.sh --context DIR   only write the build context (wheels/, image.py)
#                                          into DIR, for `docker build` (make e2e-kind)
#   docker/build-images.sh --compiled-tree install the packages of Roost's compiled wheel
#                                          that hold compiled modules into
#                                          $cache/compiled/tree when stale; print that
#                                          directory (put it first on PYTHONPATH to run the
#                                          image's compiled agent from this checkout)
here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/.." && pwd)
# The package folders the wheel is built from (pyproject's packages.find); the image
# cache key hashes the same list, so a new package cannot be left out of one of them.
packages=(api kube operator agents cli localcluster)
cache_root=${ROOST_CACHE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/roost}
out="$cache_root/images"
storage="$out/storage"
base_ref=${ROOST_IMAGE_BASE:-local}
# The dev environment's Python (make setup) by default: compiling needs its mypy.
if [[ -z "${PYTHON:-}" && -x "$repo/.venv/bin/python" ]]; then
  python=$repo/.venv/bin/python
else
  python=${PYTHON:-python3}
fi

# Wheels with compiled parts are per Python minor version: the host's must be the base's
# (3.11: Debian bookworm's python3, and the Dockerfile's default base).
check_python() {
  local host_python
  host_python=$("$python" -c 'import sys; print("%d.%d" % sys.version_info[:2])')
  if [[ "$host_python" != 3.11 ]]; then
    echo "images: the image's Python is 3.11 but $python is $host_python; set PYTHON to a Python 3.11" >&2
    exit 1
  fi
}

# Roost's own wheel into $1 (pip's output into the log $2), its per-message path compiled
# by mypyc (setup.py). Without build isolation: mypyc type-checks the modules it compiles
# against Roost's other packages and their dependencies, installed where $python runs
# (the dev environment). From a copy of the packaged sources: an in-tree build would leave
# build/ and *.egg-info in the checkout, and a stale build/lib can carry deleted modules.
roost_wheel() {
  local dest=$1 log=$2 src include
  if ! "$python" -c 'import mypyc' 2>/dev/null; then
    echo "images: $python has no mypyc (mypy) to compile Roost's per-message path; run make setup or set PYTHON" >&2
    exit 1
  fi
  include=$("$python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
  "$here/debian-packages.sh" cc=gcc "$include/Python.h=python3-dev"
  src=$(mktemp -d)
  (cd "$repo" && cp -r pyproject.toml README.md setup.py "${packages[@]}" "$src/")
  find "$src" \( -name __pycache__ -o -name '*.egg-info' \) -prune -exec rm -rf {} +
  echo "images: building Roost's wheel, compiling its per-message path (mypyc) ..." >&2
  if ! ROOST_COMPILE=1 "$python" -m pip wheel --no-deps --no-build-isolation \
      --wheel-dir "$dest" "$src" >"$log" 2>&1; then
    tail -n 30 "$log" >&2
    echo "images: building Roost's wheel failed; its log is $log" >&2
    rm -rf "$src"
    exit 1
  fi
  rm -rf "$src"
}

# The build context: Roost and its dependencies as wheels (plus pip's own, which the
# Dockerfile runs pip from) and image.py. Wheels are built here, on the host, so the image
# build needs no compiler or package index.
write_context() {
  local ctx=$1 log
  check_python
  rm -rf "$ctx"
  mkdir -p "$ctx/wheels"
  cp "$here/image.py" "$ctx/"
  log="$(dirname "$ctx")/pip-wheel.log"
  roost_wheel "$ctx/wheels" "$log"
  echo "images: collecting the wheels of Roost's dependencies (pip wheel) ..." >&2
  if ! { "$python" -m pip wheel --wheel-dir "$ctx/wheels" "$ctx"/wheels/roost-*.whl \
         && "$python" -m pip download --no-deps --dest "$ctx/wheels" pip; } >>"$log" 2>&1; then
    tail -n 30 "$log" >&2
    echo "images: pip wheel failed; its log is $log" >&2
    exit 1
  fi
}

# What the images are made of: the packaged sources, the packaging and the image files.
sources_key() {
  cd "$repo" || exit 1
  {
    find "${packages[@]}" -type f \( -name '*.py' -o -name py.typed \) \
      ! -path '*/__pycache__/*' -print0 | sort -z | xargs -0 sha256sum
    sha256sum pyproject.toml README.md setup.py docker/*
    echo "base=$base_ref"
  } | sha256sum | cut -c1-16
}

# Roost's compiled wheel installed into a directory of its own (no dependencies: those
# of the dev environment serve), rebuilt when the sources change; its packages without
# a compiled module are left out.
compiled_tree() {
  local dir="$cache_root/compiled" key wheels
  key=$(sources_key)
  if [[ -s "$dir/key" && "$(cat "$dir/key")" == "$key" && -d "$dir/tree" ]]; then
    echo "$dir/tree"
    return
  fi
  check_python
  rm -rf "$dir"
  mkdir -p "$dir"
  wheels=$(mktemp -d)
  roost_wheel "$wheels" "$dir/pip-wheel.log"
  if ! "$python" -m pip install --no-deps --no-compile --target "$dir/tree" \
      "$wheels"/roost-*.whl >>"$dir/pip-wheel.log" 2>&1; then
    tail -n 30 "$dir/pip-wheel.log" >&2
    echo "images: installing Roost's compiled wheel failed; the log is $dir/pip-wheel.log" >&2
    exit 1
  fi
  rm -rf "$wheels"
  # Only the packages that hold compiled modules: the rest comes from the checkout, so
  # paths found from a module's file (the repository's root, say) stay the checkout's.
  local package
  for package in "$dir"/tree/*/; do
    if [[ -z $(find "$package" -name '*.so' -print -quit) ]]; then
      rm -rf "$package"
    fi
  done
  echo "$key" >"$dir/key"
  echo "$dir/tree"
}

case "${1:-}" in
  --print) echo "$out"; exit 0 ;;
  --context) write_context "${2:?--context needs a directory}"; exit 0 ;;
  --compiled-tree) compiled_tree; exit 0 ;;
esac

version=$(sed -nE 's/^version = "([^"]+)"$/\1/p' "$repo/pyproject.toml")
key=$(sources_key)
if [[ -s "$out/key" && "$(cat "$out/key")" == "$key" \
      && -s "$out/roost-operator.oci.tar" && -s "$out/roost-agent.oci.tar" ]]; then
  echo "images: cached in $out (roost-operator, roost-agent $version)" >&2
  echo "$out"
  exit 0
fi

"$here/debian-packages.sh" buildah=buildah podman=podman runc=runc mmdebstrap=mmdebstrap
mkdir -p "$out"
# shellcheck source-path=SCRIPTDIR source=buildah.sh
source "$here/buildah.sh"
start=$(date +%s)

if [[ "$base_ref" == local ]]; then
  base=$("$here/build-base.sh" "$storage")
else
  base=$base_ref
fi

ctx="$out/context"
write_context "$ctx"

for target in operator agent; do
  image="roost-$target:$version"
  echo "images: building $image from $base (buildah) ..." >&2
  log="$out/build-$target.log"
  if ! buildah_ bud --layers --target "$target" --build-arg "BASE=$base" \
      -f "$here/Dockerfile" -t "$image" "$ctx" >"$log" 2>&1; then
    tail -n 30 "$log" >&2
    echo "images: building $image failed; its log is $log" >&2
    exit 1
  fi
  rm -f "$out/roost-$target.oci.tar"
  buildah_ push --quiet "localhost/$image" "oci-archive:$out/roost-$target.oci.tar.partial:localhost/$image" >/dev/null
  mv -f "$out/roost-$target.oci.tar.partial" "$out/roost-$target.oci.tar"
done
# Drop what earlier builds left behind (their images and the intermediate stages).
buildah_ rmi --prune >/dev/null 2>&1 || true
rm -rf "$ctx"
echo "$key" >"$out/key"
secs=$(( $(date +%s) - start ))
printf 'images\t%s\t%s\n' "$secs" "$(date -u +%Y-%m-%dT%H:%M:%SZ)" >>"$out/build-times.tsv"
echo "images: built roost-operator and roost-agent $version in $secs s into $out" >&2
echo "$out"
