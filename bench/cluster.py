"""Agent ↔ cluster figures: how fast a local switch shows in the API and reaches mavros.

One simulated vehicle on the local control plane: two PX4 sims flying (in this
process, real UDP), ``roost-agent`` as a process with the chart's defaults (no config,
``NODE_NAME``, 10 s report period), ``roost-operator`` as a process. The vehicle is
switched back and forth by ``Switch`` commands written to the RedundantAutopilot's spec;
each switch is a real bridge switch on the agent, reported by the same urgent write as an
automatic failover.

- ``cluster.switch_to_status_p99_ms``: from the agent's bridge switch (the wall-clock time
  of its ``Failover`` event, printed on its stdout) to the RedundantAutopilot status with
  the new ``activeAutopilot`` arriving on a watch held by this process — i.e. visible in
  the API to any client. p99 over the samples (with few samples, close to the maximum).
- ``cluster.switch_to_mavros_ms``: from the same bridge switch until the vehicle's mavros
  runs on the new autopilot: its config carries the new FCU URL, and the new mavros Pod
  (the operator deleted the old one first) carries that config and is Running and Ready
  (kwok playing the kubelet). The slowest of the samples. Polled every 50 ms.

Agent, operator, control plane and sims share this machine's two cores; the latch guard
is raised for the run (``ROOST_FAILOVER_LATCH_AFTER``) because the vehicle deliberately
switches many times within the latch window.
"""

from __future__ import annotations

import json
import statistics
import tempfile
import threading
import time
from datetime import datetime
from pathlib import Path
from typing import Any

from bench.core import Figure
from roost_api.autopilot import CommandAction
from roost_api.commands import command_patch, new_command
from roost_kube.client import Kube
from roost_kube.resources import CONFIGMAPS, PODS, REDUNDANT_AUTOPILOTS, VEHICLES
from roost_localcluster import binaries
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane
from roost_operator.vehicles.config import config_map_name
from roost_operator.vehicles.manifests import workload_name
from roost_operator.vehicles.pods import mavros_follows
from roost_sim import SimConfig, SimulatedAutopilot, autopilot_specs, start_vehicle_sims, stop_sims
from tests.support.agent import AgentProcess
from tests.support.operator import OperatorProcess
from tests.support.waiting import wait_until

COMMAND = "python -m bench cluster"
NAMESPACE = "roost-bench-failover"
VEHICLE = "bench-failover"
NODE = "bench-failover-node"
SWITCHES = 20
WAIT_S = 60.0


class StatusWatch:
    """Records when each new ``activeAutopilot`` of the RedundantAutopilot arrives."""

    def __init__(self, cluster: Cluster) -> None:
        self._kube = cluster.kube("roost-bench")
        self._stop = threading.Event()
        self.arrivals: list[tuple[float, str]] = []
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> StatusWatch:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=70)
        self._kube.close()

    def _run(self) -> None:
        last = None
        while not self._stop.is_set():
            for _, obj in self._kube.watch(REDUNDANT_AUTOPILOTS, VEHICLE, timeout_s=5):
                arrived = time.time()
                active = (obj.get("status") or {}).get("activeAutopilot")
                if active and active != last:
                    last = active
                    with self._lock:
                        self.arrivals.append((arrived, active))
                if self._stop.is_set():
                    break

    def first_after(self, since: float, active: str) -> float | None:
        with self._lock:
            return next((t for t, a in self.arrivals if t >= since and a == active), None)


def _fly(sims: list[SimulatedAutopilot]) -> None:
    for sim in sims:
        sim.wait_ready()
        sim.fly(altitude_m=5)
    for sim in sims:
        sim.wait_until(lambda s: s.landed_state == "InAir", timeout=30)


def _apply_vehicle(cluster: Cluster, sims: list[SimulatedAutopilot]) -> None:
    specs = [a.to_api() for a in autopilot_specs(sims)]
    manifests: list[dict[str, Any]] = [
        {
            "apiVersion": "roost.dev/v1alpha1",
            "kind": "Vehicle",
            "metadata": {"name": VEHICLE},
            "spec": {"nodeName": NODE, "sysid": 42},
        },
        {
            "apiVersion": "roost.dev/v1alpha1",
            "kind": "RedundantAutopilot",
            "metadata": {"name": VEHICLE},
            "spec": {"vehicleName": VEHICLE, "primary": "fc1", "autopilots": specs},
        },
    ]
    for manifest in manifests:
        cluster.kubectl("apply", "-f", "-", input_text=json.dumps(manifest))


def _mavros_on(kube: Kube, url: str) -> bool:
    config = kube.get(CONFIGMAPS, config_map_name(VEHICLE), NAMESPACE)
    mavros = kube.get(PODS, workload_name(VEHICLE, "mavros"), NAMESPACE)
    return mavros_follows(url, config, mavros)


def _ready(kube: Kube) -> bool:
    status = (kube.get(VEHICLES, VEHICLE) or {}).get("status") or {}
    return any(c["type"] == "Ready" and c["status"] == "True" for c in status.get("conditions", []))


def _new_switch(agent: AgentProcess, seen: int) -> float | None:
    """Wall-clock time of the agent's switch after the first ``seen`` (its event output)."""
    switches = agent.events("Failover")
    if len(switches) <= seen:
        return None
    return datetime.fromisoformat(switches[seen]["time"]).timestamp()


def _switch_once(
    kube: Kube, agent: AgentProcess, statuses: StatusWatch, target: SimulatedAutopilot
) -> tuple[float, float]:
    """Switch to ``target``; milliseconds from the bridge switch to status and to mavros."""
    before = len(agent.events("Failover"))
    command = new_command(CommandAction.SWITCH, target=target.name)
    kube.merge_patch(REDUNDANT_AUTOPILOTS, VEHICLE, command_patch(command))
    switched = wait_until("the switch", lambda: _new_switch(agent, before), WAIT_S, 0.01)
    seen = wait_until(
        "the status", lambda: statuses.first_after(switched, target.name), WAIT_S, 0.01
    )
    wait_until("mavros", lambda: _mavros_on(kube, target.connection), WAIT_S, 0.05)
    return (seen - switched) * 1000, (time.time() - switched) * 1000


def _measure(
    kube: Kube, agent: AgentProcess, sims: list[SimulatedAutopilot], statuses: StatusWatch
) -> tuple[list[float], list[float]]:
    to_status: list[float] = []
    to_mavros: list[float] = []
    for index in range(SWITCHES):
        status_ms, mavros_ms = _switch_once(kube, agent, statuses, sims[(index + 1) % 2])
        to_status.append(status_ms)
        to_mavros.append(mavros_ms)
        time.sleep(1.0)
    return to_status, to_mavros


def run() -> list[Figure]:
    binaries.ensure_built()
    with (
        tempfile.TemporaryDirectory(prefix="bench-cluster-") as tmp,
        ControlPlane(Path(tmp)) as plane,
    ):
        cluster = Cluster.of(plane)
        cluster.install_crds()
        cluster.add_node(NODE)
        operator = OperatorProcess(
            cluster,
            Path(tmp) / "operator.log",
            namespace=NAMESPACE,
            environment={"ROOST_FAILOVER_LATCH_AFTER": str(SWITCHES * 10)},
        )
        sims = start_vehicle_sims(["px4", "px4"], config=SimConfig.fast())
        agent = AgentProcess.in_cluster(cluster, NODE, Path(tmp) / "agent", report_interval_s=10.0)
        operator.start()
        try:
            _fly(sims)
            _apply_vehicle(cluster, sims)
            agent.start()
            with cluster.kube("roost-bench") as kube, StatusWatch(cluster) as statuses:
                wait_until("the vehicle Ready", lambda: _ready(kube), WAIT_S)
                to_status, to_mavros = _measure(kube, agent, sims, statuses)
        finally:
            agent.stop()
            operator.stop()
            stop_sims(sims)
    p99 = statistics.quantiles(to_status, n=100, method="inclusive")[98]
    return [
        Figure(
            "cluster.switch_to_status_p99_ms",
            round(p99, 1),
            "ms",
            "<= 200",
            COMMAND,
            note=f"{len(to_status)} switches; p50 {statistics.median(to_status):.1f} ms, "
            f"max {max(to_status):.1f} ms; bridge switch (agent event) to the status "
            "arriving on a watch",
        ),
        Figure(
            "cluster.switch_to_mavros_ms",
            round(max(to_mavros), 1),
            "ms",
            "<= 2000",
            COMMAND,
            note=f"slowest of {len(to_mavros)}; p50 {statistics.median(to_mavros):.1f} ms; "
            "bridge switch to the new mavros Pod Ready on the new FCU URL (50 ms polling)",
        ),
    ]
