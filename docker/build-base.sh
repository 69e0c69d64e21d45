#!/usr/bin/env bash
# Build the local Python base image for docker/Dockerfile from Debian's packages, without
# pulling anything from a container registry:
#
#   mmdebstrap --variant=essential --include=python3 bookworm rootfs.tar
#   FROM scratch + ADD rootfs.tar (docker/base.Dockerfile), stored with buildah
#
# Why this variant: minbase adds apt and its crypto libraries (about 25 MB) that an image
# never uses at run time (packages go in at build time, from wheels), and the merged-usr
# hook replaces the usrmerge package, which would pull in the whole of Perl (45 MB).
# Documentation, manual pages, locales and glibc's iconv modules (Python has its own
# codecs) are left out by dpkg path filters; copyright files stay. Then the essential packages an image needs neither to build (docker/Dockerfile
# runs only python3) nor to run -- logins and PAM, util-linux, tar, diffutils, debconf,
# Perl, bash, coreutils, findutils, grep, sed: about 50 MB -- are purged with dpkg, so its
# database still tells image scanners the truth. What remains: python3 and its
# libraries, dash as /bin/sh (for `kubectl exec`), and dpkg's database.
#
# Another architecture (arm64) is made the same way: mmdebstrap runs the packages'
# maintainer scripts as arm64 programs under qemu-user-static (docker/binfmt.sh).
#
# The root filesystem is cached under $cache/base/<key>/<arch>/rootfs.tar, keyed by this
# script, base.Dockerfile and the suite: a warm run only checks that the image exists.
#
#   docker/build-base.sh STORAGE_ROOT [ARCH]   prints the image name (roost-base:<key>-<arch>;
#                                              ARCH: a Debian architecture, default amd64)
set -euo pipefail

here=$(cd "$(dirname "$0")" && pwd)
# shellcheck disable=SC2034 # read by buildah.sh
storage=${1:?usage: build-base.sh BUILDAH_STORAGE_ROOT}
arch=${2:-$(dpkg --print-architecture)}
suite=${ROOST_BASE_SUITE:-bookworm}
cache_root=${ROOST_CACHE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/roost}
key=$(cat "$0" "$here/base.Dockerfile" <(echo "$suite") | sha256sum | cut -c1-12)
dir="$cache_root/images/base/$key/$arch"
image="roost-base:$key-$arch"
# shellcheck source-path=SCRIPTDIR source=buildah.sh
source "$here/buildah.sh"
if [[ "$arch" != "$(dpkg --print-architecture)" ]]; then
  # mmdebstrap checks with arch-test that the foreign architecture's programs run.
  "$here/debian-packages.sh" arch-test=arch-test
fi

# Three rounds, because PAM's removal scripts need debconf, debconf needs Perl, and the
# triggers that removing a shell fires need coreutils (and dpkg wants tar and diff).
purge_first=(login libpam-modules libpam-modules-bin libpam-runtime)
purge_then=(util-linux util-linux-extra bsdutils ncurses-bin debconf perl-base
  bash)
purge_last=(tar diffutils findutils grep sed coreutils)
# shellcheck disable=SC2016 # \$1 is the hook's argument (the root filesystem)
purge='chroot "$1" dpkg --purge --force-remove-essential --force-depends'

if ! buildah_ inspect --type image "$image" >/dev/null 2>&1; then
  if [[ ! -s "$dir/rootfs.tar" ]]; then
    mkdir -p "$dir"
    echo "images: building the Debian $suite $arch root filesystem with python3 (mmdebstrap, about a minute; more under emulation) ..." >&2
    log="$dir/mmdebstrap.log"
    if ! mmdebstrap --variant=essential --include=python3 --format=tar --architectures="$arch" \
        --hook-dir=/usr/share/mmdebstrap/hooks/merged-usr \
        --dpkgopt='path-exclude=/usr/share/doc/*' \
        --dpkgopt='path-include=/usr/share/doc/*/copyright' \
        --dpkgopt='path-exclude=/usr/share/man/*' \
        --dpkgopt='path-exclude=/usr/share/info/*' \
        --dpkgopt='path-exclude=/usr/share/locale/*' \
        --dpkgopt='path-exclude=/usr/lib/x86_64-linux-gnu/gconv/*' \
        --dpkgopt='path-exclude=/usr/lib/aarch64-linux-gnu/gconv/*' \
        --customize-hook="$purge ${purge_first[*]}" \
        --customize-hook="$purge ${purge_then[*]}" \
        --customize-hook="$purge ${purge_last[*]}" \
        "$suite" "$dir/rootfs.tar.partial" >"$log" 2>&1; then
      tail -n 20 "$log" >&2
      echo "images: mmdebstrap failed; its log is $log" >&2
      exit 1
    fi
    mv -f "$dir/rootfs.tar.partial" "$dir/rootfs.tar"
  fi
  ctx=$(mktemp -d)
  trap 'rm -rf "$ctx"' EXIT
  ln "$dir/rootfs.tar" "$ctx/rootfs.tar" 2>/dev/null || cp "$dir/rootfs.tar" "$ctx/rootfs.tar"
  buildah_ bud --quiet --layers=false --platform "linux/$arch" -f "$here/base.Dockerfile" \
    -t "$image" "$ctx" >/dev/null
  # Bases of earlier versions of this script are no longer used.
  for old in $(buildah_ images --format '{{.Name}}:{{.Tag}}' | grep '/roost-base:' | grep -v ":$key-"); do
    buildah_ rmi "$old" >/dev/null 2>&1 || true
  done
  find "$cache_root/images/base" -mindepth 1 -maxdepth 1 ! -name "$key" -exec rm -rf {} +
fi
echo "$image"
