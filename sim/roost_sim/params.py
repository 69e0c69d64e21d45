"""The few parameters a simulated autopilot exposes over the MAVLink parameter protocol.

Clients such as MAVSDK read the takeoff altitude (PX4 ``MIS_TAKEOFF_ALT``, ArduCopter
``PILOT_TKOFF_ALT``) and may set it; real stacks then change behaviour, so these
parameters are views onto :class:`~roost_sim.model.SimConfig`, not a decorative table.

Beside those, the real parameters Roost declares in tests and benchmarks are stored as
values (RC calibration, fence parameters), with each firmware's names and types: PX4
declares integers INT32 and everything else FLOAT; ArduPilot sends each parameter's own
type (AP_Int8 as INT8, AP_Int16 as INT16, AP_Float as REAL32), as the recorded ArduCopter
traffic shows (EK3_SRC1_POSXY type 2, MIS_TOTAL type 4, INS_GYR_ID type 6).

Integer parameters travel in PARAM_VALUE's float field the way each stack does it
(:mod:`roost_mavlink.params`, which the agent uses too): PX4 copies the bytes, ArduPilot
converts the number.
ArduPilot numbers an unrequested value (a write's answer) 65535, PX4 its real index.
Unknown names get no reply, as on the real stacks.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from roost_api.meta import Stack
from roost_mavlink.params import ParamType, bytewise_default, from_wire, saturate, to_wire
from roost_sim.model import SimConfig

REAL32 = ParamType.REAL32
INT32 = ParamType.INT32
INT16 = ParamType.INT16
INT8 = ParamType.INT8


@dataclass(frozen=True)
class Param:
    """One parameter: its MAVLink type and how to read and write it."""

    name: str
    type: ParamType
    get: Callable[[], float]
    set: Callable[[float], None] | None  # None: read-only


def _stored(values: dict[str, float], name: str, ptype: ParamType, default: float) -> Param:
    """A parameter the simulation keeps but does not act on (a value in a table)."""
    values[name] = default

    def store(value: float) -> None:
        values[name] = value

    return Param(name, ptype, lambda: values[name], store)


def _px4_extras(values: dict[str, float]) -> list[Param]:
    """Real PX4 v1.16 parameters the simulation stores: the RC calibration of 18
    channels (RCn_MIN/TRIM/MAX/REV/DZ, all FLOAT in PX4), the channel count and mapping
    (RC_CHAN_CNT, RC_MAP_*: INT32) and the geofence's."""
    params = []
    for n in range(1, 19):
        for suffix, default in (("MIN", 1000.0), ("TRIM", 1500.0), ("MAX", 2000.0)):
            params.append(_stored(values, f"RC{n}_{suffix}", REAL32, default))
        params.append(_stored(values, f"RC{n}_REV", REAL32, 1.0))
        params.append(_stored(values, f"RC{n}_DZ", REAL32, 0.0))
    params += [
        _stored(values, "RC_CHAN_CNT", INT32, 0.0),
        *(
            _stored(values, f"RC_MAP_{axis}", INT32, 0.0)
            for axis in ("ROLL", "PITCH", "YAW", "THROTTLE")
        ),
        _stored(values, "GF_ACTION", INT32, 2.0),
        _stored(values, "GF_MAX_HOR_DIST", REAL32, 0.0),
        _stored(values, "GF_MAX_VER_DIST", REAL32, 0.0),
    ]
    return params


def _ardupilot_extras(values: dict[str, float]) -> list[Param]:
    """Real ArduCopter parameters the simulation stores: the RC input calibration of
    16 channels (RCn_MIN/TRIM/MAX/DZ/OPTION are AP_Int16, RCn_REVERSED AP_Int8) and the
    fence's (FENCE_ENABLE/TYPE/ACTION AP_Int8, FENCE_ALT_MAX/RADIUS/MARGIN AP_Float)."""
    params = []
    for n in range(1, 17):
        for suffix, default in (("MIN", 1100.0), ("TRIM", 1500.0), ("MAX", 1900.0)):
            params.append(_stored(values, f"RC{n}_{suffix}", INT16, default))
        params.append(_stored(values, f"RC{n}_REVERSED", INT8, 0.0))
        params.append(_stored(values, f"RC{n}_DZ", INT16, 0.0))
        params.append(_stored(values, f"RC{n}_OPTION", INT16, 0.0))
    params += [
        _stored(values, "FENCE_ENABLE", INT8, 0.0),
        _stored(values, "FENCE_TYPE", INT8, 7.0),
        _stored(values, "FENCE_ACTION", INT8, 1.0),
        _stored(values, "FENCE_ALT_MAX", REAL32, 100.0),
        _stored(values, "FENCE_RADIUS", REAL32, 300.0),
        _stored(values, "FENCE_MARGIN", REAL32, 2.0),
    ]
    return params


class ParamStore:
    """The parameter table of one simulated autopilot."""

    def __init__(self, stack: Stack, *, sysid: int, config: SimConfig) -> None:
        self.stack = Stack(stack)
        self._config = config
        self._values: dict[str, float] = {}
        self._bytewise = bytewise_default(self.stack)
        self._params = self._table(sysid, config)
        self._by_name = {p.name: i for i, p in enumerate(self._params)}

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
                *_px4_extras(self._values),
            ]
        # ArduCopter's types: SYSID_THISMAV and LAND_SPEED are AP_Int16, DISARM_DELAY
        # AP_Int8, PILOT_TKOFF_ALT AP_Float (centimetres).
        return [
            Param("SYSID_THISMAV", INT16, lambda: float(sysid), None),
            Param(
                "PILOT_TKOFF_ALT",
                REAL32,
                lambda: c.takeoff_alt_m * 100,
                setter("takeoff_alt_m", 0.01),
            ),
            Param(
                "LAND_SPEED",
                INT16,
                lambda: round(c.landing(Stack.ARDUPILOT).descent_mps * 100),
                setter("descent_rate_mps", 0.01),
            ),
            Param("DISARM_DELAY", INT8, lambda: round(c.idle_disarm_s), setter("idle_disarm_s")),
            *_ardupilot_extras(self._values),
        ]

    def names(self) -> list[str]:
        """Parameter names in index order."""
        return [p.name for p in self._params]

    def get(self, name: str) -> float:
        """Current value of a parameter by name."""
        return self._find(name).get()

    def _find(self, name: str) -> Param:
        index = self._by_name.get(name)
        if index is None:
            raise KeyError(name)
        return self._params[index]

    def set(self, name: str, value: float) -> None:
        """Change a parameter as another client's PARAM_SET would (tests, fault drills)."""
        param = self._find(name)
        if param.set is None:
            raise KeyError(f"{name} is read-only")
        param.set(self._fit(param, value))

    def _encode(self, param: Param) -> float:
        return to_wire(param.get(), param.type, bytewise=self._bytewise)

    def _decode(self, param: Param, wire: float) -> float:
        return from_wire(wire, param.type, bytewise=self._bytewise)

    @staticmethod
    def _fit(param: Param, value: float) -> float:
        """The value as the parameter's type holds it (an integer saturates)."""
        return saturate(value, param.type)

    def _value(self, mav: Any, index: int, *, listed: bool = True) -> Any:
        """PARAM_VALUE of one parameter; ``listed``: with its index (ArduPilot sends
        65535 in a value it sends unrequested, e.g. the answer to a write)."""
        param = self._params[index]
        if not listed and self.stack is Stack.ARDUPILOT:
            index = 0xFFFF
        return mav.param_value_encode(
            param.name.encode(), self._encode(param), param.type, len(self._params), index
        )

    def handle(self, msg: Any, mav: Any, sysid: int, component_id: int) -> list[Any]:
        """Replies (PARAM_VALUE messages) to one PARAM_* request addressed to us.

        PARAM_SET is answered with the value the parameter now holds, written or not (a
        read-only one keeps its value); a name the firmware lacks gets no answer."""
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
                param.set(self._fit(param, self._decode(param, msg.param_value)))
            return [self._value(mav, index, listed=False)]
        return []

    def _index(self, name: str) -> int:
        return self._by_name.get(name, -1)
