#!/usr/bin/env bash
# Build the real Kubernetes control-plane binaries (kube-apiserver, kube-controller-manager,
# kube-scheduler, etcd), kwok and kine from the wrapper Go modules in localcluster/gomod/,
# and cache them under ~/.cache/roost/control-plane/<versions>/bin.
#
# A warm run (all binaries present) returns at once. A cold run takes 15-30 minutes on
# two cores; progress is printed per binary. Nothing is written into the repository.
#
#   localcluster/build-control-plane.sh            build if missing, print the bin dir
#   localcluster/build-control-plane.sh NAME...    only those binaries (e.g. kine)
#   localcluster/build-control-plane.sh --print    print the bin dir only
#
# kine (the K3s datastore, for `--datastore kine`) is built only when named: the default
# control plane runs on etcd. Its version is not part of the directory name (that would
# rebuild everything when it changes); kine.version beside it says which one was built.
set -euo pipefail

here=$(cd "$(dirname "$0")" && pwd)
k8s_mod="$here/gomod/kubernetes"
kwok_mod="$here/gomod/kwok"
kine_mod="$here/gomod/kine"

k8s_version=$(awk '$1=="k8s.io/kubernetes"{print $2}' "$k8s_mod/go.mod")
kwok_version=$(awk '$1=="sigs.k8s.io/kwok"{print $2}' "$kwok_mod/go.mod")
etcd_version=$(awk '$1=="go.etcd.io/etcd/server/v3"{print $2}' "$k8s_mod/go.mod")
kine_version=$(awk '$1=="github.com/k3s-io/kine"{print $2}' "$kine_mod/go.mod")
cache_root=${ROOST_CACHE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/roost}
bin_dir="$cache_root/control-plane/k8s-$k8s_version-etcd-$etcd_version-kwok-$kwok_version/bin"

# shellcheck source-path=SCRIPTDIR source=../docker/cache-lock.sh
. "$here/../docker/cache-lock.sh"
lock_cache_dir "$bin_dir" "control plane"

if [[ "${1:-}" == "--print" ]]; then
  echo "$bin_dir"
  exit 0
fi

# name | module dir | package
targets=(
  "etcd|$k8s_mod|go.etcd.io/etcd/server/v3"
  "kube-apiserver|$k8s_mod|k8s.io/kubernetes/cmd/kube-apiserver"
  "kube-controller-manager|$k8s_mod|k8s.io/kubernetes/cmd/kube-controller-manager"
  "kube-scheduler|$k8s_mod|k8s.io/kubernetes/cmd/kube-scheduler"
  "kwok|$kwok_mod|sigs.k8s.io/kwok/cmd/kwok"
  "kine|$kine_mod|github.com/k3s-io/kine"
)
default_names=(etcd kube-apiserver kube-controller-manager kube-scheduler kwok)
wanted=("$@")
[[ ${#wanted[@]} -gt 0 ]] || wanted=("${default_names[@]}")

up_to_date() {
  [[ -x "$bin_dir/$1" ]] || return 1
  [[ "$1" != kine ]] || [[ "$(cat "$bin_dir/kine.version" 2>/dev/null)" == "$kine_version" ]]
}

missing=()
for t in "${targets[@]}"; do
  name=${t%%|*}
  [[ " ${wanted[*]} " == *" $name "* ]] || continue
  up_to_date "$name" || missing+=("$t")
done
if [[ ${#missing[@]} -eq 0 ]]; then
  echo "control plane: cached in $bin_dir" >&2
  echo "$bin_dir"
  exit 0
fi

command -v go >/dev/null || { echo "error: Go is required to build the control plane (https://go.dev/doc/install)" >&2; exit 1; }
mkdir -p "$bin_dir"
minor=${k8s_version#v}; major=${minor%%.*}; minor=${minor#*.}; minor=${minor%%.*}
version_pkg=k8s.io/component-base/version
ldflags="-s -w -X $version_pkg.gitVersion=$k8s_version -X $version_pkg.gitMajor=$major -X $version_pkg.gitMinor=$minor -X $version_pkg.gitTreeState=clean"
export CGO_ENABLED=0 GOTOOLCHAIN=local GOFLAGS=-mod=mod

start=$(date +%s)
i=0
for t in "${missing[@]}"; do
  i=$((i + 1))
  IFS='|' read -r name dir pkg <<<"$t"
  echo "control plane: [$i/${#missing[@]}] building $name ($pkg) ..." >&2
  t0=$(date +%s)
  tmp="$bin_dir/.$name.partial"
  (cd "$dir" && go build -trimpath -ldflags "$ldflags" -o "$tmp" "$pkg")
  mv -f "$tmp" "$bin_dir/$name"
  [[ "$name" != kine ]] || echo "$kine_version" >"$bin_dir/kine.version"
  secs=$(( $(date +%s) - t0 ))
  echo "control plane: [$i/${#missing[@]}] $name built in $secs s" >&2
  # Build times per binary, read by bench/controlplane.py (controlplane.cold_build_s).
  printf '%s\t%s\t%s\n' "$name" "$secs" "$(date -u +%Y-%m-%dT%H:%M:%SZ)" >>"$bin_dir/../build-times.tsv"
done
echo "control plane: built ${#missing[@]} binaries in $(( $(date +%s) - start )) s into $bin_dir" >&2
echo "$bin_dir"
