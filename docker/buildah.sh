# Sourced by the image scripts: buildah and podman on Roost's own image store (never the
# machine's default one, which other users of the machine may share), with the settings
# this kind of host needs. Expects $storage (the store's root directory).
#   - runc, not crun: crun refuses hosts with a hybrid cgroup hierarchy;
#   - vfs storage: works inside containers and on any filesystem (overlay needs kernel
#     support that nested environments often lack);
#   - chroot isolation for RUN steps (no user namespaces or cgroup setup needed);
#   - podman: cgroupfs (no systemd), events in a file, and ulimits within the hard limits
#     (podman's defaults exceed them on some hosts).
# shellcheck shell=bash
runroot="${XDG_RUNTIME_DIR:-/tmp}/roost-images-$(id -u)"
store_args=(--root "${storage:?}" --runroot "$runroot" --storage-driver vfs)
buildah_() {
  BUILDAH_ISOLATION=chroot buildah "${store_args[@]}" "$@"
}
podman_() {
  podman "${store_args[@]}" --runtime runc --cgroup-manager cgroupfs --events-backend file "$@"
}
