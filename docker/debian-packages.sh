#!/usr/bin/env bash
# Install Debian packages that are missing, so a fresh Debian machine (CI) gets the tools
# the image build and the real-node harness need without a manual step.
#
#   docker/debian-packages.sh COMMAND=PACKAGE ...
#
# Each argument names a command (or, starting with /, a file) and the Debian package that
# provides it; the package is installed only when the command is not on PATH or the file
# does not exist (a warm run touches nothing). Installing
# needs root (or sudo without a password) and apt-get; without them the script names what
# is missing and exits 1, so callers can skip with that message.
set -euo pipefail

missing=()
for spec in "$@"; do
  cmd=${spec%%=*}
  pkg=${spec#*=}
  if [[ $cmd == /* ]]; then
    [[ -e $cmd ]] || missing+=("$pkg")
  else
    command -v "$cmd" >/dev/null 2>&1 || missing+=("$pkg")
  fi
done
[[ ${#missing[@]} -eq 0 ]] && exit 0

as_root=()
if [[ $(id -u) -ne 0 ]]; then
  if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    as_root=(sudo -n)
  else
    echo "missing Debian packages: ${missing[*]} (install them as root: apt-get install ${missing[*]})" >&2
    exit 1
  fi
fi
command -v apt-get >/dev/null 2>&1 || {
  echo "missing packages: ${missing[*]} (no apt-get on this machine to install them)" >&2
  exit 1
}
# One install at a time: `make test` builds the images in the background while other
# steps may install what they need, and apt-get refuses to run beside another apt-get.
exec 8>"${TMPDIR:-/tmp}/roost-debian-packages.lock"
flock 8
echo "installing Debian packages: ${missing[*]}" >&2
log=$(mktemp)
export DEBIAN_FRONTEND=noninteractive
apt=("${as_root[@]}" apt-get -o DPkg::Lock::Timeout=600)
if ! { "${apt[@]}" update && "${apt[@]}" install -y --no-install-recommends "${missing[@]}"; } >"$log" 2>&1; then
  tail -n 30 "$log" >&2
  echo "apt-get failed installing: ${missing[*]}" >&2
  rm -f "$log"
  exit 1
fi
rm -f "$log"
