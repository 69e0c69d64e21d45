"""Vehicle operator figures, on the local control plane with ``roost-operator`` running.

- ``vehicle.apply_to_ready_s``: from ``kubectl apply`` of a simulated Vehicle (mavros and
  one SITL) on a fresh fake node until its ``Ready`` condition is True: node labelled and
  tainted, ConfigMap written, both component Pods created on the node, "run" by kwok
  and Ready.
  Median over several vehicles applied one after another; the readiness poll runs every
  50 ms, so the figure is at most that much late.
- ``vehicle.idle_writes_per_min``: API write requests (counted by the API server itself,
  ``apiserver_request_total``, so no-op writes count too) to everything the operator
  writes for vehicles, per vehicle per minute, over a window in which nothing changes.
  The operator resyncs every vehicle every 10 s during the window (six resyncs), so the
  figure covers the periodic path as well as event-driven ones (node heartbeats).
"""

from __future__ import annotations

import json
import statistics
import tempfile
import time
from pathlib import Path

from bench.core import Figure
from roost_kube.client import Kube
from roost_kube.resources import VEHICLES
from roost_localcluster import binaries
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane
from tests.support.apiwrites import VEHICLE_WRITE_TARGETS, write_requests
from tests.support.operator import OperatorProcess
from tests.support.waiting import wait_until

COMMAND = "python -m bench vehicle"
VEHICLE_COUNT = 5
RESYNC_S = 10
IDLE_WINDOW_S = 60.0
SETTLE_S = 5.0
READY_TIMEOUT_S = 60.0
NAMESPACE = "roost-bench"


def _is_ready(kube: Kube, name: str) -> bool:
    status = (kube.get(VEHICLES, name) or {}).get("status") or {}
    return any(c["type"] == "Ready" and c["status"] == "True" for c in status.get("conditions", []))


def _apply_to_ready(cluster: Cluster, kube: Kube, name: str, sysid: int) -> float:
    node = f"{name}-node"
    cluster.add_node(node)
    manifest = {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Vehicle",
        "metadata": {"name": name},
        "spec": {"nodeName": node, "sysid": sysid, "simulation": {"stack": "px4"}},
    }
    started = time.monotonic()
    cluster.kubectl("apply", "-f", "-", input_text=json.dumps(manifest))
    wait_until(f"{name} Ready", lambda: _is_ready(kube, name), READY_TIMEOUT_S, poll_s=0.05)
    return time.monotonic() - started


def run() -> list[Figure]:
    binaries.ensure_built()
    with (
        tempfile.TemporaryDirectory(prefix="bench-vehicle-") as tmp,
        ControlPlane(Path(tmp)) as plane,
    ):
        cluster = Cluster.of(plane)
        cluster.install_crds()
        operator = OperatorProcess(
            cluster,
            Path(tmp) / "operator.log",
            namespace=NAMESPACE,
            environment={"ROOST_RESYNC_SECONDS": str(RESYNC_S)},
        )
        operator.start()
        try:
            with cluster.kube("roost-bench") as kube:
                times = [
                    _apply_to_ready(cluster, kube, f"bench-vehicle-{i}", 10 + i)
                    for i in range(VEHICLE_COUNT)
                ]
                time.sleep(SETTLE_S)
                before = write_requests(cluster, VEHICLE_WRITE_TARGETS)
                time.sleep(IDLE_WINDOW_S)
                writes = write_requests(cluster, VEHICLE_WRITE_TARGETS) - before
        finally:
            operator.stop()
    per_vehicle_per_min = writes / VEHICLE_COUNT / (IDLE_WINDOW_S / 60.0)
    return [
        Figure(
            "vehicle.apply_to_ready_s",
            statistics.median(times),
            "s",
            "<= 5",
            COMMAND,
            note=f"median of {VEHICLE_COUNT} simulated vehicles (mavros + 1 SITL): "
            f"{[round(t, 2) for t in times]}",
        ),
        Figure(
            "vehicle.idle_writes_per_min",
            per_vehicle_per_min,
            "1/min",
            "== 0",
            COMMAND,
            note=f"{writes} write requests to vehicles, vehicles/status, nodes, configmaps, "
            f"pods, events in {IDLE_WINDOW_S:.0f} s with {VEHICLE_COUNT} idle vehicles, "
            f"resync every {RESYNC_S} s",
        ),
    ]
