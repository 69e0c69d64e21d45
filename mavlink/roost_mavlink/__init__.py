"""MAVLink conventions of the flight stacks Roost flies, in one place.

The simulated autopilot encodes with these tables, the node agent decodes and commands
with them, and the operator displays them; none of them may spell a PX4 ``custom_mode``
or a sensor bit on its own. Pure Python: no pymavlink, no kopf, so every side can import
it cheaply and the tables are unit-tested without a link.

- :mod:`roost_mavlink.modes`: mode names <-> ``custom_mode``, DO_SET_MODE params, the
  hold/land/RTL mode per stack, which modes a pilot flies.
- :mod:`roost_mavlink.status`: heartbeat ``autopilot`` per stack, MAV_STATE, landed
  state, SYS_STATUS sensor bits and their failover severity.
- :mod:`roost_mavlink.connection`: the connection-URL scheme (``udp://`` = the agent
  listens, the autopilot sends there). The SITL port scheme is :mod:`roost_api.sitl`.

Every simulator speaks MAVLink 2. A pymavlink ``mavutil`` user must set the environment
variable ``MAVLINK20=1`` before importing ``pymavlink.mavutil`` (or call
``mavutil.set_dialect("common")`` after setting it), otherwise it parses MAVLink 1 only.
"""

from __future__ import annotations

from roost_mavlink.connection import PymavlinkDevice, pymavlink_device
from roost_mavlink.modes import (
    MAV_CMD_DO_SET_MODE,
    MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
    MAV_MODE_FLAG_SAFETY_ARMED,
    ModeIntent,
    custom_mode,
    custom_mode_from_set_mode,
    default_mode,
    hold_modes,
    intent_mode,
    is_manual_mode,
    mode_name,
    set_mode_params,
)
from roost_mavlink.status import (
    MavLandedState,
    MavState,
    SensorBit,
    SensorReport,
    SensorSeverity,
    api_landed_state,
    classify_sensors,
    heartbeat_autopilot,
    mav_state_name,
    sensor_severity,
    stack_from_heartbeat,
)

AGENT_COMPONENT_ID = 191  # MAV_COMP_ID_ONBOARD_COMPUTER: the agent's own component id
AUTOPILOT_COMPONENT_ID = 1  # MAV_COMP_ID_AUTOPILOT1
FORCE_DISARM_MAGIC = 21196  # COMPONENT_ARM_DISARM param2 that disarms even in flight

MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_NAV_LAND = 21
MAV_CMD_NAV_RETURN_TO_LAUNCH = 20
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MAV_CMD_REQUEST_MESSAGE = 512


class MavResult:
    """MAV_RESULT values of COMMAND_ACK."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4
    IN_PROGRESS = 5
    CANCELLED = 6
    COMMAND_LONG_ONLY = 7
    COMMAND_INT_ONLY = 8


_RESULT_NAMES = {
    value: f"MAV_RESULT_{name}"
    for name, value in vars(MavResult).items()
    if name.isupper() and isinstance(value, int)
}


def mav_result_name(result: int) -> str:
    """``MAV_RESULT_<NAME>`` of a COMMAND_ACK result (the number as text when unknown)."""
    return _RESULT_NAMES.get(result, str(result))


__all__ = [
    "AGENT_COMPONENT_ID",
    "AUTOPILOT_COMPONENT_ID",
    "FORCE_DISARM_MAGIC",
    "MAV_CMD_COMPONENT_ARM_DISARM",
    "MAV_CMD_DO_SET_MODE",
    "MAV_CMD_NAV_LAND",
    "MAV_CMD_NAV_RETURN_TO_LAUNCH",
    "MAV_CMD_NAV_TAKEOFF",
    "MAV_CMD_REQUEST_MESSAGE",
    "MAV_CMD_SET_MESSAGE_INTERVAL",
    "MAV_MODE_FLAG_CUSTOM_MODE_ENABLED",
    "MAV_MODE_FLAG_SAFETY_ARMED",
    "MavLandedState",
    "MavResult",
    "MavState",
    "ModeIntent",
    "PymavlinkDevice",
    "SensorBit",
    "SensorReport",
    "SensorSeverity",
    "api_landed_state",
    "classify_sensors",
    "custom_mode",
    "custom_mode_from_set_mode",
    "default_mode",
    "heartbeat_autopilot",
    "hold_modes",
    "intent_mode",
    "is_manual_mode",
    "mav_result_name",
    "mav_state_name",
    "mode_name",
    "pymavlink_device",
    "sensor_severity",
    "set_mode_params",
    "stack_from_heartbeat",
]
