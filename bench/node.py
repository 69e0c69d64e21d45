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

- ``node.arm64_agent_pod_to_first_report_s``: the same on an arm64 vehicle node (kubelet,
  containerd, shim, runc and CNI built for arm64, run under qemu-user-static; the agent
  pod from the image index's arm64 build), the ground node this machine's.
- ``agent.rss_mb_arm64``: peak RSS of that agent container's process over 30 s while it
  watches both autopilots, under emulation (qemu's translator and its code cache
  included: an upper bound for a real arm64 board).

The chart figures are one run of :class:`tests.support.realfleet.RealFleet`, the same
steps ``make e2e-node`` tests (``tests/e2e_node/test_arm64_node.py`` for arm64). Needs
root (namespaces, cgroups); elsewhere the module reports why and returns no figures.
``python -m bench nodearm64`` runs the arm64 part alone (:mod:`bench.nodearm64`).
"""

from __future__ import annotations

import contextlib
import csv
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import psutil

from bench.core import Figure
from roost_localcluster import binaries
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane
from roost_localcluster.nodenet import missing_prerequisites
from roost_localcluster.realnode import RealNodes
from tests.support.images import emulation_missing, missing_tools
from tests.support.realfleet import EMULATED_NODE_AGENT, RealFleet

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


ARM64_RSS_S = 30.0


def node_programs_rss_mb(fleet: RealFleet) -> dict[str, float]:
    """RSS of the vehicle node's own programs (kubelet, containerd, kube-proxy, the
    shims summed), in MB."""
    assert fleet.vehicle_node is not None
    found: dict[str, float] = {}
    for pid in fleet.vehicle_node.pids():
        with contextlib.suppress(psutil.Error):
            proc = psutil.Process(pid)
            line = " ".join(proc.cmdline())
            for name in ("containerd-shim-runc-v2", "kube-proxy", "kubelet", "containerd"):
                if f"/bin/{name} " in f"{line} ":
                    found[name] = round(found.get(name, 0.0) + proc.memory_info().rss / 1e6, 1)
                    break
    return found


def arm64_run(cluster: Cluster, directory: Path) -> list[Figure]:
    if reason := emulation_missing("arm64"):
        print(f"bench node: arm64 skipped ({reason})", file=sys.stderr)
        return []
    with RealNodes(cluster, directory / "arm64-nodes") as pool:
        fleet = RealFleet(
            cluster,
            pool,
            directory / "arm64-fleet",
            vehicle_arch="arm64",
            wait_s=600.0,
            agent_values=EMULATED_NODE_AGENT,
        )
        try:
            load_start = os.getloadavg()[0]
            fleet.start()
            load_reported = os.getloadavg()[0]
            programs = node_programs_rss_mb(fleet)
            peak, cpu_s = 0.0, 0.0
            proc = fleet.agent_process()
            if proc is not None:
                cpu0 = proc.cpu_times()
                deadline = time.monotonic() + ARM64_RSS_S
                while time.monotonic() < deadline:
                    peak = max(peak, proc.memory_info().rss / 1e6)
                    time.sleep(0.5)
                cpu1 = proc.cpu_times()
                cpu_s = (cpu1.user + cpu1.system) - (cpu0.user + cpu0.system)
            vehicle_ready_s = fleet.timings.vehicle_start_to_ready_s
        finally:
            fleet.stop()
    figures = [
        Figure(
            "node.arm64_agent_pod_to_first_report_s",
            fleet.timings.agent_pod_to_first_report_s,
            "s",
            "informational",
            COMMAND,
            note="arm64 vehicle node under qemu-user-static (its node start to Ready "
            f"{vehicle_ready_s:.1f} s): agent pod (arm64 image) created to its first report "
            f"of two simulated autopilots healthy; 1-min load {load_start:.1f} at the node's "
            f"start, {load_reported:.1f} at the first report",
        )
    ]
    if peak:
        figures.append(
            Figure(
                "agent.rss_mb_arm64",
                round(peak, 1),
                "MB",
                "informational",
                COMMAND,
                note=f"peak RSS over {ARM64_RSS_S:.0f} s of the arm64 agent container on the "
                "emulated vehicle node, two PX4 sims at onboard rates; includes qemu's "
                f"translator and code cache; CPU {100 * cpu_s / ARM64_RSS_S:.0f} % of a core; "
                f"the node's programs under emulation (RSS, MB): {programs}",
            )
        )
    return figures


Part = Callable[[Cluster, Path], list[Figure]]


def measure(parts: Sequence[Part]) -> list[Figure]:
    """Run ``parts`` in turn on one fresh control plane (skipped, saying why, without
    root or the image tools)."""
    reasons = missing_prerequisites() + [f"no {tool}" for tool in missing_tools()]
    if reasons:
        print(f"bench node: skipped ({'; '.join(reasons)})", file=sys.stderr)
        return []
    figures: list[Figure] = []
    with (
        tempfile.TemporaryDirectory(prefix="bench-node-") as tmp,
        ControlPlane(Path(tmp) / "control-plane") as plane,
    ):
        cluster = Cluster.of(plane)
        for part in parts:
            figures += part(cluster, Path(tmp))
    return figures


def run() -> list[Figure]:
    return cold_build() + measure(
        (lambda cluster, directory: [node_starts(cluster, directory)], chart_run, arm64_run)
    )
