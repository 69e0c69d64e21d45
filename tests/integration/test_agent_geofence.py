"""A Mission's geofence, kept by the real agent on simulated autopilots over real UDP.

The simulated autopilots serve the fence part of the MAVLink mission protocol and store
the stack's fence parameters with the firmware's names and types (roost_sim.fence,
roost_sim.params); the agent saves what they hold, uploads the fence, reads it back,
writes the parameters, reports ``FenceInSync`` per autopilot, and restores the previous
fence when ``spec.fence`` goes. The simulated bridge is the only stand-in (no GPIO
hardware here).
"""

from __future__ import annotations

import pytest

from roost_api.autopilot import AssignedFence, Fence, FenceCircle, FencePoint
from roost_api.fence import FenceAction, held_id
from roost_mavlink.fence import MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
from roost_sim.model import SimConfig
from tests.support.hubclient import HubVehicle, hub_vehicle
from tests.support.waiting import wait_until

pytestmark = pytest.mark.slow

KIND = "FenceInSync"
HOME = SimConfig().home_lat_deg, SimConfig().home_lon_deg


def square(half_deg: float = 0.001) -> list[FencePoint]:
    lat, lon = HOME
    return [
        FencePoint(latitude=lat - half_deg, longitude=lon - half_deg),
        FencePoint(latitude=lat - half_deg, longitude=lon + half_deg),
        FencePoint(latitude=lat + half_deg, longitude=lon + half_deg),
        FencePoint(latitude=lat + half_deg, longitude=lon - half_deg),
    ]


def assigned(fence: Fence, fid: str = "f1") -> AssignedFence:
    return AssignedFence(mission="default/m1", id=fid, fence=fence)


def reason(v: HubVehicle, name: str) -> str | None:
    cond = v.condition(name, KIND)
    return None if cond is None else cond.reason


def held(v: HubVehicle, name: str, fid: str) -> bool:
    cond = v.condition(name, KIND)
    return cond is not None and cond.status == "True" and held_id(cond.message) == fid


def test_the_fence_reaches_every_autopilot_of_each_stack_and_the_previous_comes_back() -> None:
    fence = Fence(polygon=square(), max_altitude_m=40, action=FenceAction.LAND)
    with hub_vehicle(["px4", "ardupilot"]) as v:
        before = {s.name: list(s.fence.items) for s in v.sims}
        ardu_alt = v.sim("fc2").params.get("FENCE_ALT_MAX")
        v.agent.apply_spec(v.spec_with(fence=assigned(fence)))
        for sim in v.sims:
            wait_until(f"{sim.name} holds it", lambda s=sim: held(v, s.name, "f1"), 15)
        for sim in v.sims:
            assert [i.command for i in sim.fence.items] == [
                MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
            ] * 4
            assert all(i.param1 == 4 for i in sim.fence.items)
        px4 = v.sim("fc1").params
        assert (px4.get("GF_ACTION"), px4.get("GF_MAX_VER_DIST")) == (5, 40)
        ardu = v.sim("fc2").params
        assert (ardu.get("FENCE_ENABLE"), ardu.get("FENCE_TYPE")) == (1, 5)
        assert (ardu.get("FENCE_ALT_MAX"), ardu.get("FENCE_ACTION")) == (40, 2)

        v.agent.apply_spec(v.spec_with(fence=None))
        for sim in v.sims:
            wait_until(f"{sim.name} restored", lambda s=sim: v.condition(s.name, KIND) is None, 15)
            assert sim.fence.items == before[sim.name]
        assert v.sim("fc2").params.get("FENCE_ALT_MAX") == ardu_alt
        assert v.sim("fc2").params.get("FENCE_ENABLE") == 0


def test_an_upload_refused_by_one_autopilot_is_reported_naming_it() -> None:
    fence = Fence(
        circle=FenceCircle(latitude=HOME[0], longitude=HOME[1], radius_m=80), max_altitude_m=30
    )
    with hub_vehicle(["px4", "px4"]) as v:
        v.sim("fc2").fence.refuse_uploads = True
        v.agent.apply_spec(v.spec_with(fence=assigned(fence)))
        wait_until("fc1 holds it", lambda: held(v, "fc1", "f1"), 15)
        wait_until("fc2 refused", lambda: reason(v, "fc2") == "UploadRefused", 15)
        cond = v.condition("fc2", KIND)
        assert cond is not None and cond.status == "False"
        assert "MISSION_ACK result 1" in cond.message
        assert v.sim("fc2").fence.items == []  # nothing stored
        assert v.sim("fc2").params.get("GF_MAX_VER_DIST") == 0  # nor half of it applied


def test_a_fence_that_does_not_contain_the_vehicle_is_not_uploaded() -> None:
    lat, lon = HOME
    away = Fence(
        circle=FenceCircle(latitude=lat + 0.01, longitude=lon, radius_m=100), max_altitude_m=30
    )
    with hub_vehicle(["px4", "px4"]) as v:
        v.agent.apply_spec(v.spec_with(fence=assigned(away)))
        for sim in v.sims:
            wait_until(
                f"{sim.name} refused",
                lambda s=sim: reason(v, s.name) == "VehicleOutsideFence",
                15,
            )
        assert all(s.fence.uploads == 0 for s in v.sims)


def test_a_fence_is_not_written_while_the_vehicle_is_armed() -> None:
    fence = Fence(polygon=square(), max_altitude_m=40)
    with hub_vehicle(["px4", "px4"]) as v:
        for sim in v.sims:
            sim.fly(3.0)
        wait_until(
            "the agent sees them armed",
            lambda: all(h.armed for h in v.agent.status().autopilots),
            10,
        )
        v.agent.apply_spec(v.spec_with(fence=assigned(fence)))
        wait_until("deferred", lambda: reason(v, "fc1") == "DeferredWhileArmed", 15)
        assert all(s.fence.uploads == 0 for s in v.sims)


def test_a_breach_in_flight_triggers_the_configured_action() -> None:
    # A 20 m circle round home, 10 m ceiling, Return on breach: the sim flies to 15 m.
    fence = Fence(
        circle=FenceCircle(latitude=HOME[0], longitude=HOME[1], radius_m=20),
        max_altitude_m=10,
        action=FenceAction.RETURN,
    )
    with hub_vehicle(["px4", "px4"]) as v:
        v.agent.apply_spec(v.spec_with(fence=assigned(fence)))
        for sim in v.sims:
            wait_until(f"{sim.name} holds it", lambda s=sim: held(v, s.name, "f1"), 15)
        sim = v.sim("fc1")
        sim.fly(15.0)
        wait_until("breach acted on", lambda: sim.snapshot().mode == "AUTO.RTL", 30)
        assert "above the fence's 10 m" in sim.fence.breaches[0]
