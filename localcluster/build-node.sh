#!/usr/bin/env bash
# Build what a real node of the local harness runs: kubelet and kube-proxy (from the same
# k8s.io/kubernetes module graph as the control plane), containerd with ctr and
# containerd-shim-runc-v2, the CNI plugins bridge, host-local, loopback and portmap, and the
# pod sandbox ("pause") image. Cached under ~/.cache/roost/node/<versions>/:
#
#   bin/        kubelet kube-proxy containerd ctr containerd-shim-runc-v2
#   cni/        bridge host-local loopback portmap
#   images/     roost-pause.oci.tar (image localhost/roost-pause:<digest of its sources>)
#               and roost-pause.name (that image name)
#
# The node also needs Debian's runc, iptables, conntrack, iproute2 and util-linux, and gcc
# for the pause binary (installed when missing, as root, by docker/debian-packages.sh).
# A warm run (everything present) returns at once; a cold one took 206 s on two cores
# (kubelet 110 s, containerd 73 s) with the control plane's Go modules already downloaded,
# timed per program in build-times.tsv.
#
# An arm64 node (--arch arm64: a Raspberry Pi's programs, run here under qemu-user-static
# through binfmt_misc, docker/binfmt.sh) is the same set cross-compiled by Go
# (GOARCH=arm64; everything is built without cgo) and the pause binary cross-compiled by
# gcc-aarch64-linux-gnu. Its directory is the amd64 one's name with "-arm64". runc stays
# the host's: Debian's arm64 runc does not start a container under qemu-user (runc
# re-executes itself through /proc/self/exe and clones with namespace and CLONE_PARENT
# flags, which qemu-user's process emulation refuses: "unable to start init: fork/exec
# /proc/self/exe: no such file or directory"), so the containers -- arm64 programs,
# the images' arm64 builds -- are started by the host's runc and run under qemu through
# binfmt_misc, as any arm64 program here. Cold: the Go programs cost what the amd64 ones
# do (the Go build cache keeps the module downloads; compiled packages are per GOARCH).
#
#   localcluster/build-node.sh [--arch ARCH]          build what is missing, print the node directory
#   localcluster/build-node.sh [--arch ARCH] --print  print the node directory only
set -euo pipefail

host_arch=$(go env GOHOSTARCH 2>/dev/null || dpkg --print-architecture)
arch=$host_arch
if [[ "${1:-}" == "--arch" ]]; then
  arch=${2:?--arch needs an architecture (amd64, arm64)}
  shift 2
fi

here=$(cd "$(dirname "$0")" && pwd)
k8s_mod="$here/gomod/kubernetes"
containerd_mod="$here/gomod/containerd"
cni_mod="$here/gomod/cni-plugins"
# The pause image's tag: a digest of its sources, so a change rebuilds it.
pause_tag=$(cat "$here/node/pause.c" "$here/node/pause-image.sh" | sha256sum | cut -c1-12)

version_of() { awk -v m="$1" '$1==m{print $2} $1=="require" && $2==m{print $3}' "$2/go.mod"; }
k8s_version=$(version_of k8s.io/kubernetes "$k8s_mod")
containerd_version=$(version_of github.com/containerd/containerd/v2 "$containerd_mod")
cni_version=$(version_of github.com/containernetworking/plugins "$cni_mod")
cache_root=${ROOST_CACHE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/roost}
node_dir="$cache_root/node/k8s-$k8s_version-containerd-$containerd_version-cni-$cni_version"
[[ "$arch" == "$host_arch" ]] || node_dir="$node_dir-$arch"

# shellcheck source-path=SCRIPTDIR source=../docker/cache-lock.sh
. "$here/../docker/cache-lock.sh"
lock_cache_dir "$node_dir" node

if [[ "${1:-}" == "--print" ]]; then
  echo "$node_dir"
  exit 0
fi

# output path | module dir | package
k8s=k8s.io/kubernetes/cmd
ctrd=github.com/containerd/containerd/v2/cmd
cni=github.com/containernetworking/plugins/plugins
targets=(
  "bin/kubelet|$k8s_mod|$k8s/kubelet"
  "bin/kube-proxy|$k8s_mod|$k8s/kube-proxy"
  "bin/containerd|$containerd_mod|$ctrd/containerd"
  "bin/ctr|$containerd_mod|$ctrd/ctr"
  "bin/containerd-shim-runc-v2|$containerd_mod|$ctrd/containerd-shim-runc-v2"
  "cni/bridge|$cni_mod|$cni/main/bridge"
  "cni/host-local|$cni_mod|$cni/ipam/host-local"
  "cni/loopback|$cni_mod|$cni/main/loopback"
  "cni/portmap|$cni_mod|$cni/meta/portmap"
)
pause_archive="$node_dir/images/roost-pause.oci.tar"
pause_name="localhost/roost-pause:$pause_tag"

"$here/../docker/debian-packages.sh" runc=runc iptables=iptables conntrack=conntrack ip=iproute2 \
  nsenter=util-linux cc=gcc

cross=()
if [[ "$arch" != "$host_arch" ]]; then
  case "$arch" in
    arm64) triplet=aarch64-linux-gnu ;;
    *) echo "node: no cross toolchain known for $arch" >&2; exit 1 ;;
  esac
  "$here/../docker/binfmt.sh" || { echo "node: $arch programs cannot run here (above: why)" >&2; exit 1; }
  "$here/../docker/debian-packages.sh" "$triplet-gcc=gcc-$triplet"
  cross=(CC="$triplet-gcc" STRIP="$triplet-strip" GOARCH="$arch")
fi

missing=()
for t in "${targets[@]}"; do
  [[ -x "$node_dir/${t%%|*}" ]] || missing+=("$t")
done
pause_current() { [[ -s "$pause_archive" && "$(cat "$node_dir/images/roost-pause.name" 2>/dev/null)" == "$pause_name" ]]; }
if [[ ${#missing[@]} -eq 0 ]] && pause_current; then
  echo "node: cached in $node_dir" >&2
  echo "$node_dir"
  exit 0
fi

command -v go >/dev/null || { echo "error: Go is required to build the node binaries (https://go.dev/doc/install)" >&2; exit 1; }
mkdir -p "$node_dir/bin" "$node_dir/cni" "$node_dir/images"
minor=${k8s_version#v}; major=${minor%%.*}; minor=${minor#*.}; minor=${minor%%.*}
version_pkg=k8s.io/component-base/version
k8s_ldflags="-X $version_pkg.gitVersion=$k8s_version -X $version_pkg.gitMajor=$major -X $version_pkg.gitMinor=$minor -X $version_pkg.gitTreeState=clean"
ctrd_ldflags="-X github.com/containerd/containerd/v2/version.Version=$containerd_version"
export CGO_ENABLED=0 GOTOOLCHAIN=local GOFLAGS=-mod=mod

record() {  # name seconds: build times, read by bench/node.py
  printf '%s\t%s\t%s\n' "$1" "$2" "$(date -u +%Y-%m-%dT%H:%M:%SZ)" >>"$node_dir/build-times.tsv"
}

start=$(date +%s)
i=0
for t in "${missing[@]}"; do
  i=$((i + 1))
  IFS='|' read -r out dir pkg <<<"$t"
  name=${out#*/}
  case "$dir" in
    "$k8s_mod") ldflags="-s -w $k8s_ldflags" ;;
    "$containerd_mod") ldflags="-s -w $ctrd_ldflags" ;;
    *) ldflags="-s -w" ;;
  esac
  echo "node: [$i/${#missing[@]}] building $name ($pkg) ..." >&2
  t0=$(date +%s)
  tmp="$node_dir/$out.partial"
  (cd "$dir" && env "${cross[@]}" go build -trimpath -ldflags "$ldflags" -o "$tmp" "$pkg")
  mv -f "$tmp" "$node_dir/$out"
  secs=$(( $(date +%s) - t0 ))
  echo "node: [$i/${#missing[@]}] $name built in $secs s" >&2
  record "$name" "$secs"
done

if ! pause_current; then
  echo "node: building the pause image ($pause_name) ..." >&2
  t0=$(date +%s)
  env "${cross[@]}" "$here/node/pause-image.sh" "$pause_archive" "$pause_name"
  echo "$pause_name" >"$node_dir/images/roost-pause.name"
  record pause-image "$(( $(date +%s) - t0 ))"
fi
echo "node: ready in $(( $(date +%s) - start )) s: $node_dir" >&2
echo "$node_dir"
