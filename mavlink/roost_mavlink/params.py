"""The MAVLink parameter protocol's value encoding, as PX4 and ArduPilot write it.

PARAM_VALUE and PARAM_SET carry every value in one 32-bit float field, with the
parameter's MAV_PARAM_TYPE beside it. An integer travels in one of two encodings: PX4
copies the integer's bytes into the float (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE;
the recorded PX4 v1.16 CAL_ACC0_ID arrives as 1.837e-39), ArduPilot converts the number
(MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST; the recorded ArduCopter INS_GYR_ID arrives
as 2752772.0). The agent (``roost_agent.params``) and the simulator (``roost_sim.params``)
both encode and decode with these functions, so the two sides cannot disagree by
construction; the tests check them against the recorded traffic instead.
"""

from __future__ import annotations

import math
import struct
from enum import IntEnum

from roost_api.core import Stack


class ParamType(IntEnum):
    """MAV_PARAM_TYPE: the types PARAM_VALUE can carry in its float field."""

    UINT8 = 1
    INT8 = 2
    UINT16 = 3
    INT16 = 4
    UINT32 = 5
    INT32 = 6
    REAL32 = 9


INT_FORMAT = {
    ParamType.UINT8: "<B",
    ParamType.INT8: "<b",
    ParamType.UINT16: "<H",
    ParamType.INT16: "<h",
    ParamType.UINT32: "<I",
    ParamType.INT32: "<i",
}
INT_RANGE = {
    ParamType.UINT8: (0, 0xFF),
    ParamType.INT8: (-0x80, 0x7F),
    ParamType.UINT16: (0, 0xFFFF),
    ParamType.INT16: (-0x8000, 0x7FFF),
    ParamType.UINT32: (0, 0xFFFFFFFF),
    ParamType.INT32: (-0x80000000, 0x7FFFFFFF),
}
FLOAT32_MAX = 3.4028234663852886e38
MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE = 1 << 4
MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST = 1 << 17


def float32(value: float) -> float:
    """``value`` as a 32-bit float holds it (what PARAM_VALUE carries)."""
    return float(struct.unpack("<f", struct.pack("<f", value))[0])


def bytewise_default(stack: Stack) -> bool:
    """How the stack encodes integers when AUTOPILOT_VERSION has not said: PX4 bytewise,
    ArduPilot by C cast."""
    return stack is Stack.PX4


def bytewise_from_capabilities(capabilities: int, stack: Stack) -> bool:
    """The encoding AUTOPILOT_VERSION's capability bits announce (the stack's default
    when they announce neither)."""
    if capabilities & MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE:
        return True
    if capabilities & MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST:
        return False
    return bytewise_default(stack)


def known_type(raw: int) -> ParamType | None:
    """The parameter type of a PARAM_VALUE (None: one PARAM_VALUE cannot carry it)."""
    try:
        return ParamType(raw)
    except ValueError:
        return None


def to_wire(value: float, ptype: ParamType, *, bytewise: bool) -> float:
    """The float PARAM_SET / PARAM_VALUE carries for ``value`` of type ``ptype``."""
    if ptype is ParamType.REAL32:
        return float32(value)
    if not bytewise:
        return float(int(value))
    raw = struct.pack(INT_FORMAT[ptype], int(value)).ljust(4, b"\0")
    return float(struct.unpack("<f", raw)[0])


def from_wire(wire: float, ptype: ParamType, *, bytewise: bool) -> float:
    """The value a PARAM_VALUE's float field carries for a parameter of type ``ptype``."""
    if ptype is ParamType.REAL32:
        return wire
    if not bytewise:
        return float(int(wire)) if math.isfinite(wire) else wire
    raw = struct.pack("<f", wire)
    size = struct.calcsize(INT_FORMAT[ptype])
    return float(struct.unpack(INT_FORMAT[ptype], raw[:size])[0])


def saturate(value: float, ptype: ParamType) -> float:
    """``value`` as a parameter of ``ptype`` holds it: a 32-bit float, or an integer
    truncated and clamped to the type's range."""
    if ptype is ParamType.REAL32:
        return float32(value)
    low, high = INT_RANGE[ptype]
    whole = int(value) if math.isfinite(value) else 0
    return float(min(max(whole, low), high))
