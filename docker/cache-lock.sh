# shellcheck shell=bash
# Sourced by the scripts that build into ~/.cache/roost: one build at a time per cache
# directory. Test workers and checkouts that start together each ask for the same
# outputs, and two builds would move or remove each other's partial files; the one that
# waited finds the outputs built. The lock is the directory's own file on descriptor 9;
# the kernel drops it when the script and its children end.
#
#   lock_cache_dir DIR LABEL   (LABEL: the script's prefix in its progress lines)
lock_cache_dir() {
  mkdir -p "$1"
  exec 9>"$1/.lock"
  if ! flock -n 9; then
    echo "$2: waiting for another build into $1 to finish ..." >&2
    flock 9
  fi
}
