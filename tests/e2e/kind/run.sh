#!/usr/bin/env bash
# `make e2e-kind`: Roost end to end on KinD, with real images and real PX4 SITL.
#
#   1. needs a container engine (docker info) and the pinned kind (built from its Go
#      module by install-kind.sh); without them it says why and exits 0 (skipped);
#   2. fake serial ports: one pseudo-terminal per vehicle worker under .kind/, held
#      open by a small process, mounted at /dev/ttyUSB0 by kind-config.yaml;
#   3. creates the cluster from kind-config.yaml (reuses a running one);
#   4. builds the operator and agent images (docker/Dockerfile) and loads them;
#   5. helm installs charts/roost with values-kind.yaml (privileged device path on);
#   6. applies the examples and the KinD fleet (tests/e2e/kind/fleet.yaml);
#   7. runs the KinD end-to-end tests (tests/e2e/kind/) against the cluster.
# The cluster is deleted at the end unless ROOST_KIND_KEEP=1.
set -euo pipefail

repo="$(cd "$(dirname "$0")/../../.." && pwd)"
cd "$repo"
here=tests/e2e/kind
# shellcheck source-path=SCRIPTDIR source=versions.env
source "$here/versions.env"
cluster=roost-e2e
namespace=roost-system
state=.kind
bin="$repo/.venv/bin"

say() { echo "e2e-kind: $*"; }
skip() {
  say "SKIPPED: $*"
  say "the KinD end-to-end run needs a container engine; everything else is covered by"
  say "\`make test\` on the control-plane harness."
  exit 0
}

# -- 1. prerequisites -----------------------------------------------------------------
command -v docker >/dev/null 2>&1 || skip "no docker CLI on PATH"
if ! engine_error="$(docker info 2>&1 >/dev/null)"; then
  skip "docker is installed but no container engine answers: $(echo "$engine_error" | grep -m1 -i -E 'error|cannot' || echo "docker info failed")"
fi
if ! kind="$("$here/install-kind.sh")"; then
  skip "kind ${KIND_VERSION} is not available and cannot be built here"
fi
for tool in kubectl helm pytest python; do
  [[ -x "$bin/$tool" ]] || { say "missing $bin/$tool: run \`make setup\`"; exit 1; }
done
kubeconfig="$repo/$state/kubeconfig"
kubectl() { "$bin/kubectl" --kubeconfig "$kubeconfig" "$@"; }
helm() { "$bin/helm" --kubeconfig "$kubeconfig" "$@"; }

# -- 2. fake serial ports -------------------------------------------------------------
holders=()
cleanup() {
  local status=$?
  for pid in "${holders[@]}"; do kill "$pid" 2>/dev/null || true; done
  if [[ "${ROOST_KIND_KEEP:-0}" != 1 ]]; then
    "$kind" delete cluster --name "$cluster" >/dev/null 2>&1 || true
  else
    say "cluster kept (ROOST_KIND_KEEP=1): KUBECONFIG=$kubeconfig"
  fi
  exit "$status"
}
trap cleanup EXIT

for i in 1 2 3; do
  mkdir -p "$state/vehicle-$i"
  link="$state/vehicle-$i/ttyUSB0"
  rm -f "$link"
  # Holds the master side open (the slave vanishes with it) and links the slave where
  # kind-config.yaml mounts it from; the agent runs as uid 65532, hence mode 0666.
  "$bin/python" -c '
import os, signal, sys
master, slave = os.openpty()
path = os.ttyname(slave)
os.chmod(path, 0o666)
os.symlink(path, sys.argv[1])
signal.sigwait({signal.SIGTERM, signal.SIGINT})
' "$link" &
  holders+=("$!")
done
for i in 1 2 3; do
  for _ in $(seq 50); do [[ -L "$state/vehicle-$i/ttyUSB0" ]] && break; sleep 0.1; done
  [[ -c "$state/vehicle-$i/ttyUSB0" ]] || { say "no pseudo-terminal for vehicle-$i"; exit 1; }
done

# -- 3. cluster -----------------------------------------------------------------------
if "$kind" get clusters 2>/dev/null | grep -qx "$cluster"; then
  say "reusing cluster $cluster"
  "$kind" export kubeconfig --name "$cluster" --kubeconfig "$kubeconfig"
else
  say "creating cluster $cluster (kind ${KIND_VERSION}, ${KIND_NODE_IMAGE%%@*})"
  "$kind" create cluster --name "$cluster" --config kind-config.yaml \
    --image "$KIND_NODE_IMAGE" --kubeconfig "$kubeconfig" --wait 180s
fi

# -- 4. images ------------------------------------------------------------------------
context="$state/image-context"
docker/build-images.sh --context "$context"
for target in operator agent; do
  say "building roost-$target:e2e"
  DOCKER_BUILDKIT=1 docker build -f docker/Dockerfile --target "$target" -t "roost-$target:e2e" "$context"
  "$kind" load docker-image "roost-$target:e2e" --name "$cluster"
done

# -- 5. chart -------------------------------------------------------------------------
helm upgrade --install roost charts/roost --namespace "$namespace" --create-namespace \
  --values charts/roost/values-kind.yaml --wait --timeout 5m

# -- 6. examples and the fleet --------------------------------------------------------
kubectl apply -f examples/
kubectl apply -f "$here/fleet.yaml"

# -- 7. end-to-end tests ----------------------------------------------------------------
say "running the KinD end-to-end tests"
ROOST_KIND_KUBECONFIG="$kubeconfig" ROOST_KIND_NAMESPACE="$namespace" \
  "$bin/pytest" -p no:cacheprovider -v "$here"
