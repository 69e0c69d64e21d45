"""The Mission resource: which vehicles fly, and what runs on and off them.

A Mission is what users ``kubectl apply``. It mirrors Starling's deployment pattern: an
onboard controller on every assigned vehicle, plus an optional offboard (central)
workload. The operator claims vehicles exclusively, gates on preflight checks, runs the
workloads with Job completion semantics, and on abort asks every vehicle's agent to run
its safety routine.

The pod templates are the real Kubernetes ``PodTemplateSpec``: the CRD generator embeds
its schema, so users get the same validation and ``kubectl explain`` as in a Job.
"""

from __future__ import annotations

from datetime import datetime
from enum import StrEnum
from typing import Annotated, Any

from pydantic import Field
from pydantic.config import JsonDict

from roost_api import shapes
from roost_api.autopilot import FENCE_RULES, AutopilotCommand, Fence
from roost_api.meta import CONDITIONS_SCHEMA, DNS_SUBDOMAIN_PATTERN, ApiModel, Condition
from roost_api.vehicle import FailoverGuard

# Marker the CRD generator replaces with the Kubernetes PodTemplateSpec schema.
EMBED_POD_TEMPLATE: JsonDict = {"x-roost-embed": "io.k8s.api.core.v1.PodTemplateSpec"}
MAX_MISSION_VEHICLES = 1000
MAX_SELECTOR_LABELS = 64

LabelValue = Annotated[
    str,
    Field(
        max_length=shapes.LABEL_VALUE_MAX,
        json_schema_extra=shapes.validations(shapes.LABEL_VALUE_RULES),
    ),
]
VehicleName = Annotated[
    str,
    Field(min_length=1, max_length=shapes.VEHICLE_NAME_MAX, pattern=DNS_SUBDOMAIN_PATTERN),
]


class MissionPhase(StrEnum):
    """Lifecycle of a Mission."""

    PENDING = "Pending"
    PREFLIGHT = "Preflight"
    RUNNING = "Running"
    SUCCEEDED = "Succeeded"
    FAILED = "Failed"
    ABORTING = "Aborting"
    ABORTED = "Aborted"

    @property
    def finished(self) -> bool:
        """True for phases a Mission never leaves."""
        return self in (MissionPhase.SUCCEEDED, MissionPhase.FAILED, MissionPhase.ABORTED)


class MissionReason(StrEnum):
    """Reasons of a Mission's phase (``status.reason``) and of its conditions.

    Besides these, ``Degraded`` carries ``FailoverAction<guard>``
    (:func:`failover_action_held_reason`) while a fleet guard holds a failover's
    consequence back, and ``PreflightPassed`` False the first failing vehicle's
    :class:`MissionVehicleReason`.
    """

    CLAIMING = "Claiming"
    INSUFFICIENT_VEHICLES = "InsufficientVehicles"
    NOT_STARTED = "NotStarted"
    ASSIGNED = "Assigned"
    PREFLIGHT_FAILED = "PreflightFailed"
    ALL_CHECKS_PASSED = "AllChecksPassed"
    NO_FAILOVER = "NoFailover"
    STARTED = "Started"
    RUNNING = "Running"
    VEHICLE_FAILED_OVER = "VehicleFailedOver"
    VEHICLE_DELETED = "VehicleDeleted"
    VEHICLE_UNREACHABLE = "VehicleUnreachable"
    VEHICLES_REACHABLE = "VehiclesReachable"
    VEHICLE_WORKLOAD_FAILED = "VehicleWorkloadFailed"
    OFFBOARD_WORKLOAD_FAILED = "OffboardWorkloadFailed"
    COMPLETED = "Completed"
    ALL_VEHICLES_ABORTED = "AllVehiclesAborted"
    ABORT_REQUESTED = "AbortRequested"
    ABORTED = "Aborted"
    ABORTED_BEFORE_START = "AbortedBeforeStart"
    INVALID_TEMPLATE = "InvalidTemplate"
    INVALID_FENCE = "InvalidFence"
    JOB_REJECTED = "JobRejected"


class MissionVehicleReason(StrEnum):
    """Reasons of one vehicle's phase in a Mission (``status.vehicles[].reason``).

    Besides these: ``FailoverAction<guard>`` (:func:`failover_action_held_reason`) while a
    fleet guard holds a failover's consequence back, and ``<action><outcome>``
    (:func:`abort_command_reason`, e.g. ``SafetyRoutinePending``) while an abort command
    is on its way.
    """

    # preflight
    PREFLIGHT_PASSED = "PreflightPassed"
    VEHICLE_MISSING = "VehicleMissing"
    VEHICLE_NOT_READY = "VehicleNotReady"
    AGENT_NOT_CONNECTED = "AgentNotConnected"
    ACTIVE_AUTOPILOT_UNHEALTHY = "ActiveAutopilotUnhealthy"
    NOT_REDUNDANT = "NotRedundant"
    FIRMWARE_UNACCEPTABLE = "FirmwareUnacceptable"
    FENCE_NOT_HELD = "FenceNotHeld"
    VEHICLE_CONFIG_MISSING = "VehicleConfigMissing"
    # the onboard workload
    JOB_CREATED = "JobCreated"
    POD_STARTING = "PodStarting"
    POD_RUNNING = "PodRunning"
    COMPLETED = "Completed"
    JOB_FAILED = "JobFailed"
    MISSION_ENDED = "MissionEnded"
    # failovers, deletion and aborts
    FAILED_OVER = "FailedOver"
    VEHICLE_DELETED = "VehicleDeleted"
    VEHICLE_UNREACHABLE = "VehicleUnreachable"
    ABORTED_BEFORE_START = "AbortedBeforeStart"
    NO_REDUNDANT_AUTOPILOT = "NoRedundantAutopilot"
    LANDED = "Landed"
    DISARMED = "Disarmed"


def failover_action_held_reason(guard: str) -> str:
    """``FailoverAction<guard>``: a failover's consequence held back by fleet guard ``guard``
    (a non-``Allowed`` :class:`roost_api.vehicle.FailoverGuard` value)."""
    return f"FailoverAction{guard}"


def abort_command_reason(action: str, outcome: str) -> str:
    """``<action><outcome>``: where the abort command to a vehicle stands (a
    :class:`~roost_api.autopilot.CommandAction` and a
    :class:`~roost_api.commands.CommandOutcome` value)."""
    return f"{action}{outcome}"


class MissionVehiclePhase(StrEnum):
    """Lifecycle of one vehicle within a Mission."""

    CLAIMED = "Claimed"
    PREFLIGHT = "Preflight"
    RUNNING = "Running"
    SUCCEEDED = "Succeeded"
    FAILED = "Failed"
    ABORTING = "Aborting"
    ABORTED = "Aborted"


class WorkloadPhase(StrEnum):
    """State of the mission's offboard Job."""

    RUNNING = "Running"
    SUCCEEDED = "Succeeded"
    FAILED = "Failed"
    STOPPED = "Stopped"


class MissionConditionType(StrEnum):
    """Condition types on a Mission; written by the operator."""

    VEHICLES_ASSIGNED = "VehiclesAssigned"
    PREFLIGHT_PASSED = "PreflightPassed"
    DEGRADED = "Degraded"
    COMPLETE = "Complete"


class OnFailover(StrEnum):
    """What a mission does when one of its vehicles fails over mid-flight."""

    CONTINUE = "Continue"
    ABORT_VEHICLE = "AbortVehicle"
    ABORT_MISSION = "AbortMission"


class OnUnreachable(StrEnum):
    """What a mission does while one of its vehicles' node cannot be reached (its link
    is lost). The vehicle's pods are kept either way and fly on."""

    CONTINUE = "Continue"
    ABORT_MISSION = "AbortMission"


class AbortAction(StrEnum):
    """How an abort stops the vehicles."""

    SAFETY_ROUTINE = "SafetyRoutine"
    EMERGENCY_STOP = "EmergencyStop"


class LabelSelectorRequirement(ApiModel):
    """A label selector requirement, as in metav1.LabelSelectorRequirement."""

    key: str = Field(max_length=317, description="Label key.")
    operator: str = Field(
        max_length=12,
        pattern=r"^(In|NotIn|Exists|DoesNotExist)$",
        description="In, NotIn, Exists or DoesNotExist.",
    )
    values: list[LabelValue] = Field(
        default_factory=list,
        max_length=64,
        description="Values for In and NotIn (at least one); none for Exists and DoesNotExist.",
    )


class LabelSelector(ApiModel):
    """A label query over Vehicles, as in metav1.LabelSelector."""

    match_labels: dict[str, LabelValue] = Field(
        default_factory=dict,
        max_length=MAX_SELECTOR_LABELS,
        description="Labels a Vehicle must carry.",
        json_schema_extra=shapes.validations(shapes.LABEL_MAP_RULES),
    )
    match_expressions: list[
        Annotated[
            LabelSelectorRequirement,
            Field(json_schema_extra=shapes.validations(shapes.LABEL_REQUIREMENT_RULES)),
        ]
    ] = Field(default_factory=list, max_length=32, description="Set-based requirements.")


class VehicleSelection(ApiModel):
    """Which vehicles a mission may use and how many it needs."""

    selector: LabelSelector | None = Field(
        default=None, description="Vehicles whose labels match; combined with names."
    )
    names: list[VehicleName] = Field(
        default_factory=list,
        max_length=MAX_MISSION_VEHICLES,
        description="Vehicles by name, each once; preferred before selector matches.",
        json_schema_extra={"x-kubernetes-list-type": "set"},
    )
    count: int = Field(
        ge=1, le=MAX_MISSION_VEHICLES, description="How many vehicles the mission needs."
    )


VEHICLE_SELECTION_RULES: list[JsonDict] = [
    {
        "rule": "has(self.selector) || size(self.names) > 0",
        "message": "vehicles needs a selector, names, or both",
    },
    {
        "rule": "has(self.selector) || self.count <= size(self.names)",
        "message": "count is larger than the number of names and there is no selector",
    },
]


class Preflight(ApiModel):
    """Checks every assigned vehicle must pass before anything starts on it."""

    require_agent_connected: bool = Field(
        default=True, description="The vehicle's node agent reports recently."
    )
    require_active_healthy: bool = Field(default=True, description="The active autopilot is OK.")
    require_redundancy: bool = Field(
        default=True, description="At least one healthy standby autopilot."
    )


class MissionSpec(ApiModel):
    """Desired state of a Mission."""

    vehicles: VehicleSelection = Field(
        description="Which vehicles fly. Immutable.",
        json_schema_extra={
            "x-kubernetes-validations": [
                {"rule": "self == oldSelf", "message": "vehicles is immutable"},
                *VEHICLE_SELECTION_RULES,
            ]
        },
    )
    onboard: dict[str, Any] = Field(
        description="Pod template run once on every assigned vehicle. Immutable.",
        json_schema_extra=EMBED_POD_TEMPLATE,
    )
    offboard: dict[str, Any] | None = Field(
        default=None,
        description="Pod template run once off the vehicles (a central monitor). Immutable.",
        json_schema_extra=EMBED_POD_TEMPLATE,
    )
    backoff_limit: int = Field(
        default=2, ge=0, le=10, description="Retries of a failed onboard pod per vehicle."
    )
    preflight: Preflight = Field(default_factory=Preflight, description="Preflight checks.")
    on_failover: OnFailover = Field(
        default=OnFailover.ABORT_VEHICLE,
        description="Continue, AbortVehicle (land it, mission goes on Degraded) or "
        "AbortMission, when a vehicle fails over mid-mission. The abort waits while the "
        "fleet guards' pause switch or the vehicle's failover latch is on.",
    )
    on_unreachable: OnUnreachable = Field(
        default=OnUnreachable.CONTINUE,
        description="Continue (the default: the vehicle flies on with its pods, the "
        "mission shows it unreachable and goes on Degraded) or AbortMission, while a "
        "vehicle's node cannot be reached (its link is lost).",
    )
    abort: bool = Field(
        default=False,
        description="Set true to abort: every vehicle runs its safety routine. Cannot be undone.",
    )
    abort_action: AbortAction = Field(
        default=AbortAction.SAFETY_ROUTINE,
        description="SafetyRoutine (hold then land) or EmergencyStop (force disarm).",
    )
    fence: Fence | None = Field(
        default=None,
        description="The Mission's flying area. Before the Mission starts, every autopilot "
        "of every claimed vehicle (standbys included) must hold it; the previous fence is "
        "restored afterwards. Immutable.",
        json_schema_extra={"x-kubernetes-validations": list(FENCE_RULES)},
    )
    flying_altitude_m: float | None = Field(
        default=None,
        gt=0,
        le=10000,
        description="The highest altitude above home the Mission's vehicles fly at; a "
        "fence's maxAltitudeM may not be below it. Immutable.",
    )


# On the whole object: metadata.name is only visible to CEL from the root.
MISSION_ROOT_RULES = [
    shapes.rule(
        f"size(self.metadata.name) <= {shapes.MISSION_NAME_MAX}",
        f"metadata.name: a Mission name is at most {shapes.MISSION_NAME_MAX} characters, "
        "like the Jobs, labels and Events Roost names after it",
    )
]

MISSION_SPEC_RULES = [
    {
        "rule": "!oldSelf.abort || self.abort",
        "message": "abort cannot be undone; create a new Mission",
    },
    {"rule": "self.onboard == oldSelf.onboard", "message": "onboard is immutable"},
    {
        "rule": "!has(self.onboard.spec) || !has(self.onboard.spec.restartPolicy) || "
        "self.onboard.spec.restartPolicy != 'Always'",
        "message": "onboard pods run to completion as a Job: restartPolicy must be Never or "
        "OnFailure (Never when omitted)",
    },
    {
        "rule": "!has(self.offboard) || !has(self.offboard.spec) || "
        "!has(self.offboard.spec.restartPolicy) || self.offboard.spec.restartPolicy != 'Always'",
        "message": "offboard pods run to completion as a Job: restartPolicy must be Never or "
        "OnFailure (Never when omitted)",
    },
    {
        "rule": "has(self.fence) == has(oldSelf.fence) && "
        "(!has(self.fence) || self.fence == oldSelf.fence)",
        "message": "fence is immutable",
    },
    {
        "rule": "!has(self.fence) || !has(self.flyingAltitudeM) || "
        "self.fence.maxAltitudeM >= self.flyingAltitudeM",
        "message": "fence.maxAltitudeM is below flyingAltitudeM: the Mission could not fly "
        "as declared without breaching its fence",
    },
    {
        "rule": "has(self.offboard) == has(oldSelf.offboard) && "
        "(!has(self.offboard) || self.offboard == oldSelf.offboard)",
        "message": "offboard is immutable",
    },
]


class MissionVehicleStatus(ApiModel):
    """One assigned vehicle's progress."""

    name: str = Field(max_length=253, pattern=DNS_SUBDOMAIN_PATTERN, description="Vehicle name.")
    node_name: str | None = Field(default=None, description="Its node.")
    phase: MissionVehiclePhase = Field(description="Where this vehicle is in the mission.")
    reason: str | None = Field(default=None, description="CamelCase reason for the phase.")
    message: str | None = Field(default=None, description="What is happening or missing.")
    job_name: str | None = Field(default=None, description="Onboard Job on this vehicle.")
    failed_over_at: datetime | None = Field(
        default=None,
        description="Time of the last autopilot failover on this vehicle that the mission "
        "has taken into account: its spec.onFailover consequence is applied, or held back "
        "as failoverActionHeld says.",
    )
    failover_action_held: FailoverGuard | None = Field(
        default=None,
        description="The fleet guard (Paused or Latched) holding back the spec.onFailover "
        "consequence of the failover at failedOverAt; unset once it is applied. The "
        "vehicle's agent runs its own safety routine after a failover regardless.",
    )
    unreachable_since: datetime | None = Field(
        default=None,
        description="Set while the vehicle's node cannot be reached: since when (its "
        "Vehicle's NodeBound condition, reason NodeUnreachable).",
    )
    command: AutopilotCommand | None = Field(
        default=None,
        description="The last request this mission wrote to the vehicle's RedundantAutopilot "
        "(safety routine or emergency stop); its outcome is in that object's "
        "status.lastCommand.",
    )


class MissionOffboardStatus(ApiModel):
    """The offboard (central) workload's progress."""

    job_name: str = Field(description="The offboard Job.")
    phase: WorkloadPhase = Field(description="Running, Succeeded, Failed or Stopped.")
    message: str | None = Field(default=None, description="What is happening.")


class RecordsState(StrEnum):
    """Where a finished Mission's record (its bundle) stands."""

    GATHERING = "Gathering"
    """Still fetching flights from vehicles (or waiting for one to come back)."""
    COMPLETE = "Complete"
    """Every claimed vehicle's flights and files are in the bundle, checksums verified."""
    PARTIAL = "Partial"
    """The bundle is final but lacks something; its manifest says what and why."""
    FAILED = "Failed"
    """No bundle could be written (the operator's records volume refused it)."""

    @property
    def final(self) -> bool:
        return self is not RecordsState.GATHERING


class VehicleRecordsStatus(ApiModel):
    """One claimed vehicle's part of the Mission's record."""

    name: str = Field(description="The Vehicle.")
    state: str = Field(
        description="Pending, Complete, Partial, Missing, OnVehicle (the flights stay on the"
        " vehicle: the operator cannot reach its records by its settings) or NotRecorded."
    )
    flights: int = Field(default=0, description="Flights of this mission gathered so far.")
    message: str | None = Field(default=None, description="What is pending or missing, and why.")


class UploadState(StrEnum):
    """Where the copy of a Mission's bundle in the configured bucket stands."""

    PENDING = "Pending"
    """Being uploaded, or waiting to try again after a temporary failure."""
    COMPLETE = "Complete"
    """Every file and the manifest are in the bucket with their SHA-256."""
    FAILED = "Failed"
    """The bucket refused it for good (credentials, bucket, region), or stayed
    unreachable too long; the message says which. Not tried again."""

    @property
    def final(self) -> bool:
        return self is not UploadState.PENDING


class RecordsUploadStatus(ApiModel):
    """The copy of the bundle in an S3-compatible bucket."""

    state: UploadState = Field(description="Pending, Complete or Failed.")
    location: str = Field(description="s3://bucket/prefix/bundle/ the bundle goes to.")
    message: str | None = Field(default=None, description="Why it is pending or failed.")
    objects: int = Field(default=0, description="Objects in the bucket so far.")
    attempts: int = Field(default=0, description="Tries that failed for a temporary reason.")
    next_attempt_time: datetime | None = Field(
        default=None, description="When a Pending upload is tried again."
    )
    complete_time: datetime | None = Field(
        default=None, description="When the last object was in the bucket."
    )


class MissionRecordsStatus(ApiModel):
    """The Mission's record: one bundle on the operator's records volume."""

    state: RecordsState = Field(description="Gathering, Complete, Partial or Failed.")
    bundle: str = Field(description="The bundle's name (``roost records get`` fetches it).")
    message: str | None = Field(default=None, description="What is pending or missing.")
    ready_time: datetime | None = Field(
        default=None, description="When the bundle became final (Complete or Partial)."
    )
    vehicles: list[VehicleRecordsStatus] = Field(
        default_factory=list, description="Per claimed vehicle."
    )
    upload: RecordsUploadStatus | None = Field(
        default=None,
        description="The copy in the configured S3-compatible bucket, once the bundle is final.",
    )


class MissionStatus(ApiModel):
    """Observed state of a Mission, written by the operator."""

    observed_generation: int | None = Field(default=None, description="Generation reconciled.")
    phase: MissionPhase = Field(default=MissionPhase.PENDING, description="Mission phase.")
    reason: str | None = Field(default=None, description="CamelCase reason for the phase.")
    message: str | None = Field(default=None, description="Why the mission is in this phase.")
    assigned_count: int = Field(default=0, description="Vehicles assigned.")
    vehicles: list[MissionVehicleStatus] = Field(
        default_factory=list, description="Per-vehicle state."
    )
    offboard: MissionOffboardStatus | None = Field(
        default=None, description="The offboard workload, once started."
    )
    conditions: list[Condition] = Field(
        default_factory=list,
        json_schema_extra=CONDITIONS_SCHEMA,
        description="VehiclesAssigned, PreflightPassed, Degraded, Complete.",
    )
    start_time: datetime | None = Field(default=None, description="When workloads started.")
    completion_time: datetime | None = Field(default=None, description="When it finished.")
    records: MissionRecordsStatus | None = Field(
        default=None, description="The flight record of a mission that flew, once it ended."
    )
