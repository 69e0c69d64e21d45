"""The RedundantAutopilot's enums and constants, without pydantic.

The node agent reads and writes these values but must not import pydantic (it costs
several MB on a companion computer; see :mod:`roost_api.core`), so they live here and
:mod:`roost_api.autopilot` re-exports them next to its models.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Protocol

MAX_AUTOPILOTS = 8


class AutopilotConditionType(StrEnum):
    """Condition types on a RedundantAutopilot; all written by the node agent."""

    READY = "Ready"
    ACTIVE_HEALTHY = "ActiveHealthy"
    REDUNDANT = "Redundant"
    FAILED_OVER = "FailedOver"
    FIRMWARE_ACCEPTABLE = "FirmwareAcceptable"


class AutopilotConditionReason(StrEnum):
    """Reasons of the RedundantAutopilot's conditions (written by the node agent).

    ``Ready`` carries the reason of the first of ``ActiveHealthy`` and ``Redundant`` that
    is not True, or ``Ready``.
    """

    # every condition, before the bridge has an active autopilot
    NO_ACTIVE_AUTOPILOT = "NoActiveAutopilot"
    # ActiveHealthy
    NO_HEALTH = "NoHealth"
    HEALTHY = "Healthy"
    DEGRADED = "Degraded"
    NO_DATA = "NoData"
    STARTING = "Starting"
    UNHEALTHY = "Unhealthy"
    # Redundant
    NO_STANDBY = "NoStandby"
    STANDBY_AVAILABLE = "StandbyAvailable"
    LATCHED = "Latched"
    STANDBY_STATE_UNKNOWN = "StandbyStateUnknown"
    NO_HEALTHY_STANDBY = "NoHealthyStandby"
    # FailedOver
    ON_PRIMARY = "OnPrimary"
    NOT_ON_PRIMARY = "NotOnPrimary"
    AUTOMATIC_FAILOVER = "AutomaticFailover"
    SWITCHED_BY_COMMAND = "SwitchedByCommand"
    # Ready
    READY = "Ready"
    # FirmwareAcceptable (with spec.firmware)
    FIRMWARE_ACCEPTABLE = "FirmwareAcceptable"
    FIRMWARE_BELOW_MINIMUM = "FirmwareBelowMinimum"
    FIRMWARE_VERSIONS_DIFFER = "FirmwareVersionsDiffer"
    NO_FIRMWARE_DATA = "NoFirmwareData"


class AutopilotEntryConditionType(StrEnum):
    """Condition types on one autopilot's entry in ``status.autopilots``."""

    STANDBY_IN_STEP = "StandbyInStep"
    PARAMETERS_IN_SYNC = "ParametersInSync"
    FENCE_IN_SYNC = "FenceInSync"


class StandbyInStepReason(StrEnum):
    """Reasons of the per-autopilot ``StandbyInStep`` condition."""

    IN_STEP = "InStep"
    ACTIVE = "Active"
    NO_DATA = "NoData"
    SILENT = "Silent"
    ARMED_DIFFERS = "ArmedDiffers"
    MODE_DIFFERS = "ModeDiffers"
    POSITION_DIFFERS = "PositionDiffers"
    ALTITUDE_DIFFERS = "AltitudeDiffers"
    REJECTED_MIRRORED = "RejectedMirroredCommand"
    NOT_MIRRORED = "NotMirrored"


class FenceReason(StrEnum):
    """Reasons of the per-autopilot ``FenceInSync`` condition (with spec.fence, and
    while a previous fence is being restored)."""

    HELD = "FenceHeld"  # the fence and its parameters read back as declared
    SAVING = "SavingPrevious"  # reading the fence it held before, to restore it later
    UPLOADING = "Uploading"
    VERIFYING = "Verifying"  # reading the uploaded fence back
    DEFERRED = "DeferredWhileArmed"  # nothing is written to an armed vehicle
    REFUSED = "UploadRefused"  # the autopilot refused the upload (MISSION_ACK error)
    NO_ANSWER = "NoAnswer"  # the transfer timed out after its retries
    MISMATCH = "ReadBackDiffers"  # what was read back is not what was uploaded
    PARAMETERS = "ParametersNotHeld"  # a fence parameter did not take
    OUTSIDE = "VehicleOutsideFence"  # its position is outside the fence: not uploaded
    RESTORING = "RestoringPrevious"


class ParametersReason(StrEnum):
    """Reasons of the per-autopilot ``ParametersInSync`` condition (first that applies)."""

    IN_SYNC = "InSync"  # every declared parameter reads back as declared
    MISSING = "UnknownParameter"  # the firmware has no parameter of that name
    INVALID = "InvalidValue"  # the value does not fit the parameter's type
    REFUSED = "WriteRefused"  # written and retried, the autopilot kept its value
    DRIFTED = "Drifted"  # set once, changed since by someone else (policy Report)
    DEFERRED = "DeferredWhileArmed"  # a write waits for the vehicle to be disarmed
    WRITING = "Writing"  # being read or written
    NO_DATA = "NoData"  # the autopilot has not answered yet


class DriftPolicy(StrEnum):
    """What the agent does when a parameter it set is changed by someone else."""

    RESTORE = "Restore"
    REPORT = "Report"


class FailoverMode(StrEnum):
    """Who decides a failover."""

    AUTOMATIC = "Automatic"
    MANUAL = "Manual"


class FinalAction(StrEnum):
    """What the safety routine does after holding."""

    LAND = "Land"
    RETURN_TO_LAUNCH = "ReturnToLaunch"
    HOLD = "Hold"


class Failback(StrEnum):
    """Whether control may return to the primary after a failover."""

    NEVER = "Never"
    MANUAL = "Manual"
    ON_GROUND = "OnGround"


class CommandAction(StrEnum):
    """Requests the cluster can make of the node agent."""

    SWITCH = "Switch"
    SAFETY_ROUTINE = "SafetyRoutine"
    EMERGENCY_STOP = "EmergencyStop"
    CLEAR_LATCH = "ClearLatch"


class FailoverTrigger(StrEnum):
    """Why the bridge switched (``lastFailover.trigger``)."""

    AUTOMATIC = "Automatic"
    COMMAND = "Command"
    FAILBACK = "Failback"


class SafetyRoutinePhase(StrEnum):
    """The safety routine after a switch, as ``lastFailover.safetyRoutine`` shows it.

    ``Run`` and ``Skipped: pilot in manual mode`` are the plan written with the switch;
    the others are the routine's progress on the new active autopilot (hold, then the
    final action). No value is written when a switch plans no routine (a command or a
    failback).
    """

    RUN = "Run"
    SKIPPED_PILOT = "Skipped: pilot in manual mode"
    STARTED = "Started"
    CONFIRMING_HOLD = "ConfirmingHold"
    HOLDING = "Holding"
    HOLD_REFUSED = "HoldRefused"
    HOLD_FAILED = "HoldFailed"
    LANDING = "Landing"
    LAND_TIMED_OUT = "LandTimedOut"
    LANDED = "Landed"
    RETURNING = "ReturningToLaunch"
    HELD = "Held"
    CANCELLED = "Cancelled"
    FAILED = "Failed"
    DISARMED = "Disarmed"

    @property
    def final(self) -> bool:
        """No further phase follows (Cancelled is not final: another routine replaced it)."""
        return self in _FINAL_SAFETY_PHASES


_FINAL_SAFETY_PHASES = frozenset(
    {
        SafetyRoutinePhase.SKIPPED_PILOT,
        SafetyRoutinePhase.LANDED,
        SafetyRoutinePhase.HELD,
        SafetyRoutinePhase.FAILED,
        SafetyRoutinePhase.DISARMED,
    }
)


class HubScope(StrEnum):
    """What the clients of one hub endpoint may send to the vehicle."""

    EVERYTHING = "Everything"  # every message (mavros, a mission controller)
    READ_ONLY = "ReadOnly"  # parameter, mission and message reads only
    ALLOW_LIST = "AllowList"  # the endpoint's allowMessages and allowCommands


class HubSigning(StrEnum):
    """Whether one hub endpoint's clients must sign (MAVLink 2 signing, the vehicle's key)."""

    AUTO = "Auto"  # required beyond loopback (no key: the endpoint refuses to start)
    REQUIRED = "Required"  # required on any address, loopback too
    UNAUTHENTICATED = "Unauthenticated"  # never, also beyond loopback (said in the status)


class HubTransport(StrEnum):
    """How one hub endpoint's clients connect."""

    UDP = "UDP"
    TCP = "TCP"


class CommandResultKind(StrEnum):
    """What the agent did with a command (``lastCommand.result``)."""

    EXECUTED = "Executed"
    REJECTED = "Rejected"
    EXPIRED = "Expired"


class LandedState(StrEnum):
    """MAV_LANDED_STATE from EXTENDED_SYS_STATE, as ``autopilots[].landedState`` shows it."""

    UNDEFINED = "Undefined"
    ON_GROUND = "OnGround"
    IN_AIR = "InAir"
    TAKEOFF = "Takeoff"
    LANDING = "Landing"


HOST_PORT_PATTERN = r"^[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?:[0-9]{1,5}$"


class HasUdpEndpoint(Protocol):
    """A hub spec (the API model or its plain twin): its UDP endpoint."""

    @property
    def udp(self) -> str: ...


MAVROS_HUB_BIND_PORT = 14555  # mavros' own UDP port when it talks to the hub


def hub_client_url(hub: HasUdpEndpoint) -> str:
    """The FCU URL mavros uses to reach the hub (``udp://:LOCAL@HOST:PORT``): the hub's
    UDP endpoint, on 127.0.0.1 when it listens on every address."""
    host, _, port = hub.udp.rpartition(":")
    if host in ("0.0.0.0", ""):
        host = "127.0.0.1"
    return f"udp://:{MAVROS_HUB_BIND_PORT}@{host}:{port}"
