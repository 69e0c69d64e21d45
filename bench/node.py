"""Real harness nodes (kubelet + containerd + CNI) and the chart's real pods on them.

- ``node.cold_build_s``: the sum of the build times ``build-node.sh`` recorded in
  ``build-times.tsv`` beside the node programs (kubelet, kube-proxy, containerd, ctr, the
  runc shim, four CNI plugins, the pause image). Read from the record, never triggered.
- ``node.start_to_ready_s``: median of three node starts with the programs cached, from
  nothing (network namespace, certificates, containerd, pause image import, kubelet,
  kube-proxy) to the Node Ready, on a running control plane.
- ``chart.install_to_operator_ready_s``: ``helm install`` of charts/roost (images imported
  on the nodes, IfNotPresent) until the operator Deployment has an available pod.
- ``chart.agent_pod_to_first_report_s``: from the agent DaemonSet pod appearing on the
  vehicle node (the operator labelled the node from the Vehicle) to the agent's first
  report of both simulated autopilots healthy in the RedundantAutopilot status.

The chart figures are one run of :class:`tests.support.realfleet.RealFleet`, the same
steps ``make e2e-node`` tests. Needs root (namespaces, cgroups); elsewhere the module
reports why and returns no figures.
"""

from __future__ import annotations

import csv
import statistics
import sys
import tempfile
import time
from pathlib import Path

from bench.core import Figure
from roost_localcluster import binaries
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane
from roost_localcluster.nodenet import missing_prerequisites
from roost_localcluster.realnode import RealNodes
from tests.support.images import missing_tools
from tests.support.realfleet import RealFleet

COMMAND = "python -m bench node"
_PROGRAMS = (*binaries.NODE_BINARIES, *binaries.CNI_PLUGINS, "pause-image")


def cold_build() -> list[Figure]:
    record = binaries.node_dir() / "build-times.tsv"
    if not record.exists():
        return []
    latest: dict[str, int] = {}
    with record.open() as f:
        for name, seconds, _when in csv.reader(f, delimiter="\t"):
            latest[name] = int(seconds)
    if not set(_PROGRAMS) <= set(latest):
        return []
    shown = {name: latest[name] for name in _PROGRAMS}
    return [
        Figure(
            "node.cold_build_s",
            float(sum(shown.values())),
            "s",
            "informational",
            "localcluster/build-node.sh (empty cache)",
            note=f"per program {shown} ({record.name}); the Go modules shared with the "
            "control plane were already downloaded",
        )
    ]


def node_starts(cluster: Cluster, directory: Path) -> Figure:
    times = []
    with RealNodes(cluster, directory / "nodes") as pool:
        for attempt in range(3):
            started = time.monotonic()
            pool.add(f"bench-node-{attempt}")
            times.append(time.monotonic() - started)
            pool.remove(f"bench-node-{attempt}")
    return Figure(
        "node.start_to_ready_s",
        statistics.median(times),
        "s",
        "<= 30",
        COMMAND,
        note=f"median of {len(times)} starts {[round(t, 2) for t in times]}: netns, "
        "certificates, containerd, pause image import, kubelet and kube-proxy to Node Ready",
    )


def chart_run(cluster: Cluster, directory: Path) -> list[Figure]:
    with RealNodes(cluster, directory / "fleet-nodes") as pool:
        fleet = RealFleet(cluster, pool, directory / "fleet")
        try:
            fleet.start()
        finally:
            fleet.stop()
    timings = fleet.timings
    return [
        Figure(
            "chart.install_to_operator_ready_s",
            timings.install_to_operator_ready_s,
            "s",
            "<= 60",
            COMMAND,
            note="helm install (images imported, IfNotPresent) to the operator Deployment "
            "available on a real ground node",
        ),
        Figure(
            "chart.agent_pod_to_first_report_s",
            timings.agent_pod_to_first_report_s,
            "s",
            "<= 30",
            COMMAND,
            note="agent DaemonSet pod created on the real vehicle node to its first report "
            "of two simulated autopilots healthy",
        ),
    ]


def run() -> list[Figure]:
    figures = cold_build()
    reasons = missing_prerequisites() + [f"no {tool}" for tool in missing_tools()]
    if reasons:
        print(f"bench node: skipped ({'; '.join(reasons)})", file=sys.stderr)
        return figures
    with (
        tempfile.TemporaryDirectory(prefix="bench-node-") as tmp,
        ControlPlane(Path(tmp) / "control-plane") as plane,
    ):
        cluster = Cluster.of(plane)
        figures.append(node_starts(cluster, Path(tmp)))
        figures += chart_run(cluster, Path(tmp))
    return figures
