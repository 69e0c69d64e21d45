"""A test's vehicles and Missions on the session cluster, with fake agents and kwok nodes.

Shared by the modules that run Missions against ``roost-operator`` as a process
(:mod:`tests.integration.test_mission_operator` explains the stand-ins). Every test
uses unique names and its own vehicle label; Missions live in :data:`FLIGHTS` and go
before their Vehicles (their finalizers need the operator).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from roost_api.wellknown import LABEL_MISSION, LABEL_VEHICLE
from roost_kube.client import Kube
from roost_kube.patches import Obj
from roost_kube.resources import MISSIONS, PODS, VEHICLES
from roost_localcluster.cluster import Cluster
from roost_operator.missions.workloads import bounded_name
from tests.support.fakeagents import FakeAgents, redundant_autopilot
from tests.support.waiting import unique, wait_until

FLIGHTS = "roost-it-flights"
WAIT_S = 60.0
HOLD_GATE = "roost.dev/test-hold"
AddNode = Callable[..., dict[str, Any]]


@dataclass
class Fleet:
    """Vehicles of one test: nodes, Vehicles and RedundantAutopilots under one label."""

    cluster: Cluster
    kube: Kube
    agents: FakeAgents
    add_node: AddNode
    label: str = field(default_factory=lambda: unique("fleet"))
    vehicles: list[str] = field(default_factory=list)
    missions: list[str] = field(default_factory=list)

    def add(self, count: int, **agent_state: Any) -> list[str]:
        names = []
        for _ in range(count):
            name = unique("drone")
            node = f"{name}-node"
            self.add_node(node)
            self.apply(
                {
                    "apiVersion": "roost.dev/v1alpha1",
                    "kind": "Vehicle",
                    "metadata": {"name": name, "labels": {"fleet": self.label}},
                    "spec": {
                        "nodeName": node,
                        "sysid": 10 + len(self.vehicles),
                        "components": {"mavros": {"enabled": False}},
                    },
                }
            )
            self.apply(redundant_autopilot(name))
            self.agents.add(name, name, node, **agent_state)
            self.vehicles.append(name)
            names.append(name)
        wait_until(
            "the Vehicles Ready", lambda: all(vehicle_ready(self.kube, n) for n in names), WAIT_S
        )
        return names

    def apply(self, manifest: Obj) -> None:
        self.cluster.kubectl("apply", "-f", "-", input_text=json.dumps(manifest))

    def mission(self, name: str, **spec: Any) -> str:
        self.missions.append(name)
        self.apply(mission_manifest(name, **spec))
        return name

    def cleanup(self) -> None:
        for name in self.missions:
            self.cluster.kubectl("delete", "mission", name, "-n", FLIGHTS, "--ignore-not-found")
        for name in self.vehicles:
            self.agents.forget(name)
            self.cluster.kubectl("delete", "redundantautopilot", name, check=False)
            self.cluster.kubectl("delete", "vehicle", name, "--ignore-not-found", "--wait=false")
        wait_until(
            "the test's Vehicles to be gone",
            lambda: all(self.kube.get(VEHICLES, n) is None for n in self.vehicles),
            WAIT_S,
        )


def mission_manifest(
    name: str,
    *,
    selector: dict[str, str] | None = None,
    names: list[str] | None = None,
    count: int,
    hold: bool = True,
    offboard: bool = False,
    **spec: Any,
) -> Obj:
    vehicles: Obj = {"count": count}
    if selector is not None:
        vehicles["selector"] = {"matchLabels": selector}
    if names is not None:
        vehicles["names"] = names
    pod: Obj = {
        "restartPolicy": "Never",
        "containers": [{"name": "controller", "image": "example.org/controller:1"}],
    }
    if hold:
        pod["schedulingGates"] = [{"name": HOLD_GATE}]
    body: Obj = {
        "vehicles": vehicles,
        "onboard": {"metadata": {"labels": {"app": "controller"}}, "spec": pod},
        **spec,
    }
    if offboard:
        body["offboard"] = {
            "spec": {
                "restartPolicy": "Never",
                "containers": [{"name": "monitor", "image": "example.org/monitor:1"}],
            }
        }
    return {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Mission",
        "metadata": {"name": name, "namespace": FLIGHTS},
        "spec": body,
    }


def vehicle_condition(kube: Kube, name: str, type_: str) -> str | None:
    """The status of the Vehicle's condition ``type_`` (None when it has none)."""
    body = kube.get(VEHICLES, name) or {}
    conditions = (body.get("status") or {}).get("conditions") or []
    return next((c["status"] for c in conditions if c["type"] == type_), None)


def vehicle_ready(kube: Kube, name: str) -> bool:
    return vehicle_condition(kube, name, "Ready") == "True"


def mission_status(kube: Kube, name: str) -> Obj:
    body = kube.get(MISSIONS, name, FLIGHTS) or {}
    status: Obj = body.get("status") or {}
    return status


def wait_phase(kube: Kube, name: str, phase: str, timeout_s: float = WAIT_S) -> Obj:
    def reached() -> Obj | None:
        status = mission_status(kube, name)
        return status if status.get("phase") == phase else None

    try:
        result: Obj = wait_until(f"mission {name} phase {phase}", reached, timeout_s)
    except TimeoutError as error:
        status = json.dumps(mission_status(kube, name))
        raise AssertionError(f"{error}; status now: {status}") from error
    return result


def pods_of(kube: Kube, mission: str) -> list[Obj]:
    return [
        p
        for p in kube.list_objects(
            PODS, namespace=FLIGHTS, labels={LABEL_MISSION: bounded_name(mission)}
        )
        if not p["metadata"].get("deletionTimestamp")
    ]


def release_holds(kube: Kube, mission: str, vehicle: str | None = None) -> None:
    """Remove the scheduling gates: the pods get scheduled, kwok runs and completes them."""
    for pod in pods_of(kube, mission):
        if vehicle is not None and pod["metadata"]["labels"].get(LABEL_VEHICLE) != vehicle:
            continue
        if pod["spec"].get("schedulingGates"):
            kube.merge_patch(
                PODS,
                pod["metadata"]["name"],
                {"spec": {"schedulingGates": None}},
                namespace=FLIGHTS,
            )
