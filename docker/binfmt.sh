#!/usr/bin/env bash
# Let this amd64 machine run arm64 (aarch64) programs: Debian's qemu-user-static as the
# kernel's binfmt_misc interpreter for aarch64 ELF files. The arm64 images' build steps
# (docker/build-images.sh) and the harness's arm64 node (localcluster/build-node.sh
# --arch arm64) need it.
#
#   docker/binfmt.sh          make sure it is set up; exit 0 when arm64 programs run
#   docker/binfmt.sh --check  only check; exit 1 with the reason on stderr
#
# Steps: install qemu-user-static when missing; mount binfmt_misc on
# /proc/sys/fs/binfmt_misc when it is not mounted; register the aarch64 entry from the
# package's own description (/usr/share/binfmts/qemu-aarch64: magic and mask) with the
# flags F (the kernel opens the interpreter once, at registration, so an arm64 program
# starts inside any mount namespace or chroot -- a container, buildah's RUN steps -- where
# /usr/libexec/qemu-binfmt does not exist) and P (argv[0] preserved, as the package's
# -binfmt-P wrapper expects). No systemd is needed (Debian registers the entry through
# systemd-binfmt or binfmt-support, neither of which runs in a container).
#
# Where the kernel refuses (no binfmt_misc, no permission to mount it or to register: an
# unprivileged container), it exits 1 saying so; the callers then skip what needs arm64.
set -euo pipefail

here=$(cd "$(dirname "$0")" && pwd)
mnt=/proc/sys/fs/binfmt_misc
entry=$mnt/qemu-aarch64
desc=/usr/share/binfmts/qemu-aarch64
# An aarch64 program to run as the proof: the arm64 dynamic loader (libc6:arm64 or the
# cross toolchain's copy) prints its version when run directly.
loaders=(/lib/ld-linux-aarch64.so.1 /usr/aarch64-linux-gnu/lib/ld-linux-aarch64.so.1)

fail() { echo "arm64 emulation: $*" >&2; exit 1; }

registered() { [[ -r $entry ]] && grep -q '^enabled' "$entry" && grep -q '^flags: .*F' "$entry"; }

check() {
  grep -qw binfmt_misc /proc/filesystems || fail "this kernel has no binfmt_misc"
  [[ -r $mnt/status ]] || fail "binfmt_misc is not mounted on $mnt"
  [[ "$(cat "$mnt/status")" == enabled ]] || fail "binfmt_misc is disabled ($mnt/status)"
  registered || fail "no aarch64 interpreter registered with the F flag ($entry)"
  local loader
  for loader in "${loaders[@]}"; do
    if [[ -x $loader ]]; then
      "$loader" --version >/dev/null 2>&1 || fail "$loader does not run under the registered interpreter"
      return 0
    fi
  done
}

if [[ "${1:-}" == --check ]]; then
  check
  exit 0
fi

"$here/debian-packages.sh" qemu-aarch64-static=qemu-user-static
grep -qw binfmt_misc /proc/filesystems || fail "this kernel has no binfmt_misc"
if [[ ! -r $mnt/status ]]; then
  mount -t binfmt_misc binfmt_misc "$mnt" 2>/dev/null \
    || fail "cannot mount binfmt_misc on $mnt (needs root outside a user namespace)"
fi
if ! registered; then
  [[ -e $entry ]] && { echo -1 >"$entry" || fail "cannot replace $entry"; }
  magic=$(sed -n 's/^magic //p' "$desc")
  mask=$(sed -n 's/^mask //p' "$desc")
  interpreter=$(sed -n 's/^interpreter //p' "$desc")
  [[ -n $magic && -n $mask && -x $interpreter ]] || fail "cannot read $desc"
  # The kernel parses the \xNN escapes itself.
  printf ':qemu-aarch64:M:0:%s:%s:%s:FP\n' "$magic" "$mask" "$interpreter" >"$mnt/register" \
    2>/dev/null || fail "the kernel refused to register the aarch64 interpreter"
fi
check
