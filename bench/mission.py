"""Mission figures, on the local control plane with ``roost-operator`` running.

- ``mission.rollout_10_s`` / ``mission.rollout_100_s``: from ``kubectl apply`` of a
  Mission needing 10 (then 100) vehicles of an idle, Ready fleet of 100 fake vehicles
  until every one of its onboard workloads is Running: vehicles claimed (one
  optimistic-concurrency write each), preflight passed, status written, one Job per
  vehicle created, scheduled onto the vehicle's node and started by kwok. kwok's default
  stages complete a Job's pod as soon as it runs, so a pod counts once it has reached
  Running or Succeeded. Polled every 100 ms.

The fleet's node agents are :class:`~tests.support.fakeagents.FakeAgents` reporting every
few seconds (the real agent reports every 10 s), so the operator's ``AgentConnected`` and
the preflight checks see live reports as they would in a fleet.

``ROOST_BENCH_MISSION_FLEET=1000`` runs the same on a fleet of 1,000 (the figure is then
``mission.rollout_100_of_1000_s``); its stand-in agents report every 20 s and the
operator calls a report stale after 60 s, as a fleet that size would be configured (1,000
agents at 10 s are 100 status writes a second on this 2-core machine's API server).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

from bench.controlplane import FLEET_SETTINGS
from bench.core import Figure
from roost_api.wellknown import LABEL_MISSION, LABEL_VEHICLE
from roost_kube.client import Kube
from roost_kube.resources import MISSIONS, PODS, VEHICLES
from roost_localcluster import binaries
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane, Settings
from roost_operator.missions.workloads import bounded_name
from tests.support.fakeagents import FakeAgents, redundant_autopilot
from tests.support.operator import OperatorProcess
from tests.support.waiting import wait_until

COMMAND = "python -m bench mission"
FLEET = int(os.environ.get("ROOST_BENCH_MISSION_FLEET", "100"))
BIG_FLEET = FLEET > 100
SIZES = (100,) if BIG_FLEET else (10, 100)
NAMESPACE = "roost-bench"
FLIGHTS = "bench-flights"
FLEET_LABEL = "bench-fleet"
AGENT_PERIOD_S = 20.0 if BIG_FLEET else 5.0
STALE_S = 60.0 if BIG_FLEET else 30.0
SETUP_TIMEOUT_S = 600.0
ROLLOUT_TIMEOUT_S = 300.0
STARTED_PHASES = frozenset({"Running", "Succeeded"})


def _documents(manifests: Sequence[Mapping[str, object]]) -> str:
    return "\n---\n".join(json.dumps(m) for m in manifests)


def _ready(kube: Kube) -> bool:
    vehicles = kube.list_objects(VEHICLES, labels={"fleet": FLEET_LABEL})
    return len(vehicles) == FLEET and all(
        any(
            c["type"] == "Ready" and c["status"] == "True"
            for c in (v.get("status") or {}).get("conditions", [])
        )
        for v in vehicles
    )


def _fleet(cluster: Cluster, kube: Kube, agents: FakeAgents) -> None:
    names = [f"bench-drone-{i:03d}" for i in range(FLEET)]
    for name in names:
        cluster.add_node(f"{name}-node", wait=False)
    cluster.wait_nodes_ready([f"{n}-node" for n in names], SETUP_TIMEOUT_S)
    vehicles = [
        {
            "apiVersion": "roost.dev/v1alpha1",
            "kind": "Vehicle",
            "metadata": {"name": name, "labels": {"fleet": FLEET_LABEL}},
            "spec": {
                "nodeName": f"{name}-node",
                "sysid": 10 + i % 240,  # MAVLink ids end at 255; vehicles never meet here
                "components": {"mavros": {"enabled": False}},
            },
        }
        for i, name in enumerate(names)
    ]
    for documents in ([redundant_autopilot(n) for n in names], vehicles):
        cluster.kubectl(
            "apply",
            "--server-side",
            "-f",
            "-",
            input_text=_documents(documents),
            timeout_s=SETUP_TIMEOUT_S,
        )
    for name in names:
        agents.add(name, name, f"{name}-node")
    wait_until("the fleet Ready", lambda: _ready(kube), SETUP_TIMEOUT_S, poll_s=1.0)


def _workloads_started(kube: Kube, mission: str) -> int:
    pods = kube.list_objects(PODS, namespace=FLIGHTS, labels={LABEL_MISSION: bounded_name(mission)})
    return len(
        {
            p["metadata"]["labels"][LABEL_VEHICLE]
            for p in pods
            if LABEL_VEHICLE in p["metadata"]["labels"]
            and (p.get("status") or {}).get("phase") in STARTED_PHASES
        }
    )


def _rollout(cluster: Cluster, kube: Kube, count: int) -> float:
    name = f"rollout-{count}"
    manifest = {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Mission",
        "metadata": {"name": name, "namespace": FLIGHTS},
        "spec": {
            "vehicles": {"selector": {"matchLabels": {"fleet": FLEET_LABEL}}, "count": count},
            "onboard": {
                "spec": {
                    "restartPolicy": "Never",
                    "containers": [{"name": "controller", "image": "example.org/controller:1"}],
                }
            },
        },
    }
    started = time.monotonic()
    cluster.kubectl("apply", "-f", "-", input_text=json.dumps(manifest))
    wait_until(
        f"{count} onboard workloads running",
        lambda: _workloads_started(kube, name) >= count,
        ROLLOUT_TIMEOUT_S,
        poll_s=0.1,
    )
    elapsed = time.monotonic() - started
    wait_until(
        f"mission {name} Succeeded",
        lambda: (
            ((kube.get(MISSIONS, name, FLIGHTS) or {}).get("status") or {}).get("phase")
            == "Succeeded"
        ),
        ROLLOUT_TIMEOUT_S,
    )
    wait_until(
        "the fleet released",
        lambda: (
            not any(
                (v.get("status") or {}).get("claimedBy")
                for v in kube.list_objects(VEHICLES, labels={"fleet": FLEET_LABEL})
            )
        ),
        ROLLOUT_TIMEOUT_S,
    )
    return elapsed


def run() -> list[Figure]:
    binaries.ensure_built()
    with (
        tempfile.TemporaryDirectory(prefix="bench-mission-") as tmp,
        ControlPlane(Path(tmp), settings=FLEET_SETTINGS if BIG_FLEET else Settings()) as plane,
    ):
        cluster = Cluster.of(plane)
        cluster.install_crds()
        cluster.kubectl("create", "namespace", FLIGHTS)
        operator = OperatorProcess(
            cluster,
            Path(tmp) / "operator.log",
            namespace=NAMESPACE,
            environment={"ROOST_AGENT_STALE_SECONDS": str(STALE_S)},
        )
        operator.start()
        try:
            with cluster.kube("roost-bench") as kube, FakeAgents(cluster, AGENT_PERIOD_S) as agents:
                _fleet(cluster, kube, agents)
                times = {count: _rollout(cluster, kube, count) for count in SIZES}
                load = os.getloadavg()[0]
        finally:
            operator.stop()
    targets = {10: "informational", 100: "<= 30"}
    suffix = f"_of_{FLEET}" if BIG_FLEET else ""
    return [
        Figure(
            f"mission.rollout_{count}{suffix}_s",
            seconds,
            "s",
            targets[count],
            COMMAND,
            note=f"apply → {count} onboard Jobs' pods Running, fleet of {FLEET} Ready fake "
            f"vehicles, stand-in agents reporting every {AGENT_PERIOD_S:.0f} s; 1-min load "
            f"average {load:.1f} on {os.cpu_count()} cores (the figure grows with the load: "
            "operator, API server and kwok share them)",
        )
        for count, seconds in times.items()
    ]
