"""The simulated autopilot's fence check (roost_sim.fence.SimFence.check): when a breach
is acted on, and with which action, per stack, as a decision table."""

from __future__ import annotations

import pytest

from roost_api.core import Stack
from roost_api.fence import Area, FenceAction, LatLon
from roost_mavlink.fence import items_for
from roost_sim.fence import SimFence

HOME = LatLon(47.397742, 8.545594)
CIRCLE = items_for(Area(centre=HOME, radius_m=20))
PX4 = {"GF_ACTION": 3.0, "GF_MAX_VER_DIST": 10.0}
AP_ON = {"FENCE_ENABLE": 1.0, "FENCE_TYPE": 5.0, "FENCE_ALT_MAX": 10.0, "FENCE_ACTION": 2.0}
AP_OFF = {**AP_ON, "FENCE_ENABLE": 0.0}


@pytest.mark.parametrize(
    ("stack", "params", "north", "alt", "flying", "action"),
    [
        (Stack.PX4, PX4, 0, 5, True, None),  # inside, below the ceiling
        (Stack.PX4, PX4, 30, 5, True, FenceAction.RETURN),  # outside the circle
        (Stack.PX4, PX4, 0, 12, True, FenceAction.RETURN),  # above the ceiling
        (Stack.PX4, PX4, 30, 5, False, None),  # on the ground: nothing
        (Stack.PX4, {**PX4, "GF_ACTION": 5.0}, 30, 5, True, FenceAction.LAND),
        (Stack.PX4, {**PX4, "GF_ACTION": 2.0}, 30, 5, True, FenceAction.HOLD),
        (Stack.PX4, {**PX4, "GF_MAX_VER_DIST": 0.0}, 0, 50, True, None),  # no ceiling
        (Stack.ARDUPILOT, AP_ON, 30, 5, True, FenceAction.LAND),
        (Stack.ARDUPILOT, AP_ON, 0, 12, True, FenceAction.LAND),
        (Stack.ARDUPILOT, AP_OFF, 30, 12, True, None),  # FENCE_ENABLE 0
        (Stack.ARDUPILOT, {**AP_ON, "FENCE_TYPE": 1.0}, 30, 5, True, None),  # altitude only
    ],
)
def test_breach_decision_table(  # noqa: PLR0917 - one parameter per column of the table
    stack: Stack,
    params: dict[str, float],
    north: float,
    alt: float,
    flying: bool,
    action: FenceAction | None,
) -> None:
    fence = SimFence(stack)
    fence.items = list(CIRCLE)
    got = fence.check(
        north_m=north, east_m=0, altitude_m=alt, home=HOME, params=params, flying=flying
    )
    assert got is action


def test_a_breach_is_acted_on_once_until_the_vehicle_is_back_inside() -> None:
    fence = SimFence(Stack.PX4)
    fence.items = list(CIRCLE)

    def check(north: float) -> FenceAction | None:
        return fence.check(
            north_m=north, east_m=0, altitude_m=5, home=HOME, params=PX4, flying=True
        )

    assert [check(n) for n in (30, 31, 32, 0, 30)] == [
        FenceAction.RETURN,
        None,
        None,
        None,
        FenceAction.RETURN,
    ]
    assert fence.breaches[0].startswith("outside the fence at 47.398")
