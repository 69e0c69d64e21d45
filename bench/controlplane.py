"""Control-plane figures: build time, warm start-to-ready time, memory with a fleet.

- ``controlplane.cold_build_s``: the sum of the per-binary build times that
  ``build-control-plane.sh`` recorded in ``build-times.tsv`` next to the cached binaries.
  A cold build takes minutes, so it is read from the record, never triggered here.
- ``controlplane.warm_start_to_ready_s``: median of three starts with the binaries cached,
  from nothing (fresh certificates, empty etcd) to usable (see ``ControlPlane.start``).
- ``controlplane.rss_mb_10_nodes`` / ``controlplane.rss_mb_1000_nodes``: summed resident
  memory of etcd, kube-apiserver, kube-controller-manager, kube-scheduler and kwok once that
  many fake vehicle nodes are Ready and each runs one DaemonSet pod (Roost's node agent is
  a DaemonSet), after a short settle.
- ``controlplane.fleet_1000_ready_s``: creating the remaining 990 nodes until all 1000 are
  Ready with their agent pod Running.
"""

from __future__ import annotations

import csv
import statistics
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from bench.core import Figure
from roost_kube.resources import PODS
from roost_localcluster import binaries, nodes
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane, Settings
from roost_localcluster.kwoknodes import KUBELET_REPORT_S

COMMAND = "python -m bench controlplane"
SETTLE_S = 10.0
AGENT_DS = "bench-agent"
VEHICLE_LABEL = "roost.dev/vehicle-class"
# 1000 nodes from one kwok: longer leases and grace period so a busy 2-core machine does not
# mark nodes NotReady while kwok renews a thousand leases.
FLEET_SETTINGS = Settings(
    node_lease_duration_s=120,
    node_monitor_grace_period_s=180,
    node_status_report_s=KUBELET_REPORT_S,
)


def _mb(plane: ControlPlane) -> float:
    return plane.rss_bytes() / 2**20


def cold_build() -> list[Figure]:
    record = binaries.bin_dir().parent / "build-times.tsv"
    if not record.exists():
        return []
    latest: dict[str, int] = {}
    with record.open() as f:
        for name, seconds, _when in csv.reader(f, delimiter="\t"):
            if name in binaries.COMPONENTS:  # kine is built only for --datastore kine
                latest[name] = int(seconds)
    if set(latest) != set(binaries.COMPONENTS):
        return []
    return [
        Figure(
            "controlplane.cold_build_s",
            float(sum(latest.values())),
            "s",
            "informational",
            "localcluster/build-control-plane.sh (empty cache)",
            note=f"per binary {latest} ({record.name}); downloading the Go modules first "
            "is not included (about 20 s here)",
        )
    ]


def warm_start(
    name: str = "controlplane.warm_start_to_ready_s",
    settings: Settings | None = None,
    command: str = COMMAND,
) -> Figure:
    times = []
    for _ in range(3):
        with tempfile.TemporaryDirectory(prefix="bench-cp-") as tmp:
            started = time.monotonic()
            plane = ControlPlane(Path(tmp), settings=settings)
            plane.start()
            times.append(time.monotonic() - started)
            plane.stop()
    return Figure(
        name,
        statistics.median(times),
        "s",
        "<= 30",
        command,
        note=f"median of {[round(t, 1) for t in times]}",
    )


def _create_fleet(cluster: Cluster, start: int, stop: int) -> list[str]:
    names = [f"bench-vehicle-{i:04d}" for i in range(start, stop)]

    def create(name: str) -> None:
        manifest = nodes.fake_node(name, labels={VEHICLE_LABEL: "bench"})
        cluster.admin.create(manifest)

    with ThreadPoolExecutor(max_workers=4) as pool:
        list(pool.map(create, names))
    return names


def _wait_agents_running(cluster: Cluster, count: int, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    kube = cluster.kube("roost-bench")
    while True:
        pods = kube.list_objects(PODS, namespace="default", labels={"app": AGENT_DS})
        running = sum(1 for p in pods if (p.get("status") or {}).get("phase") == "Running")
        if running >= count:
            return
        if time.monotonic() > deadline:
            raise TimeoutError(f"{running}/{count} agent pods Running after {timeout_s} s")
        time.sleep(2)


def _agent_daemonset() -> str:
    return (
        "apiVersion: apps/v1\nkind: DaemonSet\n"
        f"metadata: {{name: {AGENT_DS}, namespace: default}}\n"
        "spec:\n"
        f"  selector: {{matchLabels: {{app: {AGENT_DS}}}}}\n"
        "  template:\n"
        f"    metadata: {{labels: {{app: {AGENT_DS}}}}}\n"
        "    spec:\n"
        f"      nodeSelector: {{{VEHICLE_LABEL}: bench}}\n"
        "      containers: [{name: agent, image: roost-agent:bench}]\n"
    )


def _start_10_nodes(cluster: Cluster) -> None:
    """The agent DaemonSet and 10 Ready fake vehicle nodes, each running its pod."""
    cluster.kubectl("apply", "-f", "-", input_text=_agent_daemonset())
    cluster.wait_nodes_ready(_create_fleet(cluster, 0, 10))
    _wait_agents_running(cluster, 10, 120)
    time.sleep(SETTLE_S)


def memory_10_nodes(settings: Settings) -> float:
    """Summed resident MiB of the control plane with 10 nodes (see :func:`_start_10_nodes`)."""
    with (
        tempfile.TemporaryDirectory(prefix="bench-cp-") as tmp,
        ControlPlane(Path(tmp), settings=settings) as plane,
    ):
        _start_10_nodes(Cluster.of(plane))
        return _mb(plane)


def fleet_memory() -> list[Figure]:
    with tempfile.TemporaryDirectory(prefix="bench-cp-") as tmp:
        plane = ControlPlane(Path(tmp), settings=FLEET_SETTINGS)
        with plane:
            cluster = Cluster.of(plane)
            _start_10_nodes(cluster)
            rss_10 = _mb(plane)
            started = time.monotonic()
            cluster.wait_nodes_ready(_create_fleet(cluster, 10, 1000), timeout_s=900)
            _wait_agents_running(cluster, 1000, 900)
            fleet_ready_s = time.monotonic() - started
            time.sleep(SETTLE_S)
            rss_1000 = _mb(plane)
    note = "etcd+apiserver+controller-manager+scheduler+kwok, one DaemonSet pod per node"
    return [
        Figure("controlplane.rss_mb_10_nodes", rss_10, "MiB", "informational", COMMAND, note),
        Figure("controlplane.rss_mb_1000_nodes", rss_1000, "MiB", "informational", COMMAND, note),
        Figure(
            "controlplane.fleet_1000_ready_s",
            fleet_ready_s,
            "s",
            "informational",
            COMMAND,
            "990 nodes created (4 threads) until all Ready with their agent pod Running",
        ),
    ]


def run() -> list[Figure]:
    binaries.ensure_built()
    return [*cold_build(), warm_start(), *fleet_memory()]
