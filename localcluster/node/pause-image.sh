#!/usr/bin/env bash
# Build the pod sandbox image of the harness's real nodes as an OCI archive:
#
#   localcluster/node/pause-image.sh ARCHIVE NAME     e.g. ... roost-pause.oci.tar localhost/roost-pause:1
#
# One static binary (pause.c, compiled with the C compiler) in a FROM-scratch image with
# a single uncompressed layer. The archive is written directly in the OCI image layout
# (blobs, index.json, oci-layout), which `ctr images import` reads, so no image builder is
# needed. The layer is reproducible (fixed owner and modification time).
set -euo pipefail

archive=${1:?usage: pause-image.sh ARCHIVE NAME}
name=${2:?usage: pause-image.sh ARCHIVE NAME}
here=$(cd "$(dirname "$0")" && pwd)
cc=${CC:-cc}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

mkdir -p "$work/rootfs" "$work/oci/blobs/sha256"
"$cc" -static -Os -Wall -Wextra -Werror -o "$work/rootfs/pause" "$here/pause.c"
"${STRIP:-strip}" "$work/rootfs/pause"
tar --owner=0 --group=0 --numeric-owner --mtime=@0 --sort=name -C "$work/rootfs" -cf "$work/layer.tar" pause

blob() {  # FILE MEDIATYPE: store FILE as a blob, print its descriptor
  local digest size
  digest=$(sha256sum "$1" | cut -d' ' -f1)
  size=$(stat -c %s "$1")
  cp "$1" "$work/oci/blobs/sha256/$digest"
  printf '{"mediaType":"%s","digest":"sha256:%s","size":%s}' "$2" "$digest" "$size"
}

layer=$(blob "$work/layer.tar" application/vnd.oci.image.layer.v1.tar)
diff_id=$(sha256sum "$work/layer.tar" | cut -d' ' -f1)
printf '{"architecture":"%s","os":"linux","config":{"Entrypoint":["/pause"],"User":"65535:65535"},"rootfs":{"type":"layers","diff_ids":["sha256:%s"]}}' \
  "$(go env GOARCH 2>/dev/null || echo amd64)" "$diff_id" >"$work/config.json"
config=$(blob "$work/config.json" application/vnd.oci.image.config.v1+json)
printf '{"schemaVersion":2,"mediaType":"application/vnd.oci.image.manifest.v1+json","config":%s,"layers":[%s]}' \
  "$config" "$layer" >"$work/manifest.json"
manifest=$(blob "$work/manifest.json" application/vnd.oci.image.manifest.v1+json)
# io.containerd.image.name is the full name ctr imports the image under.
printf '{"schemaVersion":2,"manifests":[%s]}' \
  "${manifest%\}},\"annotations\":{\"io.containerd.image.name\":\"$name\",\"org.opencontainers.image.ref.name\":\"${name##*:}\"}}" \
  >"$work/oci/index.json"
printf '{"imageLayoutVersion":"1.0.0"}' >"$work/oci/oci-layout"
mkdir -p "$(dirname "$archive")"
tar --owner=0 --group=0 --numeric-owner --mtime=@0 --sort=name -C "$work/oci" -cf "$archive.partial" .
mv -f "$archive.partial" "$archive"
