"""The few parameters a simulated autopilot exposes over the MAVLink parameter protocol.

Clients such as MAVSDK read the takeoff altitude (PX4 ``MIS_TAKEOFF_ALT``, ArduCopter
``PILOT_TKOFF_ALT``) and may set it; real stacks then change behaviour, so these
parameters are views onto :class:`~roost_sim.model.SimConfig`, not a decorative table.

Integer parameters travel in PARAM_VALUE's float field the way each stack does it: PX4
copies the bytes (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE), ArduPilot converts the
number (PARAM_ENCODE_C_CAST). Unknown names get no reply, as on the real stacks.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from roost_api.meta import Stack
from roost_sim.model import SimConfig

REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
INT32 = mavlink.MAV_PARAM_TYPE_INT32


@dataclass(frozen=True)
class Param:
    """One parameter: its MAVLink type and how to read and write it."""

    name: str
    type: int
    get: Callable[[], float]
    set: Callable[[float], None] | None  # None: read-only


class ParamStore:
    """The parameter table of one simulated autopilot."""

    def __init__(self, stack: Stack, *, sysid: int, config: SimConfig) -> None:
        self.stack = Stack(stack)
        self._config = config
        self._params = self._table(sysid, config)

    def _table(self, sysid: int, c: SimConfig) -> list[Param]:
        def setter(attr: str, scale: float = 1.0) -> Callable[[float], None]:
            return lambda value: setattr(c, attr, value * scale)

        if self.stack is Stack.PX4:
            return [
                Param("MAV_SYS_ID", INT32, lambda: float(sysid), None),
                Param("MIS_TAKEOFF_ALT", REAL32, lambda: c.takeoff_alt_m, setter("takeoff_alt_m")),
                Param(
                    "MPC_LAND_SPEED",
                    REAL32,
                    lambda: c.landing(Stack.PX4).descent_mps,
                    setter("descent_rate_mps"),
                ),
                Param(
                    "COM_DISARM_LAND",
                    REAL32,
                    lambda: c.landing(Stack.PX4).disarm_s,
                    setter("auto_disarm_after_land_s"),
                ),
                Param("COM_DISARM_PRFLT", REAL32, lambda: c.idle_disarm_s, setter("idle_disarm_s")),
            ]
        return [
            Param("SYSID_THISMAV", INT32, lambda: float(sysid), None),
            Param(
                "PILOT_TKOFF_ALT",
                REAL32,
                lambda: c.takeoff_alt_m * 100,
                setter("takeoff_alt_m", 0.01),
            ),
            Param(
                "LAND_SPEED",
                INT32,
                lambda: round(c.landing(Stack.ARDUPILOT).descent_mps * 100),
                setter("descent_rate_mps", 0.01),
            ),
            Param("DISARM_DELAY", INT32, lambda: round(c.idle_disarm_s), setter("idle_disarm_s")),
        ]

    def names(self) -> list[str]:
        """Parameter names in index order."""
        return [p.name for p in self._params]

    def get(self, name: str) -> float:
        """Current value of a parameter by name."""
        return self._find(name).get()

    def _find(self, name: str) -> Param:
        for param in self._params:
            if param.name == name:
                return param
        raise KeyError(name)

    def _encode(self, param: Param) -> float:
        value = param.get()
        if param.type == INT32 and self.stack is Stack.PX4:
            return float(struct.unpack("<f", struct.pack("<i", int(value)))[0])
        return float(int(value)) if param.type == INT32 else float(value)

    def _decode(self, param: Param, wire: float) -> float:
        if param.type == INT32 and self.stack is Stack.PX4:
            return float(struct.unpack("<i", struct.pack("<f", wire))[0])
        return float(int(wire)) if param.type == INT32 else wire

    def _value(self, mav: Any, index: int) -> Any:
        param = self._params[index]
        return mav.param_value_encode(
            param.name.encode(), self._encode(param), param.type, len(self._params), index
        )

    def handle(self, msg: Any, mav: Any, sysid: int, component_id: int) -> list[Any]:
        """Replies (PARAM_VALUE messages) to one PARAM_* request addressed to us."""
        if msg.target_system not in (0, sysid) or msg.target_component not in (0, component_id):
            return []
        kind = msg.get_type()
        if kind == "PARAM_REQUEST_LIST":
            return [self._value(mav, i) for i in range(len(self._params))]
        if kind == "PARAM_REQUEST_READ":
            index = msg.param_index if msg.param_index >= 0 else self._index(msg.param_id)
            return [self._value(mav, index)] if 0 <= index < len(self._params) else []
        if kind == "PARAM_SET":
            index = self._index(msg.param_id)
            if index < 0:
                return []
            param = self._params[index]
            if param.set is not None:
                param.set(self._decode(param, msg.param_value))
            return [self._value(mav, index)]
        return []

    def _index(self, name: str) -> int:
        return next((i for i, p in enumerate(self._params) if p.name == name), -1)
