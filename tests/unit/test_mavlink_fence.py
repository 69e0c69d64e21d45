"""The fence part of the mission protocol (roost_mavlink.fence): the items, the stacks'
fence parameters, and the client's transfer state machine as a decision table."""

from __future__ import annotations

from typing import Any

import pytest

from roost_api.core import Stack
from roost_api.fence import Area, FenceAction, LatLon
from roost_mavlink.fence import (
    MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
    MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    MAX_RETRIES,
    RETRY_S,
    Item,
    Outcome,
    Transfer,
    action_from_params,
    area_of,
    items_for,
    max_altitude_from_params,
    mismatch,
    stack_params,
)
from roost_mavlink.params import ParamType
from roost_sim.fence import upload_problem

F = {"mission_type": 1}
V = MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
TRI = (LatLon(47.0, 8.0), LatLon(47.0, 8.001), LatLon(47.001, 8.0))


def test_a_polygon_is_one_vertex_item_each_counting_them_and_a_closed_ring_is_closed_once() -> None:
    items = items_for(Area(polygon=(*TRI, TRI[0])))
    assert items == [
        Item(V, 3.0, 470000000, 80000000),
        Item(V, 3.0, 470000000, 80010000),
        Item(V, 3.0, 470010000, 80000000),
    ]
    assert area_of(items) == Area(polygon=TRI)


def test_a_circle_is_one_item_with_its_radius() -> None:
    items = items_for(Area(centre=LatLon(47.5, 8.25), radius_m=80.5))
    assert items == [Item(MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, 80.5, 475000000, 82500000)]


@pytest.mark.parametrize(
    ("read", "differs"),
    [
        ([Item(V, 3.0, 1, 2)], None),
        ([Item(V, 3.0000001, 1, 2)], None),  # param1 compares as a 32-bit float
        ([], "read back 0 item(s), uploaded 1"),
        ([Item(V, 3.0, 1, 3)], "item 0 reads back as"),
        ([Item(MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, 3.0, 1, 2)], "item 0 reads back as"),
    ],
)
def test_read_back_comparison(read: list[Item], differs: str | None) -> None:
    found = mismatch([Item(V, 3.0, 1, 2)], read)
    assert (found is None) if differs is None else (found or "").startswith(differs)


@pytest.mark.parametrize(
    ("stack", "action", "params"),
    [
        (
            Stack.PX4,
            FenceAction.HOLD,
            [("GF_ACTION", ParamType.INT32, 2), ("GF_MAX_VER_DIST", ParamType.REAL32, 40)],
        ),
        (
            Stack.PX4,
            FenceAction.RETURN,
            [("GF_ACTION", ParamType.INT32, 3), ("GF_MAX_VER_DIST", ParamType.REAL32, 40)],
        ),
        (
            Stack.PX4,
            FenceAction.LAND,
            [("GF_ACTION", ParamType.INT32, 5), ("GF_MAX_VER_DIST", ParamType.REAL32, 40)],
        ),
        (
            Stack.PX4,
            FenceAction.REPORT,
            [("GF_ACTION", ParamType.INT32, 1), ("GF_MAX_VER_DIST", ParamType.REAL32, 40)],
        ),
        (
            Stack.ARDUPILOT,
            FenceAction.RETURN,
            [
                ("FENCE_ENABLE", ParamType.INT8, 1),
                ("FENCE_TYPE", ParamType.INT8, 5),
                ("FENCE_ALT_MAX", ParamType.REAL32, 40),
                ("FENCE_ACTION", ParamType.INT8, 1),
            ],
        ),
        (
            Stack.ARDUPILOT,
            FenceAction.HOLD,
            [
                ("FENCE_ENABLE", ParamType.INT8, 1),
                ("FENCE_TYPE", ParamType.INT8, 5),
                ("FENCE_ALT_MAX", ParamType.REAL32, 40),
                ("FENCE_ACTION", ParamType.INT8, 4),
            ],
        ),
    ],
)
def test_stack_fence_parameters(
    stack: Stack, action: FenceAction, params: list[tuple[str, ParamType, float]]
) -> None:
    got = stack_params(stack, 40, action)
    assert [(p.name, p.ptype, p.value) for p in got] == params
    values = {p.name: p.value for p in got}
    assert action_from_params(stack, values) is action
    assert max_altitude_from_params(stack, values) == 40


def test_an_ardupilot_fence_that_is_not_enabled_acts_on_nothing() -> None:
    values = {"FENCE_ENABLE": 0.0, "FENCE_TYPE": 5.0, "FENCE_ALT_MAX": 40.0, "FENCE_ACTION": 1.0}
    assert action_from_params(Stack.ARDUPILOT, values) is None
    assert max_altitude_from_params(Stack.ARDUPILOT, values) is None
    assert max_altitude_from_params(Stack.PX4, {"GF_MAX_VER_DIST": 0.0}) is None


# -- the transfer: (message in, what goes out, outcome) step by step -------------------


def names(messages: list[tuple[str, dict[str, Any]]]) -> list[str]:
    return [m[0] for m in messages]


def test_upload_decision_table() -> None:
    items = [Item(V, 3.0, 1, 2), Item(V, 3.0, 3, 4), Item(V, 3.0, 5, 6)]
    t = Transfer.upload(items)
    assert t.start(0.0) == [("MISSION_COUNT", {"count": 3, **F})]
    steps: list[tuple[str, dict[str, Any], list[str], Outcome]] = [
        ("MISSION_REQUEST_INT", {"seq": 0, **F}, ["MISSION_ITEM_INT"], Outcome.RUNNING),
        ("MISSION_REQUEST_INT", {"seq": 0, "mission_type": 0}, [], Outcome.RUNNING),  # a mission's
        ("MISSION_REQUEST", {"seq": 1, **F}, ["MISSION_ITEM_INT"], Outcome.RUNNING),  # ArduPilot
        ("MISSION_REQUEST_INT", {"seq": 1, **F}, ["MISSION_ITEM_INT"], Outcome.RUNNING),  # again
        ("MISSION_REQUEST_INT", {"seq": 9, **F}, [], Outcome.RUNNING),  # out of range
        ("MISSION_REQUEST_INT", {"seq": 2, **F}, ["MISSION_ITEM_INT"], Outcome.RUNNING),
        ("MISSION_ACK", {"type": 0, **F}, [], Outcome.DONE),
        ("MISSION_REQUEST_INT", {"seq": 0, **F}, [], Outcome.DONE),  # finished: ignored
    ]
    for name, fields, out, outcome in steps:
        sent = t.receive(name, fields, 0.1)
        assert (names(sent), t.outcome) == (out, outcome), (name, fields)
    item = Transfer.upload(items)._item(2)[1]
    assert (item["command"], item["x"], item["y"], item["mission_type"]) == (V, 5, 6, 1)


def test_an_upload_refused_reports_the_ack_result() -> None:
    t = Transfer.upload([Item(V, 3.0, 1, 2)])
    t.start(0.0)
    t.receive("MISSION_ACK", {"type": 5, **F}, 0.1)
    assert (t.outcome, t.detail) == (Outcome.REFUSED, "MISSION_ACK result 5")


def test_download_decision_table() -> None:
    t = Transfer.download()
    assert t.start(0.0) == [("MISSION_REQUEST_LIST", F)]
    steps: list[tuple[str, dict[str, Any], list[tuple[str, dict[str, Any]]], Outcome]] = [
        (
            "MISSION_COUNT",
            {"count": 2, **F},
            [("MISSION_REQUEST_INT", {"seq": 0, **F})],
            Outcome.RUNNING,
        ),
        ("MISSION_COUNT", {"count": 5, **F}, [], Outcome.RUNNING),  # a repeat: the first counts
        (
            "MISSION_ITEM_INT",
            {"seq": 0, "command": V, "param1": 3.0, "x": 1, "y": 2, **F},
            [("MISSION_REQUEST_INT", {"seq": 1, **F})],
            Outcome.RUNNING,
        ),
        (
            "MISSION_ITEM_INT",
            {"seq": 0, "command": V, "param1": 3.0, "x": 1, "y": 2, **F},
            [],
            Outcome.RUNNING,
        ),
        (
            "MISSION_ITEM_INT",
            {"seq": 1, "command": V, "param1": 3.0, "x": 3, "y": 4, **F},
            [("MISSION_ACK", {"type": 0, **F})],
            Outcome.DONE,
        ),
    ]
    for name, fields, out, outcome in steps:
        assert (t.receive(name, fields, 0.1), t.outcome) == (out, outcome), (name, fields)
    assert t.received == [Item(V, 3.0, 1, 2), Item(V, 3.0, 3, 4)]


def test_an_empty_fence_downloads_as_nothing() -> None:
    t = Transfer.download()
    t.start(0.0)
    assert t.receive("MISSION_COUNT", {"count": 0, **F}, 0.1) == [("MISSION_ACK", {"type": 0, **F})]
    assert (t.outcome, t.received) == (Outcome.DONE, [])


def test_an_unanswered_step_is_repeated_then_the_transfer_fails() -> None:
    t = Transfer.download()
    first = t.start(0.0)
    assert t.step(RETRY_S / 2) == []
    now = 0.0
    for _ in range(MAX_RETRIES):
        now += RETRY_S
        assert t.step(now) == first
    assert t.step(now + RETRY_S) == []
    assert t.outcome is Outcome.NO_ANSWER
    assert t.detail == f"no answer to MISSION_REQUEST_LIST after {MAX_RETRIES + 1} tries"


@pytest.mark.parametrize(
    ("items", "error"),
    [
        ([Item(V, 3.0, 0, 0)] * 3, None),
        ([Item(MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, 50.0, 0, 0)], None),
        ([], None),  # clears the fence
        ([Item(V, 3.0, 0, 0)] * 2, 5),  # the count says 3
        ([Item(V, 2.0, 0, 0)] * 2, 5),  # fewer than three vertices
        ([Item(16, 0.0, 0, 0)], 3),  # a waypoint is no fence item
    ],
)
def test_what_the_simulated_autopilot_refuses(items: list[Item], error: int | None) -> None:
    assert upload_problem(items) == error
