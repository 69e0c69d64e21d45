"""The three Roost kinds and how Kubernetes presents them.

One :class:`ResourceKind` per kind ties the pydantic spec/status models to the names and
scope (:class:`roost_api.core.KindName`, which the node agent reads without pydantic),
short names, printer columns and whole-spec CEL rules the CRD carries. The CRD
generator, the operator's watches and the agent's API calls all read these, so a plural
or a group is spelled in exactly one place.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from roost_api.autopilot import (
    REDUNDANT_AUTOPILOT_ROOT_RULES,
    REDUNDANT_AUTOPILOT_RULES,
    RedundantAutopilotSpec,
    RedundantAutopilotStatus,
)
from roost_api.core import (
    CATEGORY,
    GROUP,
    MISSION_KIND,
    REDUNDANT_AUTOPILOT_KIND,
    VEHICLE_KIND,
    KindName,
)
from roost_api.meta import ApiModel
from roost_api.mission import MISSION_ROOT_RULES, MISSION_SPEC_RULES, MissionSpec, MissionStatus
from roost_api.vehicle import VEHICLE_ROOT_RULES, VehicleSpec, VehicleStatus


@dataclass(frozen=True)
class PrinterColumn:
    """One ``kubectl get`` column."""

    name: str
    json_path: str
    type: str = "string"
    priority: int = 0
    description: str = ""

    def to_crd(self) -> dict[str, Any]:
        column: dict[str, Any] = {"name": self.name, "type": self.type, "jsonPath": self.json_path}
        if self.priority:
            column["priority"] = self.priority
        if self.description:
            column["description"] = self.description
        return column


def _condition(type_: str) -> str:
    return f'.status.conditions[?(@.type=="{type_}")].status'


AGE = PrinterColumn("Age", ".metadata.creationTimestamp", "date")


@dataclass(frozen=True)
class ResourceKind:
    """A Roost custom resource kind."""

    name: KindName
    short_names: tuple[str, ...]
    description: str
    spec_model: type[ApiModel]
    status_model: type[ApiModel]
    columns: tuple[PrinterColumn, ...]
    spec_rules: tuple[dict[str, str], ...] = field(default=())
    root_rules: tuple[dict[str, str], ...] = field(default=())
    """Rules on the whole object, the only place CEL sees ``metadata.name``."""

    @property
    def kind(self) -> str:
        return self.name.kind

    @property
    def plural(self) -> str:
        return self.name.plural

    @property
    def scope(self) -> Literal["Cluster", "Namespaced"]:
        return self.name.scope

    @property
    def singular(self) -> str:
        return self.kind.lower()

    @property
    def crd_name(self) -> str:
        return f"{self.plural}.{GROUP}"

    @property
    def namespaced(self) -> bool:
        return self.name.namespaced

    @property
    def group(self) -> str:
        return self.name.group

    @property
    def version(self) -> str:
        return self.name.version

    @property
    def categories(self) -> tuple[str, ...]:
        return (CATEGORY,)


VEHICLE = ResourceKind(
    name=VEHICLE_KIND,
    short_names=("veh",),
    description="A drone of the fleet: one physical or simulated vehicle whose companion "
    "computer is a Kubernetes node. Roost labels the node, writes the vehicle's config and "
    "runs its component workloads (mavros, vicon, hardware, SITL).",
    spec_model=VehicleSpec,
    status_model=VehicleStatus,
    columns=(
        PrinterColumn("Node", ".spec.nodeName"),
        PrinterColumn("Sysid", ".spec.sysid", "integer"),
        PrinterColumn("Sim", ".spec.simulation.stack", description="SITL stack if simulated"),
        PrinterColumn("Ready", _condition("Ready")),
        PrinterColumn("Autopilots", _condition("AutopilotsHealthy"), priority=0),
        PrinterColumn("Active", ".status.activeAutopilot"),
        PrinterColumn("Mission", ".status.claimedBy.name"),
        PrinterColumn("Class", ".spec.vehicleClass", priority=1),
        PrinterColumn("Type", ".spec.vehicleType", priority=1),
        PrinterColumn("Reason", '.status.conditions[?(@.type=="Ready")].reason', priority=1),
        AGE,
    ),
    root_rules=tuple(VEHICLE_ROOT_RULES),
)

REDUNDANT_AUTOPILOT = ResourceKind(
    name=REDUNDANT_AUTOPILOT_KIND,
    short_names=("rap", "autopilots"),
    description="The redundant autopilots of one vehicle and its failover policy. The node "
    "agent on the vehicle writes the status: active autopilot, health of each, last "
    "failover.",
    spec_model=RedundantAutopilotSpec,
    status_model=RedundantAutopilotStatus,
    columns=(
        PrinterColumn("Vehicle", ".spec.vehicleName"),
        PrinterColumn("Primary", ".spec.primary"),
        PrinterColumn("Active", ".status.activeAutopilot"),
        PrinterColumn("Healthy", _condition("ActiveHealthy")),
        PrinterColumn("Redundant", _condition("Redundant")),
        PrinterColumn("Failovers", ".status.failoverCount", "integer"),
        PrinterColumn("Last-Failover", ".status.lastFailover.time", "date"),
        PrinterColumn("Reason", ".status.lastFailover.reason", priority=1),
        PrinterColumn("Latency-ms", ".status.lastFailover.latencyMs", "number", priority=1),
        AGE,
    ),
    spec_rules=tuple(REDUNDANT_AUTOPILOT_RULES),
    root_rules=tuple(REDUNDANT_AUTOPILOT_ROOT_RULES),
)

MISSION = ResourceKind(
    name=MISSION_KIND,
    short_names=("msn",),
    description="What to fly: which vehicles, the onboard workload run on each, an optional "
    "offboard workload, preflight checks, failover policy and abort.",
    spec_model=MissionSpec,
    status_model=MissionStatus,
    columns=(
        PrinterColumn("Phase", ".status.phase"),
        PrinterColumn("Assigned", ".status.assignedCount", "integer"),
        PrinterColumn("Required", ".spec.vehicles.count", "integer"),
        PrinterColumn("Degraded", _condition("Degraded")),
        PrinterColumn("Reason", ".status.reason", priority=1),
        AGE,
    ),
    spec_rules=tuple(MISSION_SPEC_RULES),
    root_rules=tuple(MISSION_ROOT_RULES),
)

KINDS: tuple[ResourceKind, ...] = (VEHICLE, REDUNDANT_AUTOPILOT, MISSION)
