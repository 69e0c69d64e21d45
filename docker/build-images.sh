#!/usr/bin/env bash
# `make images`: build Roost's operator and agent images with buildah (no container
# engine or daemon needed) for linux/amd64 and linux/arm64, and export each as an OCI
# archive holding one image index (one name, both platforms):
#
#   ~/.cache/roost/images/roost-operator.oci.tar   (image localhost/roost-operator:<version>)
#   ~/.cache/roost/images/roost-agent.oci.tar      (image localhost/roost-agent:<version>)
#
# ROOST_IMAGE_ARCHS (default "amd64 arm64") chooses the platforms; "amd64" alone builds
# what a machine without arm64 emulation can (an index with one platform).
#
# arm64, how: the Debian base is made for arm64 by mmdebstrap and the Dockerfile's RUN
# steps (image.py: pip install, ahead-of-time bytecode) run as arm64 programs under
# Debian's qemu-user-static (docker/binfmt.sh registers it with the kernel's binfmt_misc).
# Roost's compiled per-message path is cross-compiled, not emulated: mypyc's C comes out
# the same for any 64-bit Linux, so the host's mypyc writes it and Debian's
# gcc-aarch64-linux-gnu compiles it against the arm64 Python headers (libpython3.11-dev:
# arm64), as an arm64 wheel (cross_env). The dependencies' arm64 wheels are the index's
# own manylinux aarch64 builds of the exact versions the amd64 build resolved
# (arm64_dependencies); a dependency with no such wheel stops the build, named.
#
# The archives carry the full name (localhost/, as podman and buildah name local images):
# `ctr images import` keeps a name as the archive gives it, and the kubelet looks a name
# without a registry up under docker.io/library/, where an imported `roost-agent:<version>`
# is not found.
#
# Steps: install the Debian tools when missing (buildah, podman, runc, mmdebstrap; a C
# compiler and Python's headers for the compiled modules; for arm64 qemu-user-static, the
# cross compiler and the arm64 headers); build the base per architecture
# (ROOST_IMAGE_BASE, default `local`: Debian's python3 via docker/build-base.sh; any
# multi-platform image reference uses that image instead); `pip wheel` Roost (its
# per-message path compiled by mypyc: setup.py) and its dependencies on the host, per
# architecture; `buildah bud --platform` both targets of docker/Dockerfile per
# architecture; `buildah manifest` an index per target; push each, with its images, into
# an OCI archive.
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
#   docker/build-images.sh --mission DIR   build a mission's image from DIR's Dockerfile (below)
#   docker/build-images.sh --compiled-tree install the packages of Roost's compiled wheel
#                                          that hold compiled modules into
#                                          $cache/compiled/tree when stale; print that
#                                          directory (put it first on PYTHONPATH to run the
#                                          image's compiled agent from this checkout)
#
# A mission's image (--mission DIR, e.g. examples/missions/sync-paths): the same way, for
# the same platforms, on the same local base: DIR's package and its dependencies as wheels
# built or fetched here (the arm64 ones by arm64_dependencies), DIR's Dockerfile built per
# architecture, one index per image. Its name is DIR's package name and version
# (roost-<name>:<version>), given in the archive as docker.io/library/roost-<name>:<version>:
# that is what the kubelet looks an unqualified image name up as, so a Mission naming
# `roost-<name>:<version>` finds it imported. Cached as $cache/images/roost-<name>.oci.tar,
# keyed on DIR's sources, its Dockerfile, this script and the base.
here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/.." && pwd)
# The package folders the wheel is built from (pyproject's packages.find); the image
# cache key hashes the same list, so a new package cannot be left out of one of them.
packages=(api kube operator agent mavlink sim cli localcluster)
host_arch=$(dpkg --print-architecture 2>/dev/null || echo amd64)
read -r -a archs <<<"${ROOST_IMAGE_ARCHS:-amd64 arm64}"
# Without ROOST_IMAGE_ARCHS, a machine where arm64 programs cannot run (docker/binfmt.sh
# says why) builds its own platform only, saying so; the tests that need arm64 skip.
if [[ -z "${ROOST_IMAGE_ARCHS:-}" && ( "${1:-}" != --* || "${1:-}" == --mission ) ]] \
    && ! "$here/binfmt.sh" 2>"${TMPDIR:-/tmp}/roost-binfmt.$$"; then
  echo "images: building $host_arch only: $(cat "${TMPDIR:-/tmp}/roost-binfmt.$$")" >&2
  archs=("$host_arch")
fi
rm -f "${TMPDIR:-/tmp}/roost-binfmt.$$"
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

# What a cross-compiling `pip wheel` of Roost needs for arm64 (setup.py's extensions built
# by setuptools): the cross compiler, the arm64 Python headers first on the include path
# (Debian's /usr/include/python3.11 picks the arm64 pyconfig.h by the compiler's own
# target), the arm64 platform tag (linux_aarch64) and extension suffix. Printed as
# NAME=VALUE lines for `env`.
cross_env() {
  local arch=$1 triplet
  case "$arch" in
    arm64) triplet=aarch64-linux-gnu ;;
    *) echo "images: no cross compiler known for $arch" >&2; exit 1 ;;
  esac
  if ! dpkg --print-foreign-architectures | grep -qx "$arch"; then
    if [[ $(id -u) -ne 0 ]]; then
      echo "images: Debian's $arch packages are not enabled (as root: dpkg --add-architecture $arch)" >&2
      exit 1
    fi
    dpkg --add-architecture "$arch"
  fi
  "$here/debian-packages.sh" "$triplet-gcc=gcc-$triplet" \
    "/usr/include/$triplet/python3.11/pyconfig.h=libpython3.11-dev:$arch"
  printf '%s\n' "CC=$triplet-gcc" "LDSHARED=$triplet-gcc -shared" \
    "CPPFLAGS=-I/usr/include/python3.11" "_PYTHON_HOST_PLATFORM=linux-${triplet%%-*}" \
    "SETUPTOOLS_EXT_SUFFIX=.cpython-311-$triplet.so"
}

# Roost's own wheel for $3 (default: this machine's architecture) into $1 (pip's output
# into the log $2), its per-message path compiled by mypyc (setup.py). Without build isolation: mypyc type-checks the modules it compiles
# against Roost's other packages and their dependencies, installed where $python runs
# (the dev environment). From a copy of the packaged sources: an in-tree build would leave
# build/ and *.egg-info in the checkout, and a stale build/lib can carry deleted modules.
roost_wheel() {
  local dest=$1 log=$2 arch=${3:-$host_arch} src include cross=()
  if ! "$python" -c 'import mypyc' 2>/dev/null; then
    echo "images: $python has no mypyc (mypy) to compile Roost's per-message path; run make setup or set PYTHON" >&2
    exit 1
  fi
  include=$("$python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
  "$here/debian-packages.sh" cc=gcc "$include/Python.h=python3-dev"
  if [[ "$arch" != "$host_arch" ]]; then
    mapfile -t cross < <(cross_env "$arch")
    [[ ${#cross[@]} -gt 0 ]] || exit 1
  fi
  src=$(mktemp -d)
  (cd "$repo" && cp -r pyproject.toml setup.py "${packages[@]}" "$src/")
  # The wheel's long description only: a line of its own, so that the README's benchmark
  # table (rewritten by every `make bench`) is not part of what the images are made of.
  echo "Roost: a Kubernetes operator and node agent for drone fleets." >"$src/README.md"
  find "$src" \( -name __pycache__ -o -name '*.egg-info' \) -prune -exec rm -rf {} +
  echo "images: building Roost's $arch wheel, compiling its per-message path (mypyc) ..." >&2
  if ! env "${cross[@]}" ROOST_COMPILE=1 "$python" -m pip wheel --no-deps --no-build-isolation \
      --wheel-dir "$dest" "$src" >"$log" 2>&1; then
    tail -n 30 "$log" >&2
    echo "images: building Roost's wheel failed; its log is $log" >&2
    rm -rf "$src"
    exit 1
  fi
  rm -rf "$src"
}

# The build context for $2 (default: this machine's architecture): Roost and its
# dependencies as wheels (plus pip's own, which the Dockerfile runs pip from) and
# image.py. Wheels are built here, on the host, so the image build needs no compiler or
# package index. Another architecture's context takes the pure wheels of this machine's
# context $3 (written first) and the index's wheels for the rest.
write_context() {
  local ctx=$1 arch=${2:-$host_arch} native=${3:-} log
  check_python
  rm -rf "$ctx"
  mkdir -p "$ctx/wheels/roost" "$ctx/wheels/dependencies"
  cp "$here/image.py" "$ctx/"
  log="$(dirname "$ctx")/pip-wheel-$arch.log"
  roost_wheel "$ctx/wheels/roost" "$log" "$arch"
  if [[ "$arch" != "$host_arch" ]]; then
    arm64_dependencies "$native/wheels/dependencies" "$ctx/wheels/dependencies" "$arch" "$log"
    return
  fi
  echo "images: collecting the wheels of Roost's dependencies (pip wheel) ..." >&2
  if ! { "$python" -m pip wheel --wheel-dir "$ctx/wheels/dependencies" "$ctx"/wheels/roost/roost-*.whl \
         && "$python" -m pip download --no-deps --dest "$ctx/wheels/dependencies" pip; } >>"$log" 2>&1; then
    tail -n 30 "$log" >&2
    echo "images: pip wheel failed; its log is $log" >&2
    exit 1
  fi
  rm -f "$ctx"/wheels/dependencies/roost-*.whl
}

# The dependencies for $3 from the native context's wheels $1 into $2: pure ones
# (py3-none-any) are the same files; for each one with compiled parts, the same version's
# manylinux wheel for the architecture (glibc 2.17 to bookworm's 2.36), binary only.
arm64_dependencies() {
  local from=$1 dest=$2 arch=$3 log=$4 wheel name version machine platforms=() specs=()
  case "$arch" in
    arm64) machine=aarch64 ;;
    *) echo "images: no wheel platform known for $arch" >&2; exit 1 ;;
  esac
  for minor in $(seq 17 36); do platforms+=(--platform "manylinux_2_${minor}_$machine"); done
  platforms+=(--platform "manylinux2014_$machine")
  for wheel in "$from"/*.whl; do
    name=$(basename "$wheel")
    case "$name" in
      roost-*) ;;
      *-none-any.whl) cp "$wheel" "$dest/" ;;
      *) version=${name#*-}; specs+=("${name%%-*}==${version%%-*}") ;;
    esac
  done
  echo "images: downloading the $arch wheels of ${#specs[@]} compiled dependencies ..." >&2
  if ! "$python" -m pip download --no-deps --only-binary=:all: --dest "$dest" \
      --implementation cp --python-version 3.11 --abi cp311 "${platforms[@]}" \
      "${specs[@]}" >>"$log" 2>&1; then
    tail -n 30 "$log" >&2
    echo "images: no $arch wheel for a dependency (above); its log is $log" >&2
    exit 1
  fi
}

# What the images are made of: the packaged sources, the packaging and the image files.
sources_key() {
  cd "$repo" || exit 1
  {
    find "${packages[@]}" -type f \( -name '*.py' -o -name '*.pyi' -o -name '*.c' -o -name py.typed \) \
      ! -path '*/__pycache__/*' -print0 | sort -z | xargs -0 sha256sum
    sha256sum pyproject.toml setup.py docker/*
    echo "base=$base_ref archs=${archs[*]}"
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

# The base image for $1 (an architecture): the local Debian one (built when missing) or
# ROOST_IMAGE_BASE.
base_image() {
  if [[ "$base_ref" == local ]]; then
    "$here/build-base.sh" "$storage" "$1"
  else
    echo "$base_ref"
  fi
}

# One image index $1 of the images $2-<arch> (one per architecture built), pushed with
# its images into the OCI archive $3, under the name $1.
push_index() {
  local name=$1 per_arch=$2 archive=$3 arch
  buildah_ manifest rm "$name" >/dev/null 2>&1 || buildah_ rmi "$name" >/dev/null 2>&1 || true
  buildah_ manifest create "$name" >/dev/null
  for arch in "${archs[@]}"; do
    buildah_ manifest add "$name" "containers-storage:localhost/$per_arch-$arch" >/dev/null
  done
  rm -f "$archive"
  buildah_ manifest push --quiet --all --format oci "$name" "oci-archive:$archive.partial:$name" >/dev/null
  mv -f "$archive.partial" "$archive"
}

# The tools, the platforms' emulation and the image store, before any build.
prepare_build() {
  "$here/debian-packages.sh" buildah=buildah podman=podman runc=runc mmdebstrap=mmdebstrap
  local arch
  for arch in "${archs[@]}"; do
    if [[ "$arch" != "$host_arch" ]] && ! "$here/binfmt.sh" --check; then
      echo "images: $arch programs cannot run here (above: why); ROOST_IMAGE_ARCHS=$host_arch builds $host_arch only" >&2
      exit 1
    fi
  done
  mkdir -p "$out"
  # shellcheck source-path=SCRIPTDIR source=buildah.sh
  source "$here/buildah.sh"
}

# A mission's image from directory $1 (see the header): prints the archives' directory.
mission_image() {
  local dir name version image archive key ctx arch base log wheels src
  dir=$(cd "${1:?--mission needs a directory}" && pwd) || exit 1
  name=$(sed -nE 's/^name = "([^"]+)"$/\1/p' "$dir/pyproject.toml" | head -n 1)
  version=$(sed -nE 's/^version = "([^"]+)"$/\1/p' "$dir/pyproject.toml" | head -n 1)
  [[ -n "$name" && -n "$version" ]] || { echo "images: no name and version in $dir/pyproject.toml" >&2; exit 1; }
  image="roost-$name:$version"
  archive="$out/roost-$name.oci.tar"
  key=$(cd "$dir" && {
    # not the tools' caches: running the mission's tests leaves a .pytest_cache in DIR
    find . -type f ! -path '*/__pycache__/*' ! -path './.*' ! -path './tests/*' ! -name '*.md' -print0 \
      | sort -z | xargs -0 sha256sum
    # by name, not path: the key of one checkout is the key of any other (a clone's path
    # is not what the image is made of)
    (cd "$here" && sha256sum build-images.sh build-base.sh base.Dockerfile)
    echo "base=$base_ref archs=${archs[*]}"
  } | sha256sum | cut -c1-16)
  if [[ -s "$out/roost-$name.key" && "$(cat "$out/roost-$name.key")" == "$key" && -s "$archive" ]]; then
    echo "images: cached in $out ($image)" >&2
    echo "$out"
    return
  fi
  check_python
  prepare_build
  local start
  start=$(date +%s)
  ctx="$out/context-$name"
  rm -rf "$ctx"
  mkdir -p "$ctx"
  cp -r "$dir/trajectories" "$ctx/" 2>/dev/null || true
  log="$out/pip-wheel-$name.log"
  echo "images: the wheels of $name and its dependencies (pip wheel) ..." >&2
  # From a copy: an in-tree build would leave build/ and *.egg-info in DIR.
  src=$(mktemp -d)
  cp -r "$dir/." "$src/"
  if ! { "$python" -m pip wheel --wheel-dir "$ctx/wheels-$host_arch" "$src" \
         && "$python" -m pip download --no-deps --dest "$ctx/pip" pip; } >"$log" 2>&1; then
    tail -n 30 "$log" >&2
    echo "images: pip wheel failed; its log is $log" >&2
    rm -rf "$src"
    exit 1
  fi
  rm -rf "$src"
  mv "$ctx"/pip/pip-*.whl "$ctx/pip.whl"
  rmdir "$ctx/pip"
  for arch in "${archs[@]}"; do
    wheels="$ctx/wheels-$arch"
    if [[ "$arch" != "$host_arch" ]]; then
      mkdir -p "$wheels"
      arm64_dependencies "$ctx/wheels-$host_arch" "$wheels" "$arch" "$log"
    fi
    base=$(base_image "$arch") || exit 1
    rm -rf "$ctx/wheels"
    cp -r "$wheels" "$ctx/wheels"
    echo "images: building $image from $base (buildah, linux/$arch) ..." >&2
    if ! buildah_ bud --layers --platform "linux/$arch" --build-arg "BASE=$base" \
        -f "$dir/Dockerfile" -t "$image-$arch" "$ctx" >"$out/build-$name-$arch.log" 2>&1; then
      tail -n 30 "$out/build-$name-$arch.log" >&2
      echo "images: building $image failed; its log is $out/build-$name-$arch.log" >&2
      exit 1
    fi
  done
  push_index "docker.io/library/$image" "$image" "$archive"
  buildah_ rmi --prune >/dev/null 2>&1 || true
  rm -rf "$ctx"
  echo "$key" >"$out/roost-$name.key"
  printf '%s\t%s\t%s\t%s\n' "$name" "$(( $(date +%s) - start ))" "$(date -u +%Y-%m-%dT%H:%M:%SZ)" \
    "${archs[*]}" >>"$out/build-times.tsv"
  echo "images: built $image (${archs[*]}) into $out" >&2
  echo "$out"
}

# One build at a time per cache: checkouts share its storage, contexts and archives.
# shellcheck source-path=SCRIPTDIR source=cache-lock.sh
. "$here/cache-lock.sh"
lock_cache() { lock_cache_dir "$out" images; }

case "${1:-}" in
  --print) echo "$out"; exit 0 ;;
  --mission) lock_cache; mission_image "${2:-}"; exit 0 ;;
  --context) write_context "${2:?--context needs a directory}"; exit 0 ;;
  --compiled-tree) lock_cache; compiled_tree; exit 0 ;;
esac

lock_cache
version=$(sed -nE 's/^version = "([^"]+)"$/\1/p' "$repo/pyproject.toml")
key=$(sources_key)
if [[ -s "$out/key" && "$(cat "$out/key")" == "$key" \
      && -s "$out/roost-operator.oci.tar" && -s "$out/roost-agent.oci.tar" ]]; then
  echo "images: cached in $out (roost-operator, roost-agent $version)" >&2
  echo "$out"
  exit 0
fi

prepare_build
start=$(date +%s)

# The native context first: the other architectures take its pure wheels.
native_ctx="$out/context-$host_arch"
write_context "$native_ctx"
for arch in "${archs[@]}"; do
  [[ "$arch" == "$host_arch" ]] || write_context "$out/context-$arch" "$arch" "$native_ctx"
done

# "cold" in the build record: a base's root filesystem had to be made too.
cold=warm
for arch in "${archs[@]}"; do
  compgen -G "$out/base/*/$arch/rootfs.tar" >/dev/null || cold=cold
  base=$(base_image "$arch") || exit 1
  # The build stage first, tagged: its steps (the dependencies' layer above all) are then
  # images with a name or a child, which the prune below keeps for the next build.
  for target in install operator agent; do
    image="roost-$target:$version-$arch"
    echo "images: building $image from $base (buildah, linux/$arch) ..." >&2
    log="$out/build-$target-$arch.log"
    if ! buildah_ bud --layers --platform "linux/$arch" --target "$target" \
        --build-arg "BASE=$base" -f "$here/Dockerfile" -t "$image" "$out/context-$arch" \
        >"$log" 2>&1; then
      tail -n 30 "$log" >&2
      echo "images: building $image failed; its log is $log" >&2
      exit 1
    fi
  done
done

# One image index per target, named without the architecture; pushed with its images.
for target in operator agent; do
  push_index "localhost/roost-$target:$version" "roost-$target:$version" "$out/roost-$target.oci.tar"
done
# Drop what earlier builds left behind: their images and the steps nothing refers to any
# more (the dependencies' steps stay while the tagged build stage is made from them).
buildah_ rmi --prune >/dev/null 2>&1 || true
rm -rf "$out"/context-*
echo "$key" >"$out/key"
secs=$(( $(date +%s) - start ))
printf 'images\t%s\t%s\t%s\t%s\n' "$secs" "$(date -u +%Y-%m-%dT%H:%M:%SZ)" "${archs[*]}" "$cold" \
  >>"$out/build-times.tsv"
echo "images: built roost-operator and roost-agent $version (${archs[*]}) in $secs s into $out" >&2
echo "$out"
