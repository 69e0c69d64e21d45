#!/usr/bin/env bash
# `make e2e-kind`: Roost end to end on a four-node KinD cluster (kind-config.yaml).
#
# Two providers (ROOST_KIND_PROVIDER=docker|podman forces one; by default docker when a
# Docker engine answers, else podman):
#   docker  the standard kindest/node image (versions.env, pinned by digest, pulled from
#           its registry), Roost's images built with `docker build` (docker/Dockerfile);
#           the vehicles fly PX4 SITL images pulled on first use;
#   podman  no registry needed: the node image is built here from Debian packages and
#           Roost's cached Kubernetes builds (node-image/build.sh, cached on versions),
#           Roost's images are the OCI archives of docker/build-images.sh, and the
#           vehicles' autopilots are roost-sim processes in each worker's network
#           namespace (what the agent sees on real hardware is a flight controller on
#           its loopback or serial port, not a pod).
# Steps: leftovers of an earlier (killed) run are removed first (containers, volumes and
# the network, by kind's labels and Roost's names); fake serial ports; the cluster; the
# images; `helm install`; the tests in tests/e2e/kind/; everything is removed on exit
# (also on Ctrl-C or SIGTERM) unless ROOST_KIND_KEEP=1. Where it cannot run (no engine,
# no root for podman, no kind) it prints why and exits 0 (SKIPPED); every wait is bounded.
# ROOST_KIND_JUNIT=FILE: the tests' JUnit report (`make test` puts it beside the others).
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
kubeconfig="$repo/$state/kubeconfig"
holders_file="$state/holders.pid"
timings="$state/timings.tsv"

say() { echo "e2e-kind: $*"; }
skip() {
  say "SKIPPED: $*"
  say "the KinD end-to-end run needs Docker, or podman as root; everything else is covered"
  say "by \`make test\` on the control-plane harness."
  exit 0
}
now() { date +%s.%N; }
# Long steps run in a session of their own, waited for in the background, so that a
# SIGTERM or SIGINT to this script reaches the cleanup at once and stops the step's whole
# process tree (kind, podman, helm, pytest and their children) by its session id.
step_pid=""
step() {
  setsid "$@" 9>&- &
  step_pid=$!
  local status=0
  wait "$step_pid" || status=$?
  step_pid=""
  return "$status"
}
mark() { awk -v name="$1" -v t0="$2" -v t1="$(now)" 'BEGIN { printf "%s\t%.3f\n", name, t1 - t0 }' >>"$timings"; }

# -- 1. provider and prerequisites ------------------------------------------------------
docker_answers() { command -v docker >/dev/null 2>&1 && docker info >/dev/null 2>&1; }
provider=${ROOST_KIND_PROVIDER:-}
if [[ -z $provider ]]; then
  if docker_answers; then provider=docker; else provider=podman; fi
fi
case "$provider" in
  docker)
    command -v docker >/dev/null 2>&1 || skip "no docker CLI on PATH"
    docker_answers || skip "docker is installed but no container engine answers"
    engine=docker ;;
  podman)
    [[ $(id -u) -eq 0 ]] || skip "podman runs KinD nodes here only as root (rootless podman cannot give a node its cgroups)"
    # A fresh Debian machine (CI) gets podman from Debian's packages, as the image
    # build gets buildah; where that cannot be done, the run skips saying why.
    docker/debian-packages.sh podman=podman >/dev/null \
      || skip "no docker engine, and podman is not installed and could not be (above: why)"
    podman info >/dev/null 2>&1 || skip "podman is installed but \`podman info\` fails"
    engine=podman
    export KIND_EXPERIMENTAL_PROVIDER=podman
    # podman's defaults for a privileged container: ulimits above this host's hard
    # limits (runc then fails with "error setting rlimits"), systemd as cgroup manager
    # and journald for events, where neither may run. A configuration of our own:
    mkdir -p "$state"
    nofile=$(ulimit -Hn); [[ $nofile == unlimited || $nofile -gt 1048576 ]] && nofile=1048576
    nproc=$(ulimit -Hu); [[ $nproc == unlimited || $nproc -gt 30000 ]] && nproc=30000
    printf '[containers]\ndefault_ulimits = ["nofile=%s:%s", "nproc=%s:%s"]\n[engine]\ncgroup_manager = "cgroupfs"\nevents_logger = "file"\n' \
      "$nofile" "$nofile" "$nproc" "$nproc" >"$state/containers.conf"
    export CONTAINERS_CONF="$repo/$state/containers.conf"
    # A network of our own (kind's default is shared), so cleanup may remove it.
    export KIND_EXPERIMENTAL_PODMAN_NETWORK=$cluster ;;
  *) say "ROOST_KIND_PROVIDER must be docker or podman, not $provider"; exit 2 ;;
esac
if ! kind="$("$here/install-kind.sh")"; then
  skip "kind ${KIND_VERSION} is not available and cannot be built here"
fi
for tool in kubectl helm pytest python; do
  [[ -x "$bin/$tool" ]] || { say "missing $bin/$tool: run \`make setup\`"; exit 1; }
done
kubectl() { "$bin/kubectl" --kubeconfig "$kubeconfig" "$@"; }

# -- 2. leftovers and cleanup -------------------------------------------------------------
# The cluster's containers carry kind's cluster label, their /var volumes a label named
# after the node (podman), the network is named after the cluster; the pseudo-terminal
# holders are recorded in $holders_file.
remove_everything() {
  if [[ -s $holders_file ]]; then
    while read -r pid; do kill "$pid" 2>/dev/null || true; done <"$holders_file"
    rm -f "$holders_file"
  fi
  timeout 120 "$kind" delete cluster --name "$cluster" >/dev/null 2>&1 || true
  local ids
  ids=$("$engine" ps -aq --filter "label=io.x-k8s.kind.cluster=$cluster" 2>/dev/null || true)
  # shellcheck disable=SC2086 # one id a word
  [[ -n $ids ]] && "$engine" rm -f -v $ids >/dev/null 2>&1
  if [[ $engine == podman ]]; then
    for node in control-plane worker worker2 worker3; do
      ids=$(podman volume ls -q --filter "label=$cluster-$node" 2>/dev/null || true)
      # shellcheck disable=SC2086 # one name a word
      [[ -n $ids ]] && podman volume rm -f $ids >/dev/null 2>&1
    done
    podman network exists "$cluster" 2>/dev/null && podman network rm -f "$cluster" >/dev/null 2>&1
    remove_leftover_nat
  fi
  true
}
# podman's CNI portmap has left a removed cluster's NAT rules behind here (nodes removed
# without their network's teardown), among them a DNAT of 127.0.0.1:<the API server's
# host port> to a node address that is gone. That port is an ordinary ephemeral one: a
# server the kernel later gives it (any test's bind to port 0) never sees a connection,
# and its clients' connects time out. The rules name the network in their comments:
# remove them, and the chains they jump to. ROOST_NAT_DRY_RUN=1 only prints them.
remove_leftover_nat() {
  command -v iptables >/dev/null 2>&1 || return 0
  "$bin/python" - "$cluster" <<'PY'
import os, shlex, subprocess, sys

named = f'name: "{sys.argv[1]}"'
dry = os.environ.get("ROOST_NAT_DRY_RUN") == "1"
for tool in ("iptables", "ip6tables"):
    for table in ("nat", "filter"):
        def run(*args: str) -> str:
            if dry and args[0] != "-S":
                print(tool, "-t", table, *args)
                return ""
            done = subprocess.run(
                [tool, "-w", "5", "-t", table, *args], capture_output=True, text=True, check=False
            )
            return done.stdout
        chains = set()
        for rule in run("-S").splitlines():
            argv = shlex.split(rule)
            if argv[:1] != ["-A"] or not any(named in arg for arg in argv):
                continue
            target = argv[argv.index("-j") + 1] if "-j" in argv else ""
            if target.startswith("CNI-") and not target.startswith("CNI-HOSTPORT-"):
                chains.add(target)
            run("-D", *argv[1:])
        for chain in sorted(chains):
            run("-F", chain)
            run("-X", chain)
PY
}
cleanup() {
  local status=$?
  trap - EXIT INT TERM
  if [[ -n $step_pid ]]; then
    kill -TERM -- "-$step_pid" 2>/dev/null || true
    wait "$step_pid" 2>/dev/null || true
  fi
  if [[ "${ROOST_KIND_KEEP:-0}" == 1 ]]; then
    say "cluster kept (ROOST_KIND_KEEP=1): KUBECONFIG=$kubeconfig; remove it with ROOST_KIND_CLEAN=1 $0"
  else
    remove_everything
    say "removed the cluster's containers, volumes and network"
  fi
  exit "$status"
}
mkdir -p "$state"
# One run at a time per checkout: a second one would remove the first one's cluster.
# (Steps and the pseudo-terminal holders do not inherit it: podman's conmon processes
# would keep it for the life of the node containers.)
exec 9>"$state/lock"
flock -n 9 || { say "another run of $0 is in progress (lock $state/lock)"; exit 1; }
if [[ "${ROOST_KIND_KEEP:-0}" != 1 ]] || [[ "${ROOST_KIND_CLEAN:-0}" == 1 ]]; then
  remove_everything
  [[ "${ROOST_KIND_CLEAN:-0}" == 1 ]] && { say "removed"; exit 0; }
fi
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
: >"$timings"

# -- 3. fake serial ports -------------------------------------------------------------------
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
' "$link" 9>&- &
  echo "$!" >>"$holders_file"
done
for i in 1 2 3; do
  for _ in $(seq 50); do [[ -L "$state/vehicle-$i/ttyUSB0" ]] && break; sleep 0.1; done
  [[ -c "$state/vehicle-$i/ttyUSB0" ]] || { say "no pseudo-terminal for vehicle-$i"; exit 1; }
done

# -- 4. node image and cluster ------------------------------------------------------------------
if [[ $provider == podman ]]; then
  # kind mounts the host's /lib/modules read-only into every node; a host without
  # loadable modules has none, and an empty directory is all the nodes need then.
  [[ -d /lib/modules ]] || mkdir -p /lib/modules
  # Node names resolve on the cluster's network only with podman's DNS plugin
  # (netavark has aardvark-dns built in); the workers join the control plane by name.
  if [[ $(podman info --format '{{.Host.NetworkBackend}}') == cni && ! -x /usr/lib/cni/dnsname ]]; then
    docker/debian-packages.sh /usr/lib/cni/dnsname=golang-github-containernetworking-plugin-dnsname \
      || skip "podman's CNI backend has no DNS plugin (Debian: golang-github-containernetworking-plugin-dnsname)"
  fi
  t0=$(now)
  step "$here/node-image/build.sh" >"$state/node-image"
  node_image=$(tail -1 "$state/node-image")
  mark node_image_s "$t0"
else
  node_image=$KIND_NODE_IMAGE
fi
t0=$(now)
if "$kind" get clusters 2>/dev/null | grep -qx "$cluster"; then
  say "reusing cluster $cluster (kept by ROOST_KIND_KEEP=1)"
  "$kind" export kubeconfig --name "$cluster" --kubeconfig "$kubeconfig"
else
  say "creating cluster $cluster with $provider (kind ${KIND_VERSION}, ${node_image%%@*})"
  create() {
    step timeout 600 "$kind" create cluster --name "$cluster" --config kind-config.yaml \
      --image "$node_image" --kubeconfig "$kubeconfig" --wait 300s
  }
  # One retry from scratch: podman 4.3 sometimes fails the first of several concurrent
  # commands on a fresh runtime directory ("creating runtime status file").
  if ! create; then
    say "kind create failed; removing what it made and trying once more"
    remove_everything
    create
  fi
fi
kubectl wait --for=condition=Ready node --all --timeout=300s >/dev/null
mark create_to_ready_s "$t0"
say "cluster ready: $(kubectl get nodes --no-headers | wc -l) nodes"

# -- 5. images --------------------------------------------------------------------------------
values=(--values charts/roost/values-kind.yaml)
if [[ $provider == podman ]]; then
  # ROOST_IMAGES_DIR: archives built before (e.g. a copy taken while another checkout
  # rebuilds the shared cache), as tests/support/images.py reads it.
  if [[ -n ${ROOST_IMAGES_DIR:-} ]]; then
    images=$ROOST_IMAGES_DIR
  else
    step docker/build-images.sh >"$state/images"
    images=$(tail -1 "$state/images")
  fi
  for target in operator agent; do
    # A copy: the archives under ~/.cache are shared with other checkouts' builds.
    archive="$state/roost-$target.oci.tar"
    cp "$images/roost-$target.oci.tar" "$archive"
    name=$(tar -xOf "$archive" index.json | "$bin/python" -c \
      'import json, sys; print(json.load(sys.stdin)["manifests"][0]["annotations"]["org.opencontainers.image.ref.name"])')
    say "loading $name"
    # What `kind load image-archive` does, by hand: kind ${KIND_VERSION} cannot read the
    # configuration dump of containerd 2.4 (version 4), which it asks for the snapshotter.
    for node in $("$kind" get nodes --name "$cluster"); do
      podman cp "$archive" "$node:/var/tmp/roost-image.oci.tar"
      step timeout 600 podman exec "$node" ctr --namespace=k8s.io images import \
        --all-platforms --digests --local /var/tmp/roost-image.oci.tar >/dev/null
      podman exec "$node" rm -f /var/tmp/roost-image.oci.tar
    done
    values+=(--set "$target.image.repository=${name%:*}" --set "$target.image.tag=${name##*:}")
    # The Mission's onboard Job runs the agent image's Python (it is on every node).
    [[ $target == agent ]] && export ROOST_KIND_ONBOARD_IMAGE=$name
  done
  export ROOST_KIND_SIMULATED=1
  # The locally built node image has no volume provisioner (kind's local-path one is
  # another image from a registry): the operator's Mission records go to an emptyDir.
  values+=(--set operator.records.persistence.enabled=false)
else
  context="$state/image-context"
  docker/build-images.sh --context "$context"
  for target in operator agent; do
    say "building roost-$target:e2e"
    DOCKER_BUILDKIT=1 docker build -f docker/Dockerfile --target "$target" -t "roost-$target:e2e" "$context"
    "$kind" load docker-image "roost-$target:e2e" --name "$cluster"
  done
fi

# -- 6. chart -----------------------------------------------------------------------------------
step "$bin/helm" --kubeconfig "$kubeconfig" upgrade --install roost charts/roost --namespace "$namespace" --create-namespace \
  "${values[@]}" --wait --timeout 5m

# -- 7. end-to-end tests ------------------------------------------------------------------------
say "running the KinD end-to-end tests"
t0=$(now)
ROOST_KIND_KUBECONFIG="$kubeconfig" ROOST_KIND_NAMESPACE="$namespace" ROOST_KIND_ENGINE="$engine" \
  ROOST_KIND_CLUSTER="$cluster" step timeout 1800 "$bin/pytest" -p no:cacheprovider -v \
  ${ROOST_KIND_JUNIT:+"--junitxml=$ROOST_KIND_JUNIT"} "$here"
mark e2e_suite_s "$t0"
