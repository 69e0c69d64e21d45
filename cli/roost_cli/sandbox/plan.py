"""The sandbox fleet on paper: names, system ids, ports and the manifests to apply.

Pure, so what the sandbox applies is unit-tested against the API models without a
cluster. Vehicles alternate PX4 and ArduPilot so both stacks' conventions are on screen;
each has two simulated autopilots of its stack behind a simulated bridge.

No port is chosen here. Fixed SITL ports (:mod:`roost_api.sitl`, 14540 + i) would
collide with other people's tests and sandboxes on the same machine, and a port found free
by binding and closing a socket can be taken by any process before its user binds it (a
simulator's own ephemeral socket once took an agent's port). So each simulator binds a
free port itself and reports it as its connection URL (``udpout://127.0.0.1:P``: the agent
sends to the simulator, which answers whoever writes to it), and the RedundantAutopilot
is written from those reports (:func:`autopilot_manifest`). The agents' MAVLink hubs are
the exception: a client (a mission's follower, MAVProxy) must know where to connect before
the agent starts, so :func:`hub_ports` picks them below the kernel's ephemeral range, where
no program is ever given a port it did not ask for. System ids do follow
:func:`roost_api.sitl.sitl_instance` (one global numbering, ``instance + 1``) so no two
autopilots of the sandbox ever share one.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from roost_api.autopilot import Thresholds
from roost_api.meta import API_VERSION, Stack
from roost_api.resources import MISSION, REDUNDANT_AUTOPILOT, VEHICLE
from roost_api.sitl import sitl_instance
from roost_api.vehicle import MAX_SIM_INSTANCE
from roost_cli.sandbox.kwok import RUNTIME_ANNOTATION

MAX_VEHICLES = 25
"""Two cores run an agent and two simulated autopilots per vehicle next to a control
plane and the operator: 25 vehicles are 50 autopilots at PX4's onboard rates (about
21,000 MAVLink messages a second) on this size of machine."""
AUTOPILOTS_PER_VEHICLE = 2
FLEET_LABEL = "fleet"
FLEET_VALUE = "sandbox"
MISSION_NAME = "survey"
MISSION_NAMESPACE = "default"
VEHICLE_SYSID_BASE = 10
"""Vehicle ids start at Starling's lowest VEHICLE_MAVLINK_SYSID."""
HOLD_SECONDS = 3.0
SIM_THRESHOLDS = {"messageErrorMinMs": Thresholds().message_error_ms}
"""The sandbox's autopilots are simulators sharing the machine's cores (ten vehicles to a
process and thread) with the control plane and every agent, not firmware on MCUs of their
own: they stall for tens of milliseconds, which the silence threshold learnt from their
steady streams (60 ms floor by default) would call silent. Their RedundantAutopilots
fix the threshold at the 200 ms ceiling instead (floor = ceiling); real vehicles keep
the learnt default (docs/health-model.md, "Tuning per airframe")."""
MISSION_RUNTIME = "10m"
"""How long kwok lets each onboard pod run: long enough to watch a failover mid-mission."""
HUB_HOST = "127.0.0.1"
HUB_PORT_BASE = 24550
"""First port tried for the agents' hubs: 14550 (MAVLink's ground-station port) + 10000,
clear of real SITLs and ground stations, and below Linux's ephemeral range (32768+);
:data:`roost_api.ports.RESERVED` keeps the ports tests pick for their programs off them."""
STACK_SHORT_NAMES = {Stack.PX4: "px4", Stack.ARDUPILOT: "apm"}
_STACK_ORDER = (Stack.PX4, Stack.ARDUPILOT)


@dataclass(frozen=True)
class AutopilotPlan:
    """One simulated autopilot of a sandbox vehicle."""

    name: str
    stack: Stack
    sysid: int
    bridge_channel: int


@dataclass(frozen=True)
class VehiclePlan:
    """One sandbox vehicle: a fake node of the same name, its autopilots, its identity."""

    name: str
    index: int
    stack: Stack
    sysid: int
    autopilots: tuple[AutopilotPlan, ...]

    @property
    def node(self) -> str:
        return self.name

    @property
    def primary(self) -> AutopilotPlan:
        return self.autopilots[0]


def plan_fleet(count: int) -> tuple[VehiclePlan, ...]:
    """``count`` vehicles ``drone-1`` …"""
    if not 1 <= count <= MAX_VEHICLES:
        raise ValueError(f"the sandbox runs 1 to {MAX_VEHICLES} vehicles, not {count}")
    fleet = []
    for index in range(count):
        stack = _STACK_ORDER[index % len(_STACK_ORDER)]
        autopilots = tuple(
            AutopilotPlan(
                name=f"{STACK_SHORT_NAMES[stack]}-{'abcdefgh'[slot]}",
                stack=stack,
                sysid=sitl_instance(index, slot, AUTOPILOTS_PER_VEHICLE) + 1,
                bridge_channel=slot,
            )
            for slot in range(AUTOPILOTS_PER_VEHICLE)
        )
        fleet.append(
            VehiclePlan(
                name=f"drone-{index + 1}",
                index=index,
                stack=stack,
                sysid=VEHICLE_SYSID_BASE + index,
                autopilots=autopilots,
            )
        )
    return tuple(fleet)


def vehicle_manifest(vehicle: VehiclePlan) -> dict[str, Any]:
    """A simulated Vehicle on its own node, labelled so the sandbox Mission selects it."""
    return {
        "apiVersion": API_VERSION,
        "kind": VEHICLE.kind,
        "metadata": {"name": vehicle.name, "labels": {FLEET_LABEL: FLEET_VALUE}},
        "spec": {
            "nodeName": vehicle.node,
            "sysid": vehicle.sysid,
            # The SITL instance is an offset on the vehicle's node, and every sandbox
            # vehicle has a node of its own; it only has to stay in the API's range.
            "simulation": {
                "stack": vehicle.stack.value,
                "instance": vehicle.index % (MAX_SIM_INSTANCE + 1),
            },
        },
    }


def hub_ports(count: int, is_free: Callable[[int], bool], below: int) -> tuple[int, ...]:
    """``count`` ports from :data:`HUB_PORT_BASE` up that ``is_free`` accepts, each below
    ``below`` (the first port the kernel hands out by itself), or ValueError."""
    found: list[int] = []
    for port in range(HUB_PORT_BASE, below):
        if len(found) == count:
            break
        if is_free(port):
            found.append(port)
    if len(found) < count:
        raise ValueError(
            f"no {count} free UDP ports on {HUB_HOST} between {HUB_PORT_BASE} and {below} "
            "for the agents' MAVLink hubs"
        )
    return tuple(found)


def autopilot_manifest(
    vehicle: VehiclePlan, connections: Mapping[str, str], hub: str | None = None
) -> dict[str, Any]:
    """Its RedundantAutopilot: automatic failover, hold then land, manual failback.

    ``connections``: autopilot name → the connection URL its simulator reported; ``hub``:
    ``HOST:PORT`` where the agent serves the vehicle's MAVLink endpoint (clients stay
    connected there across a failover).
    """
    manifest: dict[str, Any] = {
        "apiVersion": API_VERSION,
        "kind": REDUNDANT_AUTOPILOT.kind,
        "metadata": {"name": vehicle.name},
        "spec": {
            "vehicleName": vehicle.name,
            "primary": vehicle.primary.name,
            "autopilots": [
                {
                    "name": autopilot.name,
                    "stack": autopilot.stack.value,
                    "connection": connections[autopilot.name],
                    "sysid": autopilot.sysid,
                    "bridgeChannel": autopilot.bridge_channel,
                }
                for autopilot in vehicle.autopilots
            ],
            "failoverPolicy": {
                "mode": "Automatic",
                "safetyRoutine": {"holdSeconds": HOLD_SECONDS, "finalAction": "Land"},
                "failback": "Manual",
                "thresholds": dict(SIM_THRESHOLDS),
            },
        },
    }
    if hub is not None:
        # Clients see the primary autopilot's sysid (the hub's default): Vehicle sysids
        # (10 + index) and autopilot sysids (SITL numbering) overlap from the tenth vehicle.
        manifest["spec"]["hub"] = {"udp": hub}
    return manifest


def mission_manifest(count: int) -> dict[str, Any]:
    """A Mission flying every sandbox vehicle; a vehicle that fails over lands, the rest go on.

    The onboard image is never pulled: kwok plays the kubelet and reports the pods
    Running, then (after :data:`MISSION_RUNTIME`, see :mod:`.kwok`) Succeeded, which is
    all the operator observes.
    """
    return {
        "apiVersion": API_VERSION,
        "kind": MISSION.kind,
        "metadata": {"name": MISSION_NAME, "namespace": MISSION_NAMESPACE},
        "spec": {
            "vehicles": {
                "selector": {"matchLabels": {FLEET_LABEL: FLEET_VALUE}},
                "count": count,
            },
            "onFailover": "AbortVehicle",
            "preflight": {"requireRedundancy": True},
            "onboard": {
                "metadata": {
                    "labels": {"app": "survey-controller"},
                    "annotations": {RUNTIME_ANNOTATION: MISSION_RUNTIME},
                },
                "spec": {
                    "restartPolicy": "Never",
                    "containers": [
                        {
                            "name": "controller",
                            "image": "roost.dev/sandbox/survey-controller:demo",
                            "command": ["fly-survey"],
                            "resources": {"requests": {"cpu": "100m", "memory": "64Mi"}},
                        }
                    ],
                },
            },
        },
    }
