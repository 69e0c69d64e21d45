"""The Vehicle resource: one physical or simulated drone bound to one Kubernetes node.

Replaces Starling's host file ``/etc/starling/vehicle.config`` and its hand-set node
labels with a declared object. The operator derives node labels, the per-vehicle config
and the component workloads from it; the status says whether all of that is in place.
"""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from typing import Annotated

from pydantic import Field

from roost_api import shapes
from roost_api.meta import (
    CONDITIONS_SCHEMA,
    DNS_SUBDOMAIN_PATTERN,
    ApiModel,
    Condition,
    ObjectReference,
    Stack,
)

# SITL instances per node: each vehicle instance takes DEFAULT_SLOTS_PER_VEHICLE (4)
# consecutive global instances and PX4's port ranges allow 40 (roost_api.sitl).
MAX_SIM_INSTANCE = 9

Image = Annotated[
    str,
    Field(
        min_length=1,
        max_length=shapes.IMAGE_MAX,
        pattern=shapes.IMAGE_PATTERN,
        description="A container image reference (no whitespace).",
    ),
]
ConfigValue = Annotated[
    str,
    Field(
        max_length=shapes.CONFIG_VALUE_MAX,
        json_schema_extra=shapes.validations(shapes.ONE_LINE_RULES),
    ),
]


# On the whole object: metadata.name is only visible to CEL from the root.
VEHICLE_ROOT_RULES = [
    shapes.rule(
        f"size(self.metadata.name) <= {shapes.VEHICLE_NAME_MAX}",
        f"metadata.name: a Vehicle name is at most {shapes.VEHICLE_NAME_MAX} characters, "
        "because Roost writes it as a label value (roost.dev/vehicle) on its node, "
        "workloads and ConfigMaps",
    )
]


class VehicleConditionType(StrEnum):
    """Condition types on a Vehicle; all written by the operator."""

    READY = "Ready"
    NODE_BOUND = "NodeBound"
    COMPONENTS_READY = "ComponentsReady"
    AUTOPILOTS_HEALTHY = "AutopilotsHealthy"
    AGENT_CONNECTED = "AgentConnected"


class VehicleConditionReason(StrEnum):
    """Reasons of the Vehicle's conditions (written by the operator).

    ``AutopilotsHealthy`` False for another cause carries the RedundantAutopilot's
    ``Ready`` reason (:class:`~roost_api.autopilot.AutopilotConditionReason`), and ``Ready``
    the reason of its first input condition that is not True.
    """

    # NodeBound
    INVALID_VEHICLE_NAME = "InvalidVehicleName"
    NODE_CLAIMED_BY_OTHER_VEHICLE = "NodeClaimedByOtherVehicle"
    NODE_NOT_FOUND = "NodeNotFound"
    NODE_NOT_READY = "NodeNotReady"
    NODE_UNREACHABLE = "NodeUnreachable"
    NODE_LABELED = "NodeLabeled"
    NODE_REFUSED = "NodeRefused"
    AUTOPILOT_LABEL_REFUSED = "AutopilotLabelRefused"
    # ComponentsReady
    CONFIG_REFUSED = "ConfigRefused"
    WAITING_FOR_NODE = "WaitingForNode"
    NO_COMPONENTS = "NoComponents"
    ALL_COMPONENTS_READY = "AllComponentsReady"
    COMPONENTS_NOT_READY = "ComponentsNotReady"
    # AgentConnected
    NEVER_REPORTED = "NeverReported"
    REPORT_FROM_OTHER_NODE = "ReportFromOtherNode"
    REPORTS_STALE = "ReportsStale"
    REPORTING = "Reporting"
    # AutopilotsHealthy
    AGENT_NOT_CONNECTED = "AgentNotConnected"
    REDUNDANT = "Redundant"
    ACTIVE_HEALTH_UNKNOWN = "ActiveHealthUnknown"
    ACTIVE_UNHEALTHY = "ActiveUnhealthy"
    FAILED_OVER = "FailedOver"
    NOT_REDUNDANT = "NotRedundant"
    REDUNDANCY_UNKNOWN = "RedundancyUnknown"
    READY_UNKNOWN = "ReadyUnknown"
    # Ready
    AGENT_NOT_HEARD_YET = "AgentNotHeardYet"
    VEHICLE_READY = "VehicleReady"


class FailoverGuard(StrEnum):
    """Whether a cluster-side failover action may start now, and if not, which guard holds it."""

    ALLOWED = "Allowed"
    PAUSED = "Paused"
    LATCHED = "Latched"
    CONCURRENCY_LIMIT = "ConcurrencyLimit"


class FailoverActionKind(StrEnum):
    """A cluster-side failover action (``failover.action.kind``)."""

    REPOINT_MAVROS = "RepointMavros"


class ComponentSpec(ApiModel):
    """One component workload the operator runs on the vehicle's node."""

    enabled: bool = Field(description="Run this component on the vehicle.")
    image: Image | None = Field(
        default=None,
        description="Container image overriding Roost's default for this component.",
    )


class Components(ApiModel):
    """Which component workloads run on the vehicle, with optional image overrides."""

    mavros: ComponentSpec = Field(
        default_factory=lambda: ComponentSpec(enabled=True),
        description="MAVLink-to-ROS bridge, pointed at the active autopilot.",
    )
    vicon: ComponentSpec = Field(
        default_factory=lambda: ComponentSpec(enabled=False),
        description="Motion-capture bridge publishing the vehicle's pose.",
    )
    hardware: ComponentSpec = Field(
        default_factory=lambda: ComponentSpec(enabled=False),
        description="Hardware drivers (camera, payload) needing device access on the node.",
    )
    signing_keys: ComponentSpec = Field(
        default_factory=lambda: ComponentSpec(enabled=False),
        description="Hands the vehicle's MAVLink signing key (Secret roost-signing-<vehicle>, "
        "from `roost keys create`) to the node agent on this vehicle's node only: a small "
        "pod of the agent image on the node mounts that one Secret and writes the key to "
        "/var/lib/roost/signing/<vehicle>/ on the node. Enable it for every vehicle whose "
        "agent signs (docs/mavlink-signing.md). The image defaults to the Roost agent's.",
    )


class Simulation(ApiModel):
    """Present when the vehicle is simulated: the operator runs one SITL per autopilot."""

    stack: Stack = Field(description="SITL flight stack to run: px4 or ardupilot.")
    image: Image | None = Field(default=None, description="SITL container image override.")
    instance: int = Field(
        default=0,
        ge=0,
        le=MAX_SIM_INSTANCE,
        description="SITL instance offset on the node; ports and sysids derive from it.",
    )


class VehicleSpec(ApiModel):
    """Desired state of a Vehicle."""

    node_name: str = Field(
        min_length=1,
        max_length=shapes.NODE_NAME_MAX,
        pattern=DNS_SUBDOMAIN_PATTERN,
        description="Kubernetes node that is this vehicle's companion computer. Changing it "
        "moves the vehicle's workloads to the new node (hot swap). At most 63 characters: "
        "Roost labels the vehicle's RedundantAutopilot with it (roost.dev/node).",
    )
    sysid: int = Field(
        ge=1,
        le=255,
        description="MAVLink system id of the vehicle (Starling's VEHICLE_MAVLINK_SYSID). "
        "Immutable: ground stations and autopilot parameters are keyed on it.",
        json_schema_extra={
            "x-kubernetes-validations": [
                {"rule": "self == oldSelf", "message": "sysid is immutable; create a new Vehicle"}
            ]
        },
    )
    vehicle_class: str = Field(
        default="rotary",
        max_length=63,
        pattern=r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?$",
        description="Broad class of the airframe, e.g. rotary or fixed-wing "
        "(label starling.dev/vehicle-class).",
    )
    vehicle_type: str = Field(
        default="quadrotor",
        max_length=63,
        pattern=r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?$",
        description="Airframe type, e.g. quadrotor or clover (label starling.dev/vehicle-type).",
    )
    simulation: Simulation | None = Field(
        default=None,
        description="Set for a simulated vehicle; absent for real hardware.",
    )
    components: Components = Field(
        default_factory=Components,
        description="Component workloads to run on the vehicle and their images.",
    )
    config: dict[str, ConfigValue] = Field(
        default_factory=dict,
        max_length=shapes.CONFIG_MAX_ENTRIES,
        description="Extra KEY=VALUE entries for vehicle.config and the pods' environment. "
        "Keys are upper-case environment variable names; values are one line each (line "
        "breaks and other control characters are refused); at most 8192 characters of "
        "keys and values in total.",
        json_schema_extra=shapes.validations(shapes.CONFIG_RULES),
    )
    starling_compatibility: bool = Field(
        default=True,
        description="Also set Starling's node labels (starling.dev/type=vehicle, "
        "starling.dev/vehicle-class, starling.dev/vehicle-type) so Starling manifests work.",
    )


class FailoverAction(ApiModel):
    """A cluster-side failover action in progress; counted by the fleet-wide cap."""

    kind: FailoverActionKind = Field(description="What is being done, e.g. RepointMavros.")
    autopilot: str = Field(max_length=63, description="Autopilot the action moves to.")
    started_at: datetime = Field(description="When the operator started the action.")


class VehicleFailover(ApiModel):
    """The operator's side of this vehicle's failovers: what it has seen and done.

    Kept in status (not in operator memory) so a restarted operator neither repeats an
    action nor forgets a latch. The on-vehicle switch never depends on any of this.
    """

    observed_failover_count: int = Field(
        default=0, ge=0, description="RedundantAutopilot status.failoverCount last accounted."
    )
    observed_failover_time: datetime | None = Field(
        default=None, description="RedundantAutopilot status.lastFailover.time last accounted."
    )
    recent: list[datetime] = Field(
        default_factory=list,
        max_length=64,
        description="Failovers seen within the latch window, oldest first.",
    )
    latched: bool = Field(
        default=False,
        description="Too many failovers within the window: cluster-side actions wait for a "
        "human to clear the latch (annotation roost.dev/clear-failover-latch).",
    )
    latched_at: datetime | None = Field(default=None, description="When the latch was set.")
    cleared_token: str | None = Field(
        default=None,
        max_length=253,
        description="Value of roost.dev/clear-failover-latch last honoured; each new value "
        "clears one latch.",
    )
    followed_autopilot: str | None = Field(
        default=None,
        max_length=63,
        description="Autopilot the vehicle's workloads follow (mavros' FCU URL, the config's "
        "VEHICLE_FCU_URL). Lags activeAutopilot while a guard holds the re-point back.",
    )
    action: FailoverAction | None = Field(
        default=None, description="Cluster-side action in progress, if any."
    )
    blocked: FailoverGuard | None = Field(
        default=None,
        description="Guard holding back a pending action: Paused, Latched or ConcurrencyLimit.",
    )


class FlightHold(ApiModel):
    """What the operator holds back while an autopilot of the vehicle is armed."""

    reason: str = Field(description="Why, e.g. 'autopilot fc1 is armed'.")
    disruption_budget: str = Field(
        description="The PodDisruptionBudget (maxUnavailable 0) that refuses evictions of "
        "the vehicle's pods (kubectl drain) until it is on the ground."
    )
    deferred: list[str] = Field(
        default_factory=list,
        description="Components whose pod replacement (a config or image change) waits "
        "for the landing.",
    )


class VehicleStatus(ApiModel):
    """Observed state of a Vehicle, written by the operator."""

    observed_generation: int | None = Field(
        default=None, description="metadata.generation the operator last reconciled."
    )
    conditions: list[Condition] = Field(
        default_factory=list,
        json_schema_extra=CONDITIONS_SCHEMA,
        description="Ready summarises NodeBound, ComponentsReady, AutopilotsHealthy and "
        "AgentConnected.",
    )
    node_name: str | None = Field(
        default=None, description="Node the vehicle's labels and workloads are bound to."
    )
    active_autopilot: str | None = Field(
        default=None, description="Autopilot currently driving the motors, from the agent."
    )
    fcu_url: str | None = Field(
        default=None, description="FCU URL mavros is pointed at (the active autopilot's)."
    )
    failover: VehicleFailover | None = Field(
        default=None,
        description="Cluster-side failover bookkeeping: actions, guards and latch.",
    )
    claimed_by: ObjectReference | None = Field(
        default=None, description="Mission this vehicle is flying, if any."
    )
    managed_labels: list[str] = Field(
        default_factory=list, description="Node label keys Roost has set for this vehicle."
    )
    flight_hold: FlightHold | None = Field(
        default=None,
        description="Set while an autopilot is armed: pod replacements and evictions wait.",
    )
