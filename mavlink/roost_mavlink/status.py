"""Status vocabulary of an autopilot: MAV_STATE, landed state, SYS_STATUS sensor bits.

The numbers are MAVLink's (common.xml / minimal.xml); the classification of sensor bits
into failover-critical, warn-only and ignored follows the health model in
``docs/health-model.md``. The sim sets bits the way each stack does and the
agent judges them with :func:`classify_sensors`, so both read the same table.

Landed states are numbers here (MAV_LANDED_STATE, :class:`MavLandedState`) and names in the
API (:class:`roost_api.autopilot_enums.LandedState`); :func:`api_landed_state` is the one
translation between the two.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, IntFlag, StrEnum

from roost_api.autopilot_enums import LandedState
from roost_api.core import Stack

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
MAV_AUTOPILOT_INVALID = 8  # sent by components that are not autopilots (GCS, companions)
MAV_TYPE_QUADROTOR = 2
MAV_TYPE_ONBOARD_CONTROLLER = 18

_HEARTBEAT_AUTOPILOT: dict[Stack, int] = {
    Stack.PX4: MAV_AUTOPILOT_PX4,
    Stack.ARDUPILOT: MAV_AUTOPILOT_ARDUPILOTMEGA,
}


def heartbeat_autopilot(stack: Stack) -> int:
    """HEARTBEAT ``autopilot`` value a stack sends (PX4 12, ArduPilot 3)."""
    return _HEARTBEAT_AUTOPILOT[Stack(stack)]


def stack_from_heartbeat(autopilot: int) -> Stack | None:
    """The stack behind a HEARTBEAT ``autopilot`` value, or None for non-autopilots."""
    for stack, value in _HEARTBEAT_AUTOPILOT.items():
        if value == autopilot:
            return stack
    return None


class MavState(IntEnum):
    """MAV_STATE, the heartbeat's ``system_status``."""

    UNINIT = 0
    BOOT = 1
    CALIBRATING = 2
    STANDBY = 3
    ACTIVE = 4
    CRITICAL = 5
    EMERGENCY = 6
    POWEROFF = 7
    FLIGHT_TERMINATION = 8


def mav_state_name(value: int) -> str:
    """Name of a MAV_STATE value (``UNKNOWN(n)`` outside the enum)."""
    try:
        return MavState(value).name
    except ValueError:
        return f"UNKNOWN({value})"


class MavLandedState(IntEnum):
    """MAV_LANDED_STATE from EXTENDED_SYS_STATE."""

    UNDEFINED = 0
    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4


_API_LANDED_STATES: dict[int, LandedState] = {
    MavLandedState.UNDEFINED: LandedState.UNDEFINED,
    MavLandedState.ON_GROUND: LandedState.ON_GROUND,
    MavLandedState.IN_AIR: LandedState.IN_AIR,
    MavLandedState.TAKEOFF: LandedState.TAKEOFF,
    MavLandedState.LANDING: LandedState.LANDING,
}


def api_landed_state(value: int) -> LandedState:
    """The API's landed state (``autopilots[].landedState``) for a MAV_LANDED_STATE number."""
    return _API_LANDED_STATES.get(value, LandedState.UNDEFINED)


def is_airborne(value: int) -> bool:
    """True for InAir, Takeoff and Landing: the vehicle may be off the ground."""
    return value in (MavLandedState.IN_AIR, MavLandedState.TAKEOFF, MavLandedState.LANDING)


class SensorBit(IntFlag):
    """MAV_SYS_STATUS_SENSOR bits of SYS_STATUS present/enabled/health."""

    GYRO = 0x1
    ACCEL = 0x2
    MAG = 0x4
    ABSOLUTE_PRESSURE = 0x8
    DIFFERENTIAL_PRESSURE = 0x10
    GPS = 0x20
    OPTICAL_FLOW = 0x40
    VISION_POSITION = 0x80
    LASER_POSITION = 0x100
    EXTERNAL_GROUND_TRUTH = 0x200
    ANGULAR_RATE_CONTROL = 0x400
    ATTITUDE_STABILIZATION = 0x800
    YAW_POSITION = 0x1000
    Z_ALTITUDE_CONTROL = 0x2000
    XY_POSITION_CONTROL = 0x4000
    MOTOR_OUTPUTS = 0x8000
    RC_RECEIVER = 0x10000
    GYRO2 = 0x20000
    ACCEL2 = 0x40000
    MAG2 = 0x80000
    GEOFENCE = 0x100000
    AHRS = 0x200000
    TERRAIN = 0x400000
    REVERSE_MOTOR = 0x800000
    LOGGING = 0x1000000
    BATTERY = 0x2000000
    PROXIMITY = 0x4000000
    SATCOM = 0x8000000
    PREARM_CHECK = 0x10000000
    OBSTACLE_AVOIDANCE = 0x20000000
    PROPULSION = 0x40000000
    EXTENSION_USED = 0x80000000


class SensorSeverity(StrEnum):
    """What an unhealthy sensor bit means for failover."""

    CRITICAL = "critical"  # ERROR once it persists: the autopilot cannot keep attitude
    WARN = "warn"  # degrade to WARN, never a failover on its own
    IGNORE = "ignore"  # normal on the ground or irrelevant to flight safety


# From the reference table: gyro/accel/AHRS trigger failover; a second IMU failing alone,
# navigation sensors and control-loop flags only warn; prearm, RC, logging, geofence are
# ignored (ArduPilot clears PREARM_CHECK on the ground, PX4 SITL without RC clears RC).
CRITICAL_SENSORS = SensorBit.GYRO | SensorBit.ACCEL | SensorBit.AHRS
IGNORED_SENSORS = (
    SensorBit.RC_RECEIVER
    | SensorBit.PREARM_CHECK
    | SensorBit.LOGGING
    | SensorBit.GEOFENCE
    | SensorBit.EXTENSION_USED
)


def sensor_severity(bit: SensorBit) -> SensorSeverity:
    """Severity of one unhealthy sensor bit."""
    if bit & CRITICAL_SENSORS:
        return SensorSeverity.CRITICAL
    if bit & IGNORED_SENSORS:
        return SensorSeverity.IGNORE
    return SensorSeverity.WARN


def sensor_bits(mask: int) -> list[SensorBit]:
    """The single bits set in ``mask``, lowest first."""
    return [bit for bit in SensorBit if mask & bit]


def sensor_name(bit: SensorBit) -> str:
    """Lower-case name of one bit, e.g. ``gyro`` (used in health reasons)."""
    return (bit.name or f"bit{int(bit):#x}").lower()


def sensor_from_name(name: str) -> SensorBit:
    """The bit called ``name`` (case-insensitive, e.g. ``gyro`` or ``AHRS``)."""
    try:
        return SensorBit[name.upper()]
    except KeyError:
        raise KeyError(f"unknown SYS_STATUS sensor {name!r}") from None


@dataclass(frozen=True)
class SensorReport:
    """Enabled sensors reported unhealthy in one SYS_STATUS, split by severity."""

    critical: tuple[SensorBit, ...]
    warn: tuple[SensorBit, ...]
    ignored: tuple[SensorBit, ...]

    @property
    def unhealthy(self) -> tuple[SensorBit, ...]:
        """Every enabled-but-unhealthy bit that is not ignored."""
        return self.critical + self.warn


def classify_sensors(enabled: int, health: int) -> SensorReport:
    """Split the enabled-but-unhealthy bits (mavros: ``health & enabled != enabled``)."""
    bad = sensor_bits(enabled & ~health & 0xFFFFFFFF)
    by = {
        severity: tuple(b for b in bad if sensor_severity(b) is severity)
        for severity in SensorSeverity
    }
    return SensorReport(
        critical=by[SensorSeverity.CRITICAL],
        warn=by[SensorSeverity.WARN],
        ignored=by[SensorSeverity.IGNORE],
    )


# Bits each stack reports present/enabled in a healthy, flyable SITL without RC. Healthy
# is all of them except what the stack keeps unhealthy on the ground (see below).
# ArduPilot additionally reports terrain and logging.
_COMMON_SENSORS = (
    SensorBit.GYRO
    | SensorBit.ACCEL
    | SensorBit.MAG
    | SensorBit.ABSOLUTE_PRESSURE
    | SensorBit.GPS
    | SensorBit.ANGULAR_RATE_CONTROL
    | SensorBit.ATTITUDE_STABILIZATION
    | SensorBit.YAW_POSITION
    | SensorBit.Z_ALTITUDE_CONTROL
    | SensorBit.XY_POSITION_CONTROL
    | SensorBit.MOTOR_OUTPUTS
    | SensorBit.RC_RECEIVER
    | SensorBit.AHRS
    | SensorBit.BATTERY
    | SensorBit.PREARM_CHECK
)
_STACK_SENSORS: dict[Stack, SensorBit] = {
    Stack.PX4: _COMMON_SENSORS,
    Stack.ARDUPILOT: _COMMON_SENSORS | SensorBit.TERRAIN | SensorBit.LOGGING,
}


def stack_sensors(stack: Stack) -> SensorBit:
    """Sensors a healthy SITL of this stack reports present and enabled."""
    return _STACK_SENSORS[Stack(stack)]


def stack_normally_unhealthy(stack: Stack) -> SensorBit:
    """Bits a healthy, flyable SITL of this stack still reports unhealthy.

    PX4 SITL has no RC receiver, so RC_RECEIVER is enabled-but-unhealthy; ArduPilot SITL
    simulates RC and clears PREARM_CHECK once its pre-arm checks pass, so nothing.
    """
    if Stack(stack) is Stack.PX4:
        return SensorBit.RC_RECEIVER
    return SensorBit(0)
