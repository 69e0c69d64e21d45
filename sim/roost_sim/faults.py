"""The faults a simulated autopilot can show, and how each looks on the wire.

One table for the API, the control socket and the CLI, so ``roost-sim fault fc1 sensor
--value gyro`` and ``sim.inject(FaultKind.SENSOR, "gyro")`` cannot mean different things.

========  =================  ==========================================================
kind      value              on the wire
========  =================  ==========================================================
silence   --                 nothing is sent and nothing is read (cable cut, dead FC)
freeze    --                 streams continue at their rates, but every message repeats
                             the values of the freeze instant: identical time_boot_ms,
                             attitude, position, SYSTEM_TIME; commands go unanswered.
                             This is a hung main loop whose MAVLink thread still runs.
sensor    sensor name        that SYS_STATUS bit turns enabled-but-unhealthy (repeatable;
          (default gyro)     armed with a critical one the stack reports CRITICAL)
state     MAV_STATE name     heartbeat system_status forced to it (CRITICAL, EMERGENCY..)
          (default CRITICAL)
reboot    seconds silent     silent for that long, then boots again: time_boot_ms from 0,
          (default 0)        MAV_STATE BOOT, disarmed, on the ground, default mode
garbage   bytes per second   random bytes and corrupted copies of real frames between
          (default 2000)     frames
loss      percent            each frame out and each chunk in dropped with that chance
jitter    milliseconds       each outgoing frame delayed uniformly 0..J ms, order kept
spoof     foreign sysid      10 Hz HEARTBEAT (EMERGENCY) + ATTITUDE from another sysid,
          (default sysid+100) and EMERGENCY heartbeats from a non-autopilot component
                             (gimbal, autopilot=INVALID) of our own sysid
battery   --                 the battery fails: voltage drops, charge reads empty within
                             4 s, health bit clears, CRITICAL; PX4 then holds 5 s and
                             lands (see :mod:`roost_sim.battery`; a shared battery
                             fails for every autopilot on it)
lag       percent of speed   the vehicle flies slower than planned (wind, a weak
          (default 50)       battery): horizontal speed, acceleration and climb are
                             scaled to that percentage until cleared
========  =================  ==========================================================

``clear`` removes one kind or all of them (a pending reboot is not undone; a cleared
battery fault is a fresh pack).

Numeric values must be finite and within :data:`NUMERIC_RANGES`: an infinite jitter
would delay every frame forever, which no ``clear`` could undo. :func:`check_value` is
the one judge of a value, used by :meth:`SimulatedAutopilot.inject` and, before anything
is sent, by the ``roost fault`` and ``roost-sim fault`` command lines.
"""

from __future__ import annotations

import math
from enum import StrEnum

from roost_mavlink.status import MavState, SensorBit, sensor_from_name


class FaultKind(StrEnum):
    """Injectable fault kinds."""

    SILENCE = "silence"
    FREEZE = "freeze"
    SENSOR = "sensor"
    STATE = "state"
    REBOOT = "reboot"
    GARBAGE = "garbage"
    LOSS = "loss"
    JITTER = "jitter"
    SPOOF = "spoof"
    BATTERY = "battery"
    LAG = "lag"


DEFAULT_GARBAGE_BYTES_PER_S = 2000.0
SPOOF_SYSID_OFFSET = 100


def _whole_number(value: float) -> int:
    if not math.isfinite(value) or not value.is_integer():
        raise ValueError(f"{value!r} is not a whole number")
    return int(value)


def parse_sensor(value: str | float | None) -> SensorBit:
    """A sensor given by name (``gyro``) or bit value; gyro when omitted."""
    if value is None or value == "":
        return SensorBit.GYRO
    if isinstance(value, float):
        value = _whole_number(value)
    if isinstance(value, int) or str(value).isdigit() or str(value).startswith("0x"):
        bit = SensorBit(int(str(value), 0))
        if bin(int(bit)).count("1") != 1:
            raise ValueError(f"sensor value {value!r} is not a single bit")
        return bit
    return sensor_from_name(str(value))


def parse_state(value: str | float | None) -> MavState:
    """A MAV_STATE given by name (``EMERGENCY``) or number; CRITICAL when omitted."""
    if value is None or value == "":
        return MavState.CRITICAL
    if isinstance(value, float):
        value = _whole_number(value)
    if isinstance(value, int) or str(value).isdigit():
        return MavState(int(value))
    try:
        return MavState[str(value).upper()]
    except KeyError:
        raise ValueError(f"unknown MAV_STATE {value!r}") from None


NUMERIC_RANGES: dict[FaultKind, tuple[float, float, str]] = {
    FaultKind.REBOOT: (0, 3600, "seconds silent"),
    FaultKind.GARBAGE: (0, 100_000, "bytes per second"),
    FaultKind.LOSS: (0, 100, "percent"),
    FaultKind.JITTER: (0, 10_000, "milliseconds"),
    FaultKind.SPOOF: (1, 255, "a system id"),
    FaultKind.LAG: (1, 100, "percent of the normal speed"),
}
VALUELESS = frozenset({FaultKind.SILENCE, FaultKind.FREEZE, FaultKind.BATTERY})


def parse_number(kind: FaultKind, value: str | float | None, default: float) -> float:
    """The number for reboot, garbage, loss, jitter, spoof or lag: finite and in range."""
    if value is None or value == "":
        return default
    low, high, unit = NUMERIC_RANGES[kind]
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{kind} takes a number ({unit}), not {value!r}") from None
    if not math.isfinite(number) or not low <= number <= high:
        raise ValueError(f"{kind} value {value!r} out of range: {unit} from {low:g} to {high:g}")
    if kind is FaultKind.SPOOF and not number.is_integer():
        raise ValueError(f"spoof takes a whole system id, not {value!r}")
    return number


def parse_sysid(value: str | float | None, default: int) -> int:
    """A MAVLink system id 1..255 for ``spoof``."""
    return int(parse_number(FaultKind.SPOOF, value, default))


def check_value(kind: FaultKind | str, value: str | float | None) -> None:
    """Raise ValueError (with the reason) unless ``value`` is valid for ``kind``."""
    kind = FaultKind(kind)
    try:
        if kind in VALUELESS:
            if value is not None and value != "":
                raise ValueError(f"{kind} takes no value")
        elif kind is FaultKind.SENSOR:
            parse_sensor(value)
        elif kind is FaultKind.STATE:
            parse_state(value)
        else:
            parse_number(kind, value, 0.0)
    except KeyError as error:
        raise ValueError(error.args[0] if error.args else str(error)) from None
