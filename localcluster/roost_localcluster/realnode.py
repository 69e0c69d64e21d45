"""Real nodes for the local harness: kubelet, containerd and CNI in a network namespace each.

Why: kwok plays the kubelet of the fleet's fake nodes, which shows what the scheduler and
controllers do but never runs an image. A real node runs the chart's pods for real:
images imported into containerd, a pod sandbox, pod networking, the service-account token
mounted by the kubelet, the agent on the host network of *its* node, ``kubectl logs`` and
``exec`` through the kubelet. It is the shape of a K3s agent on a companion computer
(docs/real-node.md maps the parts), beside any number of kwok nodes in the same cluster.

Per node (``RealNodes.add``), all built by ``localcluster/build-node.sh``:

- a network namespace with its own address on the harness's bridge
  (:mod:`roost_localcluster.nodenet`); the API server is reached through a relay on the
  bridge's address (:mod:`roost_localcluster.relay`), and pods reach it at the
  ``kubernetes`` Service (10.96.0.1) through kube-proxy, whose EndpointSlice the harness
  writes (the API server's own endpoint reconciler is off: it would publish 127.0.0.1);
- containerd (CRI, overlayfs, Debian's runc, ``restrict_oom_score_adj`` since the harness
  has no CAP_SYS_RESOURCE) with a locally built pause image as the sandbox image;
- the CNI bridge plugin (``cni0`` inside the namespace, host-local addresses, masquerade)
  plus portmap and loopback;
- kubelet (cgroupfs driver under its own cgroup root ``/roost-<tag>-<index>``, swap and
  cgroup v1 tolerated) with a client certificate for ``system:node:<name>`` (Node
  authoriser, NodeRestriction) and a serving certificate signed by the harness CA;
- kube-proxy (iptables mode, inside the namespace).

The programs enter only the node's *network* namespace (``nsenter --net``): kubelet and
containerd must share one mount namespace, as on a real machine, so volumes the kubelet
mounts are what containerd binds into containers. Teardown stops them by pid, kills what
is left in the node's cgroup (pods, shims) by pid, unmounts every mount under the node's
directories, removes the cgroups, the namespace and the veth. Needs root.

A pool records what it owns in ``/run/roost-node/<tag>.json`` (with its pid); a pool whose
process was SIGKILLed leaves its programs dead (parent-death signal) but namespaces,
links, cgroups, mounts and containers behind, which the next pool sweeps from that record
(:func:`sweep_stale`). Short paths (unix sockets: the containerd socket, the kubelet's
root directory) are under ``/run/roost-node/<tag>-<index>``; the rest under the pool's
directory.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import ipaddress
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import psutil
import yaml

from roost_kube.errors import ApiError
from roost_kube.resources import NODES
from roost_localcluster import binaries, nodes, pki
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane
from roost_localcluster.nodenet import NodeNetwork, missing_prerequisites
from roost_localcluster.processes import ManagedProcess

POD_CIDR = "10.214.0.0/16"
"""Pods of real nodes: node ``index`` hands out 10.214.<index>.0/24 (masqueraded inside the
node's namespace, so two harnesses using the same addresses never meet)."""
RUNTIME_ROOT = Path("/run/roost-node")  # short paths: unix sockets allow 107 bytes
CNI_CACHE = Path("/var/lib/cni/results")  # libcni's, not configurable through containerd
CONTAINER_LOG_LINKS = Path("/var/log/containers")  # the kubelet's, fixed
CONTAINERD_NAMESPACE = "k8s.io"
START_TIMEOUT_S = 180.0
_PROGRAMS = ("containerd", "kubelet", "kube-proxy")


class RealNodeError(RuntimeError):
    """A node program did not start or the node did not become Ready; carries log tails."""


# ---- cgroups ---------------------------------------------------------------------------
def cgroup_mounts() -> list[Path]:
    """Mount points of every cgroup hierarchy (v1 controllers and the v2 tree)."""
    found = []
    for line in Path("/proc/self/mountinfo").read_text().splitlines():
        before, _, after = line.partition(" - ")
        if after.split()[0] in ("cgroup", "cgroup2"):
            found.append(Path(before.split()[4]))
    return found


def _tracking_hierarchy() -> Path:
    """The hierarchy whose ``cgroup.procs`` lists the node's processes: v1 ``pids`` where
    mounted (every process is in it), else the v2 tree."""
    mounts = cgroup_mounts()
    for mount in mounts:
        if mount.name == "pids":
            return mount
    for mount in mounts:
        if (mount / "cgroup.controllers").exists():
            return mount
    raise RealNodeError("no cgroup hierarchy to track node processes in")


def _make_cgroup(mount: Path, relative: str) -> None:
    path = mount / relative.lstrip("/")
    parent = path.parent
    path.mkdir(parents=True, exist_ok=True)
    for name in ("cpuset.cpus", "cpuset.mems"):  # an empty cpuset admits no task
        own, inherited = path / name, parent / name
        if own.exists() and not own.read_text().strip():
            own.write_text(inherited.read_text())


def _cgroup_pids(root: Path) -> set[int]:
    pids: set[int] = set()
    if not root.is_dir():
        return pids
    for procs in root.rglob("cgroup.procs"):
        with contextlib.suppress(OSError):
            pids.update(int(p) for p in procs.read_text().split())
    return pids


def _remove_cgroup_tree(root: Path) -> None:
    if not root.is_dir():
        return
    for path in sorted((p for p in root.rglob("*") if p.is_dir()), key=lambda p: -len(p.parts)):
        with contextlib.suppress(OSError):
            path.rmdir()
    with contextlib.suppress(OSError):
        root.rmdir()


# ---- mounts --------------------------------------------------------------------------
def _unescape(path: str) -> str:
    return path.encode().decode("unicode_escape") if "\\" in path else path


def mounts_under(*directories: Path) -> list[Path]:
    """Mount points at or below ``directories``, deepest (and latest) first."""
    roots = [str(d.resolve()) for d in directories]
    points = []
    for line in Path("/proc/self/mountinfo").read_text().splitlines():
        point = _unescape(line.split()[4])
        if any(point == r or point.startswith(r + "/") for r in roots):
            points.append(Path(point))
    return list(reversed(points))


def _unmount_all(*directories: Path) -> None:
    for _ in range(5):
        points = mounts_under(*directories)
        if not points:
            return
        for point in points:
            subprocess.run(["umount", "-l", str(point)], capture_output=True, check=False)


# ---- configuration -------------------------------------------------------------------
@dataclass
class RealNode:
    """One real node: where its files are and the programs running it."""

    name: str
    index: int
    address: str
    namespace: str
    directory: Path
    runtime_dir: Path
    cgroup: str
    arch: str = binaries.HOST_ARCH
    processes: dict[str, ManagedProcess] = field(default_factory=dict)

    @property
    def containerd_socket(self) -> Path:
        return self.runtime_dir / "containerd.sock"

    @property
    def pod_subnet(self) -> str:
        return f"10.214.{self.index}.0/24"

    @property
    def logs_dir(self) -> Path:
        return self.directory / "logs"

    @property
    def platform(self) -> str:
        """The node's OCI platform: what its containerd runs and imports."""
        return f"linux/{self.arch}"

    def ctr(self, *args: str) -> list[str]:
        """A ``ctr`` command line against this node's containerd (CRI's namespace); the
        host's own ``ctr`` (a client: it runs natively for a node of any architecture)."""
        node_bin = binaries.node_dir() / "bin"
        return [
            str(node_bin / "ctr"),
            "--address",
            str(self.containerd_socket),
            "--namespace",
            CONTAINERD_NAMESPACE,
            *args,
        ]

    def pids(self) -> set[int]:
        """Every process of the node: its programs, shims and containers."""
        return _cgroup_pids(_tracking_hierarchy() / self.cgroup.lstrip("/"))

    def run_in_namespace(self, argv: Sequence[str]) -> list[str]:
        """``argv`` in this node's network namespace only (see the module docstring)."""
        return ["nsenter", f"--net=/run/netns/{self.namespace}", "--", *argv]


def containerd_config(node: RealNode, node_dir: Path) -> str:
    """containerd's configuration (version 3) for ``node``; everything under its dirs."""
    state = node.runtime_dir / "state"
    lines = [
        "version = 3",
        f"root = {json.dumps(str(node.directory / 'containerd'))}",
        f"state = {json.dumps(str(state))}",
        "[grpc]",
        f"  address = {json.dumps(str(node.containerd_socket))}",
        "[plugins.'io.containerd.nri.v1.nri']",
        "  disable = true",
        "[plugins.'io.containerd.internal.v1.opt']",
        f"  path = {json.dumps(str(node.directory / 'opt'))}",
        "[plugins.'io.containerd.cri.v1.images']",
        "  snapshotter = 'overlayfs'",
        "[plugins.'io.containerd.cri.v1.images'.pinned_images]",
        f"  sandbox = {json.dumps(binaries.pause_image(node_dir))}",
        "[plugins.'io.containerd.cri.v1.runtime']",
        # No CAP_SYS_RESOURCE here: never ask for an OOM score below containerd's own.
        "  restrict_oom_score_adj = true",
        "  netns_mounts_under_state_dir = true",
        "  cdi_spec_dirs = []",
        "[plugins.'io.containerd.cri.v1.runtime'.containerd]",
        "  default_runtime_name = 'runc'",
        "[plugins.'io.containerd.cri.v1.runtime'.containerd.runtimes.runc]",
        "  runtime_type = 'io.containerd.runc.v2'",
        "[plugins.'io.containerd.cri.v1.runtime'.containerd.runtimes.runc.options]",
        # Debian's runc: crun refuses hosts with a hybrid cgroup hierarchy. An arm64
        # node's too: arm64 runc cannot start containers under qemu-user (build-node.sh).
        f"  BinaryName = {json.dumps(shutil.which('runc') or 'runc')}",
        f"  Root = {json.dumps(str(node.runtime_dir / 'runc'))}",
        "  SystemdCgroup = false",
        "[plugins.'io.containerd.cri.v1.runtime'.cni]",
        f"  bin_dirs = [{json.dumps(str(node_dir / 'cni'))}]",
        f"  conf_dir = {json.dumps(str(node.directory / 'cni' / 'net.d'))}",
        # containerd brings up the pod's loopback itself: no host-wide CNI cache entry.
        "  use_internal_loopback = true",
        "[plugins.'io.containerd.grpc.v1.cri']",
        "  stream_server_address = '127.0.0.1'",
    ]
    return "\n".join(lines) + "\n"


def cni_config(node: RealNode) -> dict[str, Any]:
    """The pod network: a bridge inside the node's namespace, masqueraded, plus portmap."""
    return {
        "cniVersion": "1.0.0",
        # The node's own name: libcni caches results host-wide under <name>-<container>.
        "name": node.namespace,
        "plugins": [
            {
                "type": "bridge",
                "bridge": "cni0",
                "isGateway": True,
                "isDefaultGateway": True,
                "ipMasq": True,
                "hairpinMode": True,
                "ipam": {
                    "type": "host-local",
                    "ranges": [[{"subnet": node.pod_subnet}]],
                    "dataDir": str(node.directory / "cni" / "ipam"),
                },
            },
            {"type": "portmap", "capabilities": {"portMappings": True}},
        ],
    }


def kubelet_config(node: RealNode, keys: pki.Pki, serving: tuple[Path, Path]) -> dict[str, Any]:
    """KubeletConfiguration of ``node`` (what this host needs is explained inline)."""
    return {
        "apiVersion": "kubelet.config.k8s.io/v1beta1",
        "kind": "KubeletConfiguration",
        "address": node.address,
        "port": 10250,
        "readOnlyPort": 0,
        "healthzBindAddress": "127.0.0.1",
        "healthzPort": 10248,
        "tlsCertFile": str(serving[0]),
        "tlsPrivateKeyFile": str(serving[1]),
        "authentication": {
            "anonymous": {"enabled": False},
            "webhook": {"enabled": True},
            "x509": {"clientCAFile": str(keys.ca_cert)},
        },
        "authorization": {"mode": "Webhook"},
        "containerRuntimeEndpoint": f"unix://{node.containerd_socket}",
        # No systemd: cgroupfs, under a cgroup root of its own (two kubelets sharing one
        # would each remove the other's pod cgroups as orphans).
        "cgroupDriver": "cgroupfs",
        "cgroupRoot": node.cgroup,
        "failSwapOn": False,
        "failCgroupV1": False,
        "clusterDomain": "cluster.local",
        "resolvConf": "",
        "podLogsDir": str(node.directory / "pod-logs"),
        # Imported images must never be garbage-collected (nothing could pull them back),
        # and a full disk on this shared machine must not evict the node's pods.
        "imageGCHighThresholdPercent": 100,
        "imageGCLowThresholdPercent": 99,
        "evictionHard": {
            "memory.available": "1Mi",
            "nodefs.available": "0%",
            "imagefs.available": "0%",
            "nodefs.inodesFree": "0%",
        },
        "serializeImagePulls": False,
        "registerNode": True,
        "maxPods": 30,
    }


def kube_proxy_config(node: RealNode, kubeconfig: Path) -> dict[str, Any]:
    return {
        "apiVersion": "kubeproxy.config.k8s.io/v1alpha1",
        "kind": "KubeProxyConfiguration",
        "clientConnection": {"kubeconfig": str(kubeconfig)},
        "hostnameOverride": node.name,
        "bindAddress": node.address,
        "healthzBindAddress": "127.0.0.1:10256",
        "metricsBindAddress": "127.0.0.1:10249",
        "mode": "iptables",
        "clusterCIDR": POD_CIDR,
        # The namespace's conntrack table is the host's: leave its sysctls alone.
        "conntrack": {
            "maxPerCore": 0,
            "min": 0,
            "tcpEstablishedTimeout": "0s",
            "tcpCloseWaitTimeout": "0s",
        },
    }


def api_endpoint_slice(address: str, port: int) -> dict[str, Any]:
    """The ``kubernetes`` Service's endpoints as pods of real nodes reach the API server."""
    return {
        "apiVersion": "discovery.k8s.io/v1",
        "kind": "EndpointSlice",
        "metadata": {
            "name": "kubernetes",
            "namespace": "default",
            "labels": {
                "kubernetes.io/service-name": "kubernetes",
                "endpointslice.kubernetes.io/managed-by": "roost-localcluster",
            },
        },
        "addressType": "IPv4",
        "endpoints": [{"addresses": [address], "conditions": {"ready": True}}],
        "ports": [{"name": "https", "port": port, "protocol": "TCP"}],
    }


# ---- the pool ------------------------------------------------------------------------
class RealNodes:
    """Real nodes beside the kwok ones of ``cluster`` (its control plane started here).

    ``add`` starts a node and waits until it is Ready; ``remove`` stops one; ``cleanup``
    (or leaving the ``with`` block) stops all and removes the network. A node's logs are
    in ``<directory>/<name>/logs``.
    """

    def __init__(self, cluster: Cluster, directory: Path | None = None) -> None:
        if cluster.control_plane is None:
            raise ValueError("real nodes need a control plane started by this process")
        reasons = missing_prerequisites()
        if reasons:
            raise RealNodeError("real nodes cannot run here: " + "; ".join(reasons))
        self.cluster = cluster
        self.plane: ControlPlane = cluster.control_plane
        self.directory = Path(directory or tempfile.mkdtemp(prefix="roost-nodes-")).resolve()
        self.tag = secrets.token_hex(3)
        self.node_dir = binaries.ensure_node_built()
        self._node_dirs = {binaries.HOST_ARCH: self.node_dir}
        self.network: NodeNetwork | None = None
        self.relay: ManagedProcess | None = None
        self.nodes: dict[str, RealNode] = {}
        self._registrations: dict[str, tuple[dict[str, str], list[dict[str, str]]]] = {}
        self._next_index = 0
        sweep_stale()
        atexit.register(self.cleanup)

    def _record(self) -> None:
        """Write what this pool owns to ``RUNTIME_ROOT/<tag>.json``, so that a later pool
        can take it down if this process dies without cleaning up (see :func:`sweep_stale`)."""
        if self.network is None:
            return
        RUNTIME_ROOT.mkdir(parents=True, exist_ok=True)
        record = {
            "pid": os.getpid(),
            "create_time": psutil.Process().create_time(),
            "subnet": str(self.network.subnet),
            "nodes": [
                {f.name: str(getattr(n, f.name)) for f in _RECORDED_FIELDS}
                for n in self.nodes.values()
            ],
        }
        _owner_file(self.tag).write_text(json.dumps(record))

    def __enter__(self) -> Self:
        return self

    def programs(self, arch: str) -> Path:
        """The directory of the node programs built for ``arch`` (built when missing)."""
        if arch not in self._node_dirs:
            self._node_dirs[arch] = binaries.ensure_node_built(arch)
        return self._node_dirs[arch]

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.cleanup()

    # ---- shared network ----------------------------------------------------------------
    def _ensure_network(self) -> NodeNetwork:
        if self.network is not None:
            return self.network
        assert self.plane.ports is not None, "control plane not started"
        port = self.plane.ports.apiserver
        network = NodeNetwork.create(self.tag)
        self.network = network
        self._record()
        relay = ManagedProcess(
            "api-relay",
            [
                sys.executable,
                "-m",
                "roost_localcluster.relay",
                f"{network.host_address}:{port}",
                f"127.0.0.1:{port}",
            ],
            self.directory / "api-relay.log",
        )
        relay.launch(die_with_parent=True)
        self.relay = relay
        _wait_for(lambda: "relaying" in relay.log.read_text(), 10, "the API relay", [relay])
        self.publish_api()
        return network

    def publish_api(self) -> None:
        """Point the ``kubernetes`` Service at this pool's relay (its EndpointSlice). One
        pool per control plane does: another pool's (a test's second pool) replaces it, and
        the first one's pods lose the API server until this is called again."""
        assert self.network is not None and self.plane.ports is not None
        slice_manifest = api_endpoint_slice(self.network.host_address, self.plane.ports.apiserver)
        self.cluster.kubectl("apply", "-f", "-", input_text=json.dumps(slice_manifest))

    # ---- nodes ---------------------------------------------------------------------------
    def add(
        self,
        name: str,
        *,
        labels: Mapping[str, str] | None = None,
        taints: Iterable[Mapping[str, str]] = (),
        images: Sequence[Path] = (),
        timeout_s: float = START_TIMEOUT_S,
        arch: str = binaries.HOST_ARCH,
    ) -> RealNode:
        """Start a real node called ``name``; returns once it is Ready.

        ``labels`` and ``taints`` are registered by the kubelet (NodeRestriction allows no
        ``kubernetes.io`` labels but its own). ``images`` are OCI archives imported into
        its containerd before the kubelet starts. ``arch`` other than this machine's
        (``arm64``): kubelet, kube-proxy, containerd, its shim and the CNI plugins built
        for it, run under qemu-user-static (docker/binfmt.sh); the kubelet itself then
        reports ``kubernetes.io/arch=<arch>``, and containerd runs the images' arm64
        builds (started by the host's runc, see build-node.sh).
        """
        network = self._ensure_network()
        index = self._next_index
        self._next_index += 1
        node = RealNode(
            name=name,
            index=index,
            address=network.node_address(index),
            namespace=network.namespace(index),
            directory=self.directory / name,
            runtime_dir=RUNTIME_ROOT / f"{self.tag}-{index}",
            cgroup=f"/roost-{self.tag}-{index}",
            arch=arch,
        )
        self.nodes[name] = node
        self._registrations[name] = (dict(labels or {}), [dict(t) for t in taints])
        self._record()
        try:
            network.add_node(index)
            peers = {n.index: n.pod_subnet for n in self.nodes.values() if n is not node}
            network.route_pods(index, node.pod_subnet, peers)
            self._prepare(node)
            self._start_containerd(node)
            pause = self.programs(node.arch) / binaries.PAUSE_ARCHIVE
            self.import_images(node, [pause, *images])
            self._start_kubelet(node, labels or {}, taints)
            self._start_kube_proxy(node)
            self._wait_ready(node, timeout_s)
        except BaseException:
            self.remove(name)
            raise
        return node

    def _prepare(self, node: RealNode) -> None:
        for sub in ("logs", "containerd", "cni/net.d", "pod-logs", "pki"):
            (node.directory / sub).mkdir(parents=True, exist_ok=True)
        node.runtime_dir.mkdir(parents=True, exist_ok=True)
        for mount in cgroup_mounts():
            _make_cgroup(mount, node.cgroup)
        _make_cgroup(_tracking_hierarchy(), f"{node.cgroup}/runtime")
        config = containerd_config(node, self.programs(node.arch))
        (node.directory / "containerd.toml").write_text(config)
        conflist = node.directory / "cni" / "net.d" / "10-roost.conflist"
        conflist.write_text(json.dumps(cni_config(node), indent=2))

    def _launch(self, node: RealNode, name: str, argv: list[str]) -> ManagedProcess:
        """Start one node program in the node's network namespace and cgroup."""
        path = f"{self.programs(node.arch) / 'bin'}:/usr/local/sbin:/usr/sbin:/sbin:"
        if node.arch != binaries.HOST_ARCH:
            # The arm64 shim cannot start under qemu-user ("start failed: ... invalid
            # argument"): containerd finds the host's first, as it finds the host's runc.
            shim_dir = node.directory / "host-shim"
            shim_dir.mkdir(exist_ok=True)
            shim = shim_dir / "containerd-shim-runc-v2"
            if not shim.exists():
                shim.symlink_to(self.node_dir / "bin" / "containerd-shim-runc-v2")
            path = f"{shim_dir}:{path}"
        env = {**os.environ, "PATH": path + os.environ.get("PATH", "/usr/bin:/bin")}
        proc = ManagedProcess(name, node.run_in_namespace(argv), node.logs_dir / f"{name}.log")
        proc.launch(env, die_with_parent=True)
        node.processes[name] = proc
        # nsenter execs the program: the pid is the program's, and what it forks (shims,
        # their containers' first processes) starts in the same cgroup.
        procs = _tracking_hierarchy() / node.cgroup.lstrip("/") / "runtime" / "cgroup.procs"
        with contextlib.suppress(OSError):
            procs.write_text(str(proc.pid))
        return proc

    def _start_containerd(self, node: RealNode) -> None:
        config = node.directory / "containerd.toml"
        containerd = self.programs(node.arch) / "bin" / "containerd"
        proc = self._launch(node, "containerd", [str(containerd), "--config", str(config)])
        _wait_for(node.containerd_socket.exists, 60, "containerd's socket", [proc])
        _wait_for(
            lambda: (
                subprocess.run(node.ctr("version"), capture_output=True, check=False).returncode
                == 0
            ),
            30,
            "containerd to answer",
            [proc],
        )

    def import_images(self, node: RealNode, archives: Sequence[Path]) -> None:
        """Import OCI archives into the node's containerd (``ctr images import``, into
        the CRI's namespace), under the names the archives give (``make images`` names
        them ``localhost/roost-<target>:<version>``). An archive holding an image index
        (amd64 and arm64) is imported with the index and the node's platform's content
        only (``--platform``; ``--all-platforms`` would store both)."""
        for archive in archives:
            self._ctr(
                node, "images", "import", "--no-unpack", "--platform", node.platform,
                str(archive), timeout_s=600,
            )  # fmt: skip

    def _ctr(self, node: RealNode, *args: str, timeout_s: float = 60) -> str:
        done = subprocess.run(
            node.ctr(*args), capture_output=True, text=True, check=False, timeout=timeout_s
        )
        if done.returncode != 0:
            raise RealNodeError(f"ctr {' '.join(args)}: {done.stderr.strip()}")
        return done.stdout

    def images(self, node: RealNode) -> list[str]:
        """Names of the images in the node's containerd."""
        done = subprocess.run(
            node.ctr("images", "list", "--quiet"), capture_output=True, text=True, check=True
        )
        return done.stdout.split()

    def _start_kubelet(
        self, node: RealNode, labels: Mapping[str, str], taints: Iterable[Mapping[str, str]]
    ) -> None:
        keys = self.plane.pki
        identity = pki.node_identity(node.name)
        node_keys = pki.Pki(node.directory / "pki")
        shutil.copy(keys.ca_cert, node_keys.ca_cert)
        shutil.copy(keys.ca_key, node_keys.ca_key)
        node_keys.ca_key.chmod(0o600)
        try:
            pki.issue_client(node_keys, identity)
            pki.issue_client(node_keys, pki.KUBE_PROXY)
            serving = pki.issue_kubelet_serving(node_keys, node.name, node.address)
        finally:
            node_keys.ca_key.unlink()  # the node keeps no CA key, as on a real fleet
        server = self._server()
        kubeconfig = pki.write_kubeconfig(
            node.directory / "kubelet.kubeconfig", node_keys, server, identity, "kubernetes"
        )
        pki.write_kubeconfig(
            node.directory / "kube-proxy.kubeconfig",
            node_keys,
            server,
            pki.KUBE_PROXY,
            "kubernetes",
        )
        config = node.directory / "kubelet.yaml"
        config.write_text(yaml.safe_dump(kubelet_config(node, node_keys, serving)))
        argv = [
            str(self.programs(node.arch) / "bin" / "kubelet"),
            f"--config={config}",
            f"--kubeconfig={kubeconfig}",
            f"--hostname-override={node.name}",
            f"--node-ip={node.address}",
            # Short: the kubelet's unix sockets live there (107 bytes at most).
            f"--root-dir={node.runtime_dir / 'kubelet'}",
            "--v=1",
        ]
        if labels:
            argv.append("--node-labels=" + ",".join(f"{k}={v}" for k, v in labels.items()))
        taint_args = [f"{t['key']}={t.get('value', '')}:{t['effect']}" for t in taints]
        if taint_args:
            argv.append("--register-with-taints=" + ",".join(taint_args))
        self._launch(node, "kubelet", argv)

    def _start_kube_proxy(self, node: RealNode) -> None:
        config = node.directory / "kube-proxy.yaml"
        kubeconfig = node.directory / "kube-proxy.kubeconfig"
        config.write_text(yaml.safe_dump(kube_proxy_config(node, kubeconfig)))
        programs = self.programs(node.arch) / "bin"
        argv = [str(programs / "kube-proxy"), f"--config={config}", "--v=1"]
        self._launch(node, "kube-proxy", argv)

    def _server(self) -> str:
        assert self.network is not None and self.plane.ports is not None
        return f"https://{self.network.host_address}:{self.plane.ports.apiserver}"

    def _wait_ready(self, node: RealNode, timeout_s: float) -> None:
        def ready() -> bool:
            try:
                found = self.cluster.admin.get(NODES, node.name)
            except ApiError:
                return False
            return found is not None and nodes.node_is_ready(found)

        _wait_for(ready, timeout_s, f"node {node.name} Ready", list(node.processes.values()))

    # ---- faults ----------------------------------------------------------------------------
    def set_link(self, name: str, *, up: bool) -> None:
        """Cut (``up=False``) or restore node ``name``'s link to the harness: a vehicle's
        WiFi drop. Its programs and pods keep running; nothing but its network changes."""
        assert self.network is not None, "no node was added"
        self.network.set_link(self.nodes[name].index, up=up)

    def power_off(self, name: str) -> None:
        """Node ``name``'s computer loses power: every process of it (containerd, kubelet,
        kube-proxy, the containers and their shims) is killed at once, its mounts go and
        so does what lives in ``/run`` on a real machine (containerd's and runc's runtime
        state). What a disk keeps stays: images, the kubelet's pod directories (emptyDir
        volumes), certificates. :meth:`power_on` boots it again."""
        node = self.nodes[name]
        _kill_cgroup_tree(_tracking_hierarchy() / node.cgroup.lstrip("/"))
        for proc in node.processes.values():
            proc.stop(grace_s=0.0)  # already dead: reaped
        node.processes.clear()
        _unmount_all(node.directory, node.runtime_dir)
        for volatile in ("state", "runc"):
            shutil.rmtree(node.runtime_dir / volatile, ignore_errors=True)
        node.containerd_socket.unlink(missing_ok=True)

    def power_on(self, name: str, *, wait_ready: bool = True) -> None:
        """Boot node ``name`` again after :meth:`power_off`: containerd, the kubelet (which
        finds its pods in the API and starts their containers anew) and kube-proxy;
        returns once the Node is Ready (``wait_ready``) or at once."""
        node = self.nodes[name]
        labels, taints = self._registrations.get(name, ({}, []))
        self._start_containerd(node)
        self._start_kubelet(node, labels, taints)
        self._start_kube_proxy(node)
        if wait_ready:
            self._wait_ready(node, START_TIMEOUT_S)

    # ---- teardown ------------------------------------------------------------------------
    def remove(self, name: str, delete_node: bool = True) -> None:
        """Stop node ``name``: its programs, pods and mounts, cgroups and namespace."""
        node = self.nodes.pop(name, None)
        self._registrations.pop(name, None)
        if node is None:
            return
        for program in reversed(_PROGRAMS):
            proc = node.processes.pop(program, None)
            if proc is not None:
                proc.stop(grace_s=5.0)
        release(node, self.network)
        if self.network is not None:
            self.network.unroute_pods(node.pod_subnet, [n.index for n in self.nodes.values()])
        self._record()
        if delete_node:
            self.cluster.kubectl("delete", "node", name, "--ignore-not-found", check=False)

    def cleanup(self) -> None:
        """Remove every node, the relay, the API's EndpointSlice and the bridge."""
        for name in list(self.nodes):
            self.remove(name)
        if self.relay is not None:
            self.relay.stop()
            self.relay = None
        if self.network is not None:
            self.cluster.kubectl(
                "delete", "endpointslice", "kubernetes", "-n", "default", "--ignore-not-found",
                check=False,
            )  # fmt: skip
            self.network.delete()
            self.network = None
        _owner_file(self.tag).unlink(missing_ok=True)
        atexit.unregister(self.cleanup)
        with contextlib.suppress(OSError):
            RUNTIME_ROOT.rmdir()  # only when no other harness uses it


def release(node: RealNode, network: NodeNetwork | None) -> None:
    """Take down what is left of a node whose programs have stopped (or died): processes
    in its cgroup, mounts under its directories, its cgroups, veth and namespace."""
    _kill_cgroup_tree(_tracking_hierarchy() / node.cgroup.lstrip("/"))
    _unmount_all(node.directory, node.runtime_dir)
    for mount in cgroup_mounts():
        _remove_cgroup_tree(mount / node.cgroup.lstrip("/"))
    if network is not None:
        network.remove_node(node.index)
    shutil.rmtree(node.runtime_dir, ignore_errors=True)
    # What the kubelet and libcni write to fixed host paths for this node's containers.
    for cached in CNI_CACHE.glob(f"{node.namespace}-*"):
        cached.unlink(missing_ok=True)
    for link in CONTAINER_LOG_LINKS.glob("*.log"):
        with contextlib.suppress(OSError):
            if link.is_symlink() and link.readlink().is_relative_to(node.directory):
                link.unlink()


_RECORDED_FIELDS = [f for f in dataclasses.fields(RealNode) if f.name != "processes"]


def _owner_file(tag: str) -> Path:
    return RUNTIME_ROOT / f"{tag}.json"


def sweep_stale() -> list[str]:
    """Take down the nodes and networks of pools whose process is gone (SIGKILLed test
    runs: their programs died with them, by the parent-death signal, but namespaces,
    links, cgroups and mounts outlive processes). Returns the tags swept."""
    swept = []
    for path in sorted(RUNTIME_ROOT.glob("*.json")) if RUNTIME_ROOT.is_dir() else []:
        try:
            record = json.loads(path.read_text())
            owner = psutil.Process(int(record["pid"]))
            if abs(owner.create_time() - float(record["create_time"])) < 0.01:
                continue  # alive: another harness's
        except psutil.NoSuchProcess:
            pass
        except (OSError, ValueError, KeyError):
            continue
        tag = path.stem
        network = NodeNetwork(tag, ipaddress.IPv4Network(record["subnet"]))
        for entry in record["nodes"]:
            node = RealNode(
                name=entry["name"],
                index=int(entry["index"]),
                address=entry["address"],
                namespace=entry["namespace"],
                directory=Path(entry["directory"]),
                runtime_dir=Path(entry["runtime_dir"]),
                cgroup=entry["cgroup"],
            )
            release(node, network)
        network.delete()
        path.unlink(missing_ok=True)
        swept.append(tag)
    return swept


def _kill_cgroup_tree(root: Path, timeout_s: float = 10.0) -> None:
    """SIGKILL every process in the node's cgroup tree until it is empty: all of them were
    started by the node's programs (containers, their shims)."""
    deadline = time.monotonic() + timeout_s
    while pids := _cgroup_pids(root):
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        if time.monotonic() > deadline:
            raise RealNodeError(f"processes {sorted(pids)} in {root} survived SIGKILL")
        time.sleep(0.1)


def _wait_for(
    check: Callable[[], bool], timeout_s: float, what: str, watch: Sequence[ManagedProcess]
) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if check():
                return
        except OSError:
            pass
        for proc in watch:
            if not proc.alive():
                raise RealNodeError(
                    f"{proc.name} exited while waiting for {what}; log {proc.log}:\n"
                    f"{proc.log_tail(40)}"
                )
        if time.monotonic() > deadline:
            tails = "\n".join(f"--- {p.name} ({p.log}):\n{p.log_tail(15)}" for p in watch)
            raise RealNodeError(f"timed out after {timeout_s:.0f} s waiting for {what}\n{tails}")
        time.sleep(0.25)
