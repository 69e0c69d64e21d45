"""Nothing changes under a vehicle in the air: ``disruption.drain_refused_in_flight`` and
``disruption.pod_replacements_in_flight``.

On the local control plane with ``roost-operator`` running and a simulated Vehicle
(mavros and two SITL pods run by kwok on a fake node) with a RedundantAutopilot: the
agent's report says both autopilots are armed, the Vehicle's config changes (which
replaces its pods on the ground), and ``kubectl drain`` of its node runs (Eviction API,
10 s timeout), then one Eviction per pod for the refusal's reason; then the report says
disarmed and the node is drained again. The script is
:func:`tests.support.disruption.fly_change_and_drain`, which the integration test runs
too.

- ``disruption.drain_refused_in_flight``: 1 when the drain in flight was refused (a
  non-zero exit, and every eviction "would violate the pod's disruption budget") and the
  one after landing succeeded, else 0;
- ``disruption.pod_replacements_in_flight``: the vehicle's component pods replaced
  between the arm and the drain's end (the config change is deferred to the landing).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

from bench.core import Figure
from roost_kube.client import Kube
from roost_kube.resources import VEHICLES
from roost_localcluster import binaries
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane
from tests.support.disruption import fly_change_and_drain
from tests.support.fakeagents import redundant_autopilot
from tests.support.operator import OperatorProcess
from tests.support.waiting import wait_until

COMMAND = "python -m bench disruption"
NAMESPACE = "roost-bench"
VEHICLE = "bench-flying"


def _components_ready(kube: Kube) -> bool:
    conditions = ((kube.get(VEHICLES, VEHICLE) or {}).get("status") or {}).get("conditions", [])
    return any(c["type"] == "ComponentsReady" and c["status"] == "True" for c in conditions)


def run() -> list[Figure]:
    binaries.ensure_built()
    with (
        tempfile.TemporaryDirectory(prefix="bench-disruption-") as tmp,
        ControlPlane(Path(tmp)) as plane,
    ):
        cluster = Cluster.of(plane)
        cluster.install_crds()
        operator = OperatorProcess(cluster, Path(tmp) / "operator.log", namespace=NAMESPACE)
        operator.start()
        try:
            with cluster.kube("roost-bench") as kube:
                node = f"{VEHICLE}-node"
                cluster.add_node(node)
                ra = json.dumps(redundant_autopilot(VEHICLE))
                cluster.kubectl("apply", "-f", "-", input_text=ra)
                vehicle = {
                    "apiVersion": "roost.dev/v1alpha1",
                    "kind": "Vehicle",
                    "metadata": {"name": VEHICLE},
                    "spec": {"nodeName": node, "sysid": 10, "simulation": {"stack": "px4"}},
                }
                cluster.kubectl("apply", "-f", "-", input_text=json.dumps(vehicle))
                wait_until("components ready", lambda: _components_ready(kube), 60)
                outcome = fly_change_and_drain(
                    cluster, kube, vehicle=VEHICLE, node=node, namespace=NAMESPACE
                )
        finally:
            operator.stop()
    refused = outcome.drain_in_flight.returncode != 0 and all(
        "disruption budget" in answer for answer in outcome.evictions_in_flight.values()
    )
    proceeded = outcome.drain_after_landing.returncode == 0
    return [
        Figure(
            "disruption.drain_refused_in_flight",
            1 if refused and proceeded else 0,
            "",
            "== 1",
            COMMAND,
            f"kubectl drain of an armed vehicle's node refused (exit "
            f"{outcome.drain_in_flight.returncode}; every pod's eviction: disruption budget), "
            "the same drain after "
            f"the disarm report proceeded (exit {outcome.drain_after_landing.returncode})",
        ),
        Figure(
            "disruption.pod_replacements_in_flight",
            outcome.replacements_in_flight,
            "",
            "== 0",
            COMMAND,
            f"component pods replaced while armed after a config change and the drain; "
            f"deferred {outcome.deferred} ({outcome.hold_reason}), replaced after landing: "
            f"{outcome.replaced_after_landing}",
        ),
    ]
