#!/usr/bin/env bash
# Build the KinD node image from Debian packages and Roost's own Kubernetes builds, for
# machines where no registry serves kindest/node (podman provider). Prints the image name.
#
#   tests/e2e/kind/node-image/build.sh            build when missing, print the image name
#   tests/e2e/kind/node-image/build.sh --print    print the image name only
#
# What goes in:
#   - a Debian root (mmdebstrap, the host's apt sources): systemd, dbus, runc, iptables,
#     iproute2, conntrack, mount tools — what kubelet, containerd and kubeadm call;
#   - kubelet, kube-proxy, containerd, ctr, the shim and the CNI plugins from
#     localcluster/build-node.sh, the control-plane binaries from
#     localcluster/build-control-plane.sh, and kubeadm and kubectl built here from the same
#     Go module graph (so every Kubernetes binary is one version);
#   - files/: the entrypoint, the systemd units, containerd's config, the pod network
#     service (roost-podnet, standing in for kindnetd, which cannot be built here) and the
#     /kind/ files kind reads (version, manifests);
#   - every image `kubeadm config images list` names, built from those binaries as FROM-
#     scratch images under exactly those names and imported at build time into the image's
#     containerd store (/var/lib/containerd, copied into each node's /var volume), so no
#     node ever pulls. CoreDNS is built from its Go module at the tag kubeadm names
#     (cached under ~/.cache/roost/kind/coredns-<version>/). etcd's image holds the
#     control plane's etcd build, the patch release Kubernetes' own module graph pins,
#     under the tag kubeadm names (one patch release apart at most; both 3.6).
#
# Cached: the image is named localhost/roost-kind-node:<k8s version>-<key>, the key a
# digest of the versions and of this directory; its OCI archive is kept under
# ~/.cache/roost/kind/node-image/ so a podman storage reset costs a `podman load`, not a
# build. Cold and warm times go to build-times.tsv there (read by bench/kind.py).
set -euo pipefail

here=$(cd "$(dirname "$0")" && pwd)
repo=$(cd "$here/../../../.." && pwd)
suite=bookworm
cache_root=${ROOST_CACHE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/roost}
node_dir=$("$repo/localcluster/build-node.sh" --print)
cp_dir=$("$repo/localcluster/build-control-plane.sh" --print)
k8s_version=$(awk '$1=="k8s.io/kubernetes"{print $2}' "$repo/localcluster/gomod/kubernetes/go.mod")
key=$( { echo "$suite ${node_dir##*/} ${cp_dir%/bin}"; find "$here" -type f -print0 | sort -z | xargs -0 cat; } \
  | sha256sum | cut -c1-12)
image="localhost/roost-kind-node:$k8s_version-$key"
out="$cache_root/kind/node-image"
archive="$out/roost-kind-node-$k8s_version-$key.oci.tar"
times="$out/build-times.tsv"

if [[ "${1:-}" == "--print" ]]; then
  echo "$image"
  exit 0
fi
say() { echo "kind-node-image: $*" >&2; }
record() { printf '%s\t%s\t%s\n' "$1" "$2" "$(date -u +%Y-%m-%dT%H:%M:%SZ)" >>"$times"; }
mkdir -p "$out"
start=$(date +%s.%N)
since() { awk -v t0="$1" -v t1="$(date +%s.%N)" 'BEGIN { printf "%.3f\n", t1 - t0 }'; }
elapsed() { since "$start"; }

if podman image exists "$image" 2>/dev/null; then
  record warm "$(elapsed)"
  echo "$image"
  exit 0
fi
if [[ -s "$archive" ]]; then
  say "loading $image from $archive"
  podman load --quiet --input "$archive" >/dev/null
  record load "$(elapsed)"
  echo "$image"
  exit 0
fi

"$repo/docker/debian-packages.sh" mmdebstrap=mmdebstrap buildah=buildah
"$repo/localcluster/build-node.sh" >/dev/null
"$repo/localcluster/build-control-plane.sh" >/dev/null

work=$(mktemp -d "${TMPDIR:-/tmp}/roost-kind-node.XXXXXX")
ctrd_pid=""
containers=()  # buildah working containers, removed on exit
cleanup() {
  [[ -n "$ctrd_pid" ]] && kill "$ctrd_pid" 2>/dev/null && wait "$ctrd_pid" 2>/dev/null
  for c in "${containers[@]}"; do buildah rm "$c" >/dev/null 2>&1 || true; done
  rm -rf "$work"
}
trap cleanup EXIT
root="$work/rootfs"

# -- the Debian root ----------------------------------------------------------------------
packages=systemd,systemd-sysv,dbus,libseccomp2,runc,iptables,iproute2,conntrack,ethtool,socat,util-linux,mount,procps,kmod,ca-certificates,bash,findutils
# The Debian root is its own cache stage (keyed on the suite and the packages): a change
# to files/ or to the Kubernetes builds does not debootstrap again.
root_tar="$out/debian-root-$suite-$(echo "$packages" | sha256sum | cut -c1-12).tar"
if [[ -s "$root_tar" ]]; then
  say "reusing the Debian root $root_tar"
  mkdir -p "$root"
  tar -C "$root" -xf "$root_tar"
  record debian-root-cached "$(elapsed)"
else
  say "debootstrapping $suite"
  mmdebstrap --quiet --variant=minbase --mode=root --include="$packages" \
    --dpkgopt='path-exclude=/usr/share/doc/*' --dpkgopt='path-exclude=/usr/share/man/*' \
    --dpkgopt='path-exclude=/usr/share/locale/*' \
    "$suite" "$root"
  tar -C "$root" -cf "$root_tar.partial" .
  mv -f "$root_tar.partial" "$root_tar"
  find "$out" -name 'debian-root-*.tar' ! -path "$root_tar" -delete
  record debian-root "$(elapsed)"
fi
root_done=$(date +%s.%N)

# -- kubeadm and kubectl, from the control plane's module graph -------------------------
k8s_bin="$cache_root/kind/k8s-$k8s_version"
if [[ ! -x "$k8s_bin/kubeadm" || ! -x "$k8s_bin/kubectl" ]]; then
  say "building kubeadm and kubectl $k8s_version"
  mod=$(mktemp -d)
  cp "$repo/localcluster/gomod/kubernetes/go.mod" "$repo/localcluster/gomod/kubernetes/go.sum" "$mod/"
  cp "$repo"/localcluster/gomod/kubernetes/*.go "$mod/" 2>/dev/null || true
  minor=${k8s_version#v1.}; minor=${minor%%.*}
  v=k8s.io/component-base/version
  (cd "$mod" && CGO_ENABLED=0 GOTOOLCHAIN=local GOFLAGS=-mod=mod go build -trimpath \
    -ldflags "-s -w -X $v.gitVersion=$k8s_version -X $v.gitMajor=1 -X $v.gitMinor=$minor -X $v.gitTreeState=clean" \
    -o "$k8s_bin.partial/" k8s.io/kubernetes/cmd/kubeadm k8s.io/kubernetes/cmd/kubectl)
  rm -rf "$mod" "$k8s_bin"
  mv "$k8s_bin.partial" "$k8s_bin"
fi

install -m 0755 "$node_dir"/bin/{kubelet,containerd,ctr,containerd-shim-runc-v2} "$root/usr/local/bin/"
install -m 0755 "$k8s_bin"/{kubeadm,kubectl} "$root/usr/local/bin/"
mkdir -p "$root/opt/cni/bin" "$root/etc/cni/net.d"
install -m 0755 "$node_dir"/cni/* "$root/opt/cni/bin/"
cp -a "$here/files/." "$root/"
echo "$k8s_version" >"$root/kind/version"
# systemd sets a fresh machine id per container; no getty, no timers on a node.
: >"$root/etc/machine-id"
rm -f "$root/var/lib/dbus/machine-id"
chroot "$root" systemctl enable containerd.service kubelet.service roost-podnet.service >/dev/null 2>&1
chroot "$root" systemctl mask getty@tty1.service console-getty.service systemd-logind.service \
  apt-daily.timer apt-daily-upgrade.timer e2scrub_all.timer fstrim.timer >/dev/null 2>&1 || true

# -- the images kubeadm asks for, from the same binaries ------------------------------------
mkdir -p "$work/images"
scratch_image() {  # NAME ARCHIVE ENTRYPOINT FILE... : a FROM-scratch image of static binaries
  local name=$1 archive=$2 entry=$3 c
  shift 3
  c=$(buildah from scratch); containers+=("$c")
  buildah copy --quiet "$c" "$@" /usr/local/bin/ >/dev/null
  buildah config --entrypoint "[\"$entry\"]" --env PATH=/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin "$c"
  buildah commit --quiet "$c" "oci-archive:$archive:$name" >/dev/null
  buildah rm "$c" >/dev/null
}
images=$(chroot "$root" kubeadm config images list --kubernetes-version "$k8s_version" 2>/dev/null)
say "images: ${images//$'\n'/ }"
for name in $images; do
  base=${name##*/}; base=${base%%:*}
  a="$work/images/$base.oci.tar"
  case "$base" in
    kube-apiserver|kube-controller-manager|kube-scheduler)
      scratch_image "$name" "$a" "/usr/local/bin/$base" "$cp_dir/$base" ;;
    etcd)
      scratch_image "$name" "$a" /usr/local/bin/etcd "$cp_dir/etcd" ;;
    kube-proxy)
      # kube-proxy programs iptables: its image carries the node root's iptables and
      # conntrack (the same Debian build, so the same nft/legacy choice as the node).
      c=$(buildah from scratch); containers+=("$c")
      m=$(buildah mount "$c")
      # Debian's merged /usr: /lib, /lib64, /bin and /sbin are links into /usr, first.
      for l in lib lib64 sbin bin; do
        [[ -L "$root/$l" ]] && mkdir -p "$m/usr/$l" && cp -a "$root/$l" "$m/"
      done
      pkgs="libc6 libgcc-s1 iptables libxtables12 libip4tc2 libip6tc2 libnftnl11 libmnl0 libnetfilter-conntrack3 libnfnetlink0 conntrack"
      # shellcheck disable=SC2086
      (cd "$root" && { chroot "$root" dpkg -L $pkgs 2>/dev/null || true; } | sort -u | while read -r f; do
        if [[ -f "$root$f" || -L "$root$f" ]]; then echo ".$f"; fi; done | tar -cf - -T - ) | tar --keep-directory-symlink -xf - -C "$m"
      mkdir -p "$m/etc/alternatives" "$m/usr/local/bin"
      cp -a "$root"/etc/alternatives/{iptables,iptables-save,iptables-restore,ip6tables,ip6tables-save,ip6tables-restore} "$m/etc/alternatives/"
      for l in iptables iptables-save iptables-restore ip6tables ip6tables-save ip6tables-restore; do
        ln -sf "/etc/alternatives/$l" "$m/usr/sbin/$l"
      done
      install -m 0755 "$node_dir/bin/kube-proxy" "$m/usr/local/bin/"
      buildah unmount "$c" >/dev/null
      buildah config --entrypoint '["/usr/local/bin/kube-proxy"]' --env PATH=/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin "$c"
      buildah commit --quiet "$c" "oci-archive:$a:$name" >/dev/null
      buildah rm "$c" >/dev/null ;;
    pause)
      # Roost's pause image, under the name kubeadm and containerd expect.
      src=$(cat "$node_dir/images/roost-pause.name")
      c=$(buildah from "oci-archive:$node_dir/images/roost-pause.oci.tar"); containers+=("$c")
      buildah commit --quiet "$c" "oci-archive:$a:$name" >/dev/null
      buildah rm "$c" >/dev/null
      : "$src" ;;
    coredns)
      # CoreDNS at the tag kubeadm names, built from its module (cached per version).
      dns_version=${name##*:}
      dns_bin="$cache_root/kind/coredns-$dns_version"
      if [[ ! -x "$dns_bin/coredns" ]]; then
        say "building CoreDNS $dns_version"
        rm -rf "$dns_bin.partial"
        CGO_ENABLED=0 GOTOOLCHAIN=local GOFLAGS=-mod=mod GOBIN="$dns_bin.partial" \
          go install -trimpath -ldflags "-s -w" "github.com/coredns/coredns@$dns_version"
        rm -rf "$dns_bin"
        mv "$dns_bin.partial" "$dns_bin"
      fi
      c=$(buildah from scratch); containers+=("$c")
      buildah copy --quiet "$c" "$dns_bin/coredns" /coredns >/dev/null
      buildah config --entrypoint '["/coredns"]' --port 53/udp --port 53/tcp "$c"
      buildah commit --quiet "$c" "oci-archive:$a:$name" >/dev/null
      buildah rm "$c" >/dev/null ;;
    *) say "no recipe for $name"; exit 1 ;;
  esac
done
sed -i "s|@PAUSE_IMAGE@|$(echo "$images" | grep /pause:)|" "$root/etc/containerd/config.toml"
record images "$(elapsed)"

# Import into the root's containerd store with a containerd of our own (no CRI, its own
# socket and state), content only: each node unpacks with its snapshotter on first use.
state="$work/containerd-state"
mkdir -p "$state"
printf 'version = 3\nroot = "%s"\nstate = "%s"\ndisabled_plugins = ["io.containerd.grpc.v1.cri", "io.containerd.cri.v1.runtime", "io.containerd.cri.v1.images"]\n[grpc]\n  address = "%s"\n' \
  "$root/var/lib/containerd" "$state" "$state/sock" >"$work/containerd.toml"
"$node_dir/bin/containerd" --config "$work/containerd.toml" >"$work/containerd.log" 2>&1 &
ctrd_pid=$!
for _ in $(seq 100); do [[ -S "$state/sock" ]] && break; sleep 0.1; done
for a in "$work"/images/*.oci.tar; do
  "$node_dir/bin/ctr" --address "$state/sock" --namespace k8s.io images import --no-unpack --local "$a" >/dev/null
done
"$node_dir/bin/ctr" --address "$state/sock" --namespace k8s.io images ls -q >&2
kill "$ctrd_pid"; wait "$ctrd_pid" 2>/dev/null || true; ctrd_pid=""
rm -rf "$root/var/lib/containerd/tmpmounts" "$root"/var/lib/containerd/io.containerd.snapshotter.v1.*

# -- the node image ---------------------------------------------------------------------------
say "committing $image"
ctr_id=$(buildah from scratch); containers+=("$ctr_id")
m=$(buildah mount "$ctr_id")
tar -C "$root" -cf - . | tar -C "$m" -xf -
buildah unmount "$ctr_id" >/dev/null
buildah config --entrypoint '["/usr/local/bin/entrypoint", "/sbin/init"]' --cmd '' \
  --env container=podman --stop-signal SIGRTMIN+3 "$ctr_id"
buildah commit --quiet "$ctr_id" "$image" >/dev/null
buildah rm "$ctr_id" >/dev/null
podman save --quiet --format oci-archive -o "$archive.partial" "$image"
mv -f "$archive.partial" "$archive"
find "$out" -name 'roost-kind-node-*.oci.tar' ! -path "$archive" -delete
for old in $(podman images --format '{{.Repository}}:{{.Tag}}' "${image%%:*}"); do
  [[ $old == "$image" ]] || podman rmi "$old" >/dev/null 2>&1 || true
done
record cold "$(elapsed)"
record after-root "$(since "$root_done")"
say "built $image in $(elapsed) s"
echo "$image"
