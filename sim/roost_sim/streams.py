"""Which messages each simulated stack streams, how often and from when: the calibrated tables.

Why a table: the agent's health model is only as honest as the traffic it is tested
against, and the two stacks differ completely. Measured on the real firmware:

- **PX4 v1.16** (onboard link, ``mavlink start -m onboard``) streams about 400 frames/s
  unasked, from before its first heartbeat: :data:`PX4_STREAMS` (rate in Hz and the
  start-up step after which the message appears). HEARTBEAT stays at 1 Hz -- PX4 refuses
  SET_MESSAGE_INTERVAL for it -- so a mode change is seen up to a second later. Four
  messages PX4 also sends are left out because the MAVLink library cannot encode them:
  LINK_NODE_STATUS (1 Hz), TIME_ESTIMATE_TO_TARGET (0.5 Hz), EVENT and
  CURRENT_EVENT_SEQUENCE (about 1 and 0.3 Hz).
- **ArduCopter 4.7** streams nothing but HEARTBEAT (plus TIMESYNC every 10 s and one
  GPS_GLOBAL_ORIGIN + HOME_POSITION when its EKF origin is set) until a client asks:
  SET_MESSAGE_INTERVAL per message, or REQUEST_DATA_STREAM per group
  (:data:`ARDUPILOT_STREAM_GROUPS`, ArduCopter's grouping). It answers every request
  and streams at the requested rate; messages it can produce are in
  :data:`ARDUPILOT_MESSAGES`. A reboot forgets every request. With
  ``SimConfig.preset_streams`` it streams :data:`ARDUPILOT_PRESET_RATES` from boot, as
  with its stream-rate parameters (SRn_*) set, for clients that do not request streams.
  The grouping of EXTENDED_SYS_STATE into EXTENDED_STATUS is the simulator's choice.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from pymavlink.dialects.v20 import all as mavlink

from roost_api.meta import Stack


class Gate(StrEnum):
    """The start-up step after which a stream appears (see ``roost_sim.model.BootTimes``)."""

    POWER_ON = "power-on"  # raw sensors, from the first frame
    HEARTBEAT = "heartbeat"  # PX4's MAVLink app is fully up (about 1 s)
    ATTITUDE = "attitude"  # PX4: attitude messages (about 1.4 s)
    ESTIMATOR = "estimator"  # the estimator runs: battery, home, mode reports (about 2 s)
    POSITION = "position"  # a global position estimate exists
    SETPOINT = "setpoint"  # a position setpoint exists (PX4: from the first takeoff)


@dataclass(frozen=True)
class Stream:
    """One unrequested stream: ``hz`` from ``gate`` on."""

    hz: float
    gate: Gate = Gate.POWER_ON


def _id(name: str) -> int:
    value = getattr(mavlink, f"MAVLINK_MSG_ID_{name}")
    assert isinstance(value, int)
    return value


# PX4 v1.16 onboard link, rates measured over 20-48 s recordings.
PX4_STREAMS: dict[int, Stream] = {
    _id("ATTITUDE"): Stream(100.0, Gate.ATTITUDE),
    _id("ATTITUDE_QUATERNION"): Stream(50.0, Gate.ATTITUDE),
    _id("GLOBAL_POSITION_INT"): Stream(50.0, Gate.POSITION),
    _id("HIGHRES_IMU"): Stream(50.0),
    _id("LOCAL_POSITION_NED"): Stream(30.0),
    _id("ODOMETRY"): Stream(30.0),
    _id("ALTITUDE"): Stream(10.0),
    _id("ATTITUDE_TARGET"): Stream(10.0),
    _id("DISTANCE_SENSOR"): Stream(10.0),
    _id("POSITION_TARGET_LOCAL_NED"): Stream(10.0),
    _id("POSITION_TARGET_GLOBAL_INT"): Stream(10.0, Gate.SETPOINT),
    _id("SERVO_OUTPUT_RAW"): Stream(10.0),
    _id("TIMESYNC"): Stream(10.0),
    _id("VFR_HUD"): Stream(10.0),
    _id("GPS_RAW_INT"): Stream(8.0),
    _id("SYS_STATUS"): Stream(5.0),
    _id("EXTENDED_SYS_STATE"): Stream(5.0),
    _id("HEARTBEAT"): Stream(1.0, Gate.HEARTBEAT),
    _id("ESTIMATOR_STATUS"): Stream(1.0, Gate.HEARTBEAT),
    _id("MISSION_CURRENT"): Stream(1.0, Gate.HEARTBEAT),
    _id("OPEN_DRONE_ID_LOCATION"): Stream(1.0, Gate.HEARTBEAT),
    _id("OPEN_DRONE_ID_SYSTEM"): Stream(1.0, Gate.HEARTBEAT),
    _id("PING"): Stream(1.0, Gate.HEARTBEAT),
    _id("SCALED_PRESSURE"): Stream(1.0, Gate.HEARTBEAT),
    _id("SYSTEM_TIME"): Stream(1.0, Gate.HEARTBEAT),
    _id("BATTERY_STATUS"): Stream(0.5, Gate.ESTIMATOR),
    _id("CURRENT_MODE"): Stream(0.5, Gate.ESTIMATOR),
    _id("HOME_POSITION"): Stream(0.5, Gate.ESTIMATOR),
    _id("VIBRATION"): Stream(0.5, Gate.ESTIMATOR),
}

# What ArduCopter streams to a link nobody has asked anything on.
ARDUPILOT_UNREQUESTED: dict[int, Stream] = {
    _id("HEARTBEAT"): Stream(1.0),
    _id("TIMESYNC"): Stream(0.1, Gate.HEARTBEAT),
}
ARDUPILOT_TIMESYNC_START_S = 9.0  # its first unrequested TIMESYNC, seconds after boot

# Messages the ArduPilot flavour can stream on request (LOCAL_POSITION_NED only once the
# EKF has a position, as measured).
ARDUPILOT_MESSAGES: dict[int, Gate] = {
    _id("HEARTBEAT"): Gate.POWER_ON,
    _id("SYS_STATUS"): Gate.POWER_ON,
    _id("EXTENDED_SYS_STATE"): Gate.POWER_ON,
    _id("ATTITUDE"): Gate.POWER_ON,
    _id("GLOBAL_POSITION_INT"): Gate.POWER_ON,
    _id("LOCAL_POSITION_NED"): Gate.POSITION,
    _id("EKF_STATUS_REPORT"): Gate.POWER_ON,
    _id("GPS_RAW_INT"): Gate.POWER_ON,
    _id("VFR_HUD"): Gate.POWER_ON,
    _id("SYSTEM_TIME"): Gate.POWER_ON,
    _id("BATTERY_STATUS"): Gate.POWER_ON,
    _id("HOME_POSITION"): Gate.POSITION,
    _id("SERVO_OUTPUT_RAW"): Gate.POWER_ON,
    _id("VIBRATION"): Gate.POWER_ON,
    _id("TIMESYNC"): Gate.POWER_ON,
    _id("SCALED_PRESSURE"): Gate.POWER_ON,
}

# REQUEST_DATA_STREAM groups (MAV_DATA_STREAM_*), restricted to ARDUPILOT_MESSAGES.
ARDUPILOT_STREAM_GROUPS: dict[int, tuple[int, ...]] = {
    mavlink.MAV_DATA_STREAM_RAW_SENSORS: (_id("SCALED_PRESSURE"),),
    mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: (
        _id("SYS_STATUS"),
        _id("EXTENDED_SYS_STATE"),
        _id("GPS_RAW_INT"),
    ),
    mavlink.MAV_DATA_STREAM_RC_CHANNELS: (_id("SERVO_OUTPUT_RAW"),),
    mavlink.MAV_DATA_STREAM_POSITION: (_id("GLOBAL_POSITION_INT"), _id("LOCAL_POSITION_NED")),
    mavlink.MAV_DATA_STREAM_EXTRA1: (_id("ATTITUDE"),),
    mavlink.MAV_DATA_STREAM_EXTRA2: (_id("VFR_HUD"),),
    mavlink.MAV_DATA_STREAM_EXTRA3: (
        _id("SYSTEM_TIME"),
        _id("BATTERY_STATUS"),
        _id("EKF_STATUS_REPORT"),
        _id("VIBRATION"),
    ),
}

# As if SRn_* stream-rate parameters were set: the streams a health monitor needs.
ARDUPILOT_PRESET_RATES: dict[int, float] = {
    _id("SYS_STATUS"): 2.0,
    _id("EXTENDED_SYS_STATE"): 2.0,
    _id("ATTITUDE"): 50.0,
    _id("GLOBAL_POSITION_INT"): 10.0,
    _id("LOCAL_POSITION_NED"): 10.0,
    _id("EKF_STATUS_REPORT"): 1.0,
    _id("GPS_RAW_INT"): 1.0,
    _id("SYSTEM_TIME"): 1.0,
    _id("BATTERY_STATUS"): 1.0,
    _id("HOME_POSITION"): 1.0,
}


def default_rates(stack: Stack, *, preset: bool = False) -> dict[int, float]:
    """Unrequested rates by message id for ``stack`` (``preset``: ArduPilot SRn_* set)."""
    if Stack(stack) is Stack.PX4:
        return {msg_id: s.hz for msg_id, s in PX4_STREAMS.items()}
    rates = {msg_id: s.hz for msg_id, s in ARDUPILOT_UNREQUESTED.items()}
    if preset:
        rates.update(ARDUPILOT_PRESET_RATES)
    return rates


def gate_of(stack: Stack, msg_id: int) -> Gate:
    """The start-up step after which ``msg_id`` may be sent on ``stack``."""
    if Stack(stack) is Stack.PX4:
        stream = PX4_STREAMS.get(msg_id)
        return stream.gate if stream else Gate.POWER_ON
    if msg_id in ARDUPILOT_UNREQUESTED:
        return ARDUPILOT_UNREQUESTED[msg_id].gate
    return ARDUPILOT_MESSAGES.get(msg_id, Gate.POWER_ON)


def streamable(stack: Stack, msg_id: int) -> bool:
    """The stack can stream ``msg_id`` (SET_MESSAGE_INTERVAL is accepted for it)."""
    if Stack(stack) is Stack.PX4:
        return msg_id in PX4_STREAMS
    return msg_id in ARDUPILOT_MESSAGES
