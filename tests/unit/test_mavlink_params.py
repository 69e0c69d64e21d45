"""roost_mavlink.params: the parameter protocol's value encodings, checked against
recorded real traffic (PX4 v1.16 and ArduCopter PARAM_VALUEs) when the recordings are
present (``$ROOST_CAPTURES_DIR``, else ``shared/captures`` beside the repository;
skipped otherwise, read in place)."""

from __future__ import annotations

import math
import os
import struct

os.environ.setdefault("MAVLINK20", "1")

import pytest
from pymavlink import mavutil

from roost_api.core import Stack
from roost_mavlink.params import (
    ParamType,
    bytewise_from_capabilities,
    from_wire,
    saturate,
    to_wire,
)
from tests.support.captures import capture

F, I32 = ParamType.REAL32, ParamType.INT32


@pytest.mark.parametrize("ptype", [t for t in ParamType if t is not ParamType.REAL32])
@pytest.mark.parametrize("bytewise", [True, False])
def test_integers_survive_both_encodings(ptype: ParamType, bytewise: bool) -> None:
    for value in (0, 1, 7, 100, 127):
        wire = to_wire(value, ptype, bytewise=bytewise)
        assert from_wire(wire, ptype, bytewise=bytewise) == value


def test_bytewise_is_the_integers_bytes_and_c_cast_the_number() -> None:
    assert struct.pack("<f", to_wire(1310988, I32, bytewise=True)) == struct.pack("<i", 1310988)
    assert to_wire(1310988, I32, bytewise=False) == 1310988.0
    assert to_wire(-3, ParamType.INT8, bytewise=True) != -3.0
    assert (
        from_wire(to_wire(-3, ParamType.INT8, bytewise=True), ParamType.INT8, bytewise=True) == -3
    )
    assert to_wire(6.2, F, bytewise=True) == to_wire(6.2, F, bytewise=False)


def test_capabilities_choose_the_encoding() -> None:
    assert bytewise_from_capabilities(1 << 4, Stack.ARDUPILOT)
    assert not bytewise_from_capabilities(1 << 17, Stack.PX4)
    assert bytewise_from_capabilities(0, Stack.PX4)
    assert not bytewise_from_capabilities(0, Stack.ARDUPILOT)


def _param_values(name: str) -> list[tuple[str, float, int]]:
    path = capture(name)
    log = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    out = []
    while (msg := log.recv_match(type="PARAM_VALUE")) is not None:
        out.append((msg.param_id, msg.param_value, msg.param_type))
    return out


def test_recorded_px4_integers_are_bytewise() -> None:
    values = _param_values("px4-v1.16-sih-boot-arm-takeoff-loiter-land.tlog")
    ints = [(n, w) for n, w, t in values if t == ParamType.INT32]
    assert ints and {t for _, _, t in values} <= {ParamType.INT32, ParamType.REAL32}
    for name, wire in ints:  # device ids and priorities: whole numbers read bytewise
        value = from_wire(wire, I32, bytewise=True)
        assert to_wire(value, I32, bytewise=True) == wire, name
    by_name = {n: from_wire(w, I32, bytewise=True) for n, w in ints}
    assert by_name["CAL_MAG0_PRIO"] == 50  # a sensor priority, 0..100
    assert bytewise_from_capabilities(0, Stack.PX4)


def test_recorded_ardupilot_integers_are_c_cast_with_their_own_types() -> None:
    values = _param_values("arducopter-streams-arm-takeoff-brake-land.tlog")
    by_name = {n: (w, t) for n, w, t in values}
    assert by_name["EK3_SRC1_POSXY"] == (3.0, ParamType.INT8)
    assert by_name["MIS_TOTAL"][1] == ParamType.INT16
    wire, ptype = by_name["INS_GYR_ID"]
    assert ptype == ParamType.INT32 and from_wire(wire, I32, bytewise=False) == 2752772
    assert not bytewise_from_capabilities(0, Stack.ARDUPILOT)


def test_a_value_saturates_to_its_type() -> None:
    assert saturate(300, ParamType.INT8) == 127
    assert saturate(-5.7, ParamType.UINT8) == 0
    assert saturate(math.inf, ParamType.INT16) == 0
    assert saturate(6.2, F) == float(struct.unpack("<f", struct.pack("<f", 6.2))[0])
