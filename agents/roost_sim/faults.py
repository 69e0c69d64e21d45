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
========  =================  ==========================================================

``clear`` removes one kind or all of them (a pending reboot is not undone).

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


DEFAULT_GARBAGE_BYTES_PER_S = 2000.0
SPOOF_SYSID_OFFSET = 100


def parse_sensor(value: str | int | None) -> SensorBit:
    """A sensor given by name (``gyro``) or bit value; gyro when omitted."""
    if value is None or value == "":
        return SensorBit.GYRO
    if isinstance(value, int) or str(value).isdigit() or str(value).startswith("0x"):
        bit = SensorBit(int(str(value), 0))
        if bin(int(bit)).count("1") != 1:
            raise ValueError(f"sensor value {value!r} is not a single bit")
        return bit
    return sensor_from_name(str(value))


def parse_state(value: str | int | None) -> MavState:
    """A MAV_STATE given by name (``EMERGENCY``) or number; CRITICAL when omitted."""
    if value is None or value == "":
        return MavState.CRITICAL
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
}
VALUELESS = frozenset({FaultKind.SILENCE, FaultKind.FREEZE})


def parse_number(kind: FaultKind, value: str | float | None, default: float) -> float:
    """The number for reboot, garbage, loss, jitter or spoof: finite and in range."""
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


def check_value(kind: FaultKind | str, value: str | float | None) -> None:
    """Raise ValueError (with the reason) unless ``value`` is valid for ``kind``."""
    kind = FaultKind(kind)
    try:
        if kind in VALUELESS:
            if value is not None and value != "":
                raise ValueError(f"{kind} takes no value")
        elif kind is FaultKind.SENSOR:
            parse_sensor(value if not isinstance(value, float) else int(value))
        elif kind is FaultKind.STATE:
            parse_state(value if not isinstance(value, float) else int(value))
        else:
            parse_number(kind, value, 0.0)
    except KeyError as error:
        raise ValueError(error.args[0] if error.args else str(error)) from None
