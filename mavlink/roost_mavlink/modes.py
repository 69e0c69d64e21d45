"""Flight modes of PX4 and ArduCopter: names, ``custom_mode`` numbers, DO_SET_MODE params.

Why one module: the simulator encodes modes into heartbeats, the agent decodes them and
commands hold/land/RTL, and the operator shows them. If each spelled PX4's bit-packed
``custom_mode`` on its own, a typo would make the safety routine wait for a mode the
autopilot never reports. Everything here is pure and keyed by :class:`roost_api.core.Stack`.

PX4 packs ``custom_mode = (sub_mode << 24) | (main_mode << 16)`` (``px4_custom_mode.h``);
mode names follow PX4/QGroundControl spelling (``AUTO.LOITER`` is what PX4 calls "Hold").
The PX4 table is complete for v1.16: main modes 1-10 (9 SIMPLE is reserved, 10 is flight
termination), the AUTO sub modes up to the external (ROS 2) modes and the POSCTL sub
modes. ArduCopter's ``custom_mode`` is the plain mode number (``mode.h``), complete for
ArduCopter 4.x (numbers 8, 10 and 12 are retired). A value outside the tables is named by
its numbers (``UNKNOWN(main=11,sub=0)``, ``UNKNOWN(42)``) so an operator can still look
it up, and it is never mistaken for a known mode.

``MAV_CMD_DO_SET_MODE`` (176) carries param1 = ``MAV_MODE_FLAG_CUSTOM_MODE_ENABLED`` (1);
PX4 reads param2 = main mode and param3 = sub mode; ArduPilot reads param2 = mode number.
"""

from __future__ import annotations

from enum import StrEnum

from roost_api.core import Stack

MAV_MODE_FLAG_CUSTOM_MODE_ENABLED = 1
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_CMD_DO_SET_MODE = 176


def px4_custom_mode(main_mode: int, sub_mode: int = 0) -> int:
    """Pack a PX4 main/sub mode pair into the heartbeat's ``custom_mode``."""
    if not (0 <= main_mode <= 0xFF and 0 <= sub_mode <= 0xFF):
        raise ValueError(f"PX4 main/sub mode out of range: {main_mode}/{sub_mode}")
    return (sub_mode << 24) | (main_mode << 16)


def px4_split_custom_mode(custom_mode: int) -> tuple[int, int]:
    """Unpack PX4 ``custom_mode`` into (main_mode, sub_mode)."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


class Px4MainMode:
    """PX4 ``PX4_CUSTOM_MAIN_MODE_*`` numbers."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7
    RATTITUDE = 8  # RATTITUDE_LEGACY: removed from the firmware, kept so old logs decode
    SIMPLE = 9  # reserved by PX4, never flown
    TERMINATION = 10  # flight termination: motors off, parachute if fitted


class Px4AutoSubMode:
    """PX4 ``PX4_CUSTOM_SUB_MODE_AUTO_*`` numbers (sub modes of main mode AUTO)."""

    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6
    FOLLOW_TARGET = 8
    PRECLAND = 9
    VTOL_TAKEOFF = 10
    EXTERNAL1 = 11  # EXTERNAL1..EXTERNAL8 (11-18): modes registered by ROS 2 components


class Px4PosctlSubMode:
    """PX4 ``PX4_CUSTOM_SUB_MODE_POSCTL_*`` numbers (sub modes of main mode POSCTL)."""

    POSCTL = 0
    ORBIT = 1
    SLOW = 2


PX4_EXTERNAL_MODES = 8


# PX4 name -> custom_mode. Non-AUTO main modes have sub mode 0 on the wire.
PX4_MODES: dict[str, int] = {
    "MANUAL": px4_custom_mode(Px4MainMode.MANUAL),
    "ALTCTL": px4_custom_mode(Px4MainMode.ALTCTL),
    "POSCTL": px4_custom_mode(Px4MainMode.POSCTL),
    "ACRO": px4_custom_mode(Px4MainMode.ACRO),
    "OFFBOARD": px4_custom_mode(Px4MainMode.OFFBOARD),
    "STABILIZED": px4_custom_mode(Px4MainMode.STABILIZED),
    "RATTITUDE": px4_custom_mode(Px4MainMode.RATTITUDE),
    "SIMPLE": px4_custom_mode(Px4MainMode.SIMPLE),
    "TERMINATION": px4_custom_mode(Px4MainMode.TERMINATION),
    "POSCTL.ORBIT": px4_custom_mode(Px4MainMode.POSCTL, Px4PosctlSubMode.ORBIT),
    "POSCTL.SLOW": px4_custom_mode(Px4MainMode.POSCTL, Px4PosctlSubMode.SLOW),
    "AUTO.READY": px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.READY),
    "AUTO.TAKEOFF": px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.TAKEOFF),
    "AUTO.LOITER": px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.LOITER),
    "AUTO.MISSION": px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.MISSION),
    "AUTO.RTL": px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.RTL),
    "AUTO.LAND": px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.LAND),
    "AUTO.FOLLOW_TARGET": px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.FOLLOW_TARGET),
    "AUTO.PRECLAND": px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.PRECLAND),
    "AUTO.VTOL_TAKEOFF": px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.VTOL_TAKEOFF),
    **{
        f"AUTO.EXTERNAL{i + 1}": px4_custom_mode(Px4MainMode.AUTO, Px4AutoSubMode.EXTERNAL1 + i)
        for i in range(PX4_EXTERNAL_MODES)
    },
}

# ArduCopter mode name -> number (custom_mode).
ARDUCOPTER_MODES: dict[str, int] = {
    "STABILIZE": 0,
    "ACRO": 1,
    "ALT_HOLD": 2,
    "AUTO": 3,
    "GUIDED": 4,
    "LOITER": 5,
    "RTL": 6,
    "CIRCLE": 7,
    "LAND": 9,
    "DRIFT": 11,
    "SPORT": 13,
    "FLIP": 14,
    "AUTOTUNE": 15,
    "POSHOLD": 16,
    "BRAKE": 17,
    "THROW": 18,
    "AVOID_ADSB": 19,
    "GUIDED_NOGPS": 20,
    "SMART_RTL": 21,
    "FLOWHOLD": 22,
    "FOLLOW": 23,
    "ZIGZAG": 24,
    "SYSTEMID": 25,
    "AUTOROTATE": 26,
    "AUTO_RTL": 27,
    "TURTLE": 28,
}

_MODES: dict[Stack, dict[str, int]] = {Stack.PX4: PX4_MODES, Stack.ARDUPILOT: ARDUCOPTER_MODES}
_NAMES: dict[Stack, dict[int, str]] = {
    stack: {number: name for name, number in table.items()} for stack, table in _MODES.items()
}

# Modes in which a pilot flies the vehicle through the sticks. After a failover the thesis
# switched the bridge but left such a pilot in control (no hold/land). ArduCopter LOITER is
# stick-steerable too, but it is NOT listed: without a radio its throttle rests low and it
# descends, so an autopilot found in LOITER must get the safety routine (whose hold is
# BRAKE), not be left to a pilot who may not exist.
_MANUAL_MODES: dict[Stack, frozenset[str]] = {
    Stack.PX4: frozenset(
        {
            "MANUAL",
            "ALTCTL",
            "POSCTL",
            "POSCTL.SLOW",
            "POSCTL.ORBIT",
            "ACRO",
            "STABILIZED",
            "RATTITUDE",
        }
    ),
    Stack.ARDUPILOT: frozenset(
        {"STABILIZE", "ACRO", "ALT_HOLD", "DRIFT", "SPORT", "FLIP", "POSHOLD", "FLOWHOLD"}
    ),
}


class ModeIntent(StrEnum):
    """What the agent wants the autopilot to do, independent of stack."""

    HOLD = "hold"
    LAND = "land"
    RETURN_TO_LAUNCH = "rtl"
    TAKEOFF = "takeoff"


# ArduCopter takes off in GUIDED (NAV_TAKEOFF). Its hold is BRAKE (stops and holds
# position and altitude with no pilot input), never LOITER (follows the throttle stick,
# which rests low without a radio: measured 2.45 m/s down into the ground). PX4's
# AUTO.LOITER holds position and altitude on its own.
_INTENT_MODES: dict[Stack, dict[ModeIntent, str]] = {
    Stack.PX4: {
        ModeIntent.HOLD: "AUTO.LOITER",
        ModeIntent.LAND: "AUTO.LAND",
        ModeIntent.RETURN_TO_LAUNCH: "AUTO.RTL",
        ModeIntent.TAKEOFF: "AUTO.TAKEOFF",
    },
    Stack.ARDUPILOT: {
        ModeIntent.HOLD: "BRAKE",
        ModeIntent.LAND: "LAND",
        ModeIntent.RETURN_TO_LAUNCH: "RTL",
        ModeIntent.TAKEOFF: "GUIDED",
    },
}

# What each stack reports right after boot, before anyone changes mode.
_DEFAULT_MODES: dict[Stack, str] = {Stack.PX4: "AUTO.LOITER", Stack.ARDUPILOT: "STABILIZE"}


def mode_names(stack: Stack) -> list[str]:
    """All mode names known for ``stack``."""
    return list(_MODES[Stack(stack)])


def custom_mode(stack: Stack, name: str) -> int:
    """``custom_mode`` for a mode name; raises KeyError for names the stack lacks."""
    try:
        return _MODES[Stack(stack)][name.upper()]
    except KeyError:
        raise KeyError(f"{stack} has no mode named {name!r}") from None


def mode_name(stack: Stack, custom_mode_value: int) -> str:
    """Name of a heartbeat ``custom_mode``; unknown values are named by their numbers.

    PX4: ``UNKNOWN(main=M,sub=S)``, or ``UNKNOWN(0x...)`` when bits outside the main/sub
    bytes are set; ArduCopter: ``UNKNOWN(N)``.
    """
    stack = Stack(stack)
    names = _NAMES[stack]
    if custom_mode_value in names:
        return names[custom_mode_value]
    if stack is Stack.PX4:
        if custom_mode_value & ~0xFFFF0000:
            return f"UNKNOWN(0x{custom_mode_value:08x})"
        main, sub = px4_split_custom_mode(custom_mode_value)
        return f"UNKNOWN(main={main},sub={sub})"
    return f"UNKNOWN({custom_mode_value})"


def hold_modes(stack: Stack) -> tuple[str, ...]:
    """Hold modes that need no pilot input, best first (ArduCopter: BRAKE, then GUIDED)."""
    if Stack(stack) is Stack.ARDUPILOT:
        return ("BRAKE", "GUIDED")
    return (intent_mode(stack, ModeIntent.HOLD),)


def intent_mode(stack: Stack, intent: ModeIntent) -> str:
    """The mode name that carries out ``intent`` on ``stack`` (hold -> AUTO.LOITER/BRAKE)."""
    return _INTENT_MODES[Stack(stack)][ModeIntent(intent)]


def default_mode(stack: Stack) -> str:
    """The mode a freshly booted autopilot of this stack reports."""
    return _DEFAULT_MODES[Stack(stack)]


def is_manual_mode(stack: Stack, name: str) -> bool:
    """True when a pilot flies in this mode (the agent then skips the safety routine)."""
    return name.upper() in _MANUAL_MODES[Stack(stack)]


def set_mode_params(
    stack: Stack, name: str
) -> tuple[float, float, float, float, float, float, float]:
    """The seven COMMAND_LONG params of MAV_CMD_DO_SET_MODE that select mode ``name``."""
    value = custom_mode(stack, name)
    flag = float(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
    if Stack(stack) is Stack.PX4:
        main, sub = px4_split_custom_mode(value)
        return (flag, float(main), float(sub), 0.0, 0.0, 0.0, 0.0)
    return (flag, float(value), 0.0, 0.0, 0.0, 0.0, 0.0)


def custom_mode_from_set_mode(stack: Stack, param1: float, param2: float, param3: float) -> int:
    """Decode DO_SET_MODE params into ``custom_mode`` (the autopilot's side of the above).

    Raises ValueError when the custom-mode flag is missing or the mode is unknown, which
    is what makes an autopilot answer MAV_RESULT_DENIED/UNSUPPORTED.
    """
    if not int(param1) & MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        raise ValueError("DO_SET_MODE without MAV_MODE_FLAG_CUSTOM_MODE_ENABLED")
    stack = Stack(stack)
    if stack is Stack.PX4:
        main, sub = int(param2), int(param3)
        keeps_sub = main in (Px4MainMode.AUTO, Px4MainMode.POSCTL)
        value = px4_custom_mode(main, sub if keeps_sub else 0)
    else:
        value = int(param2)
    if value not in _NAMES[stack]:
        raise ValueError(f"{stack} has no mode with custom_mode {value:#x}")
    return value
