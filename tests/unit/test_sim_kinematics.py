"""Horizontal flight of the simulated multicopter (roost_sim.kinematics), stepped with a
fixed dt: no clock, no sockets."""

from __future__ import annotations

import itertools
import math

import pytest

from roost_sim.kinematics import Horizontal, global_from_ned, ned_from_global

DT = 0.02


def fly(h: Horizontal, target: tuple[float, float], seconds: float, **limits: float) -> list[float]:
    """Step for ``seconds``; the speeds seen after each step."""
    speeds = []
    for _ in range(round(seconds / DT)):
        h.step(DT, target, **{"max_speed_mps": 5.0, "max_accel_mps2": 3.0, **limits})
        speeds.append(h.speed_mps)
    return speeds


def test_flies_straight_to_the_target_within_its_limits_and_stops_on_it() -> None:
    h = Horizontal()
    speeds = fly(h, (30.0, 40.0), 20.0)
    assert max(speeds) <= 5.0 + 1e-9
    accelerations = [abs(b - a) / DT for a, b in itertools.pairwise(speeds)]
    assert max(accelerations) <= 3.0 + 1e-6
    assert h.distance_to(30.0, 40.0) < 0.01 and h.speed_mps == 0.0
    # straight: the direction of flight never leaves the line from home to the target
    assert math.isclose(math.atan2(h.east_m, h.north_m), math.atan2(40.0, 30.0), abs_tol=1e-6)


def test_the_time_to_a_target_is_what_accelerating_cruising_and_braking_take() -> None:
    h = Horizontal()
    speeds = fly(h, (50.0, 0.0), 30.0)
    arrived = next(i for i, s in enumerate(speeds) if i > 5 and s == 0.0) * DT
    # 5 m/s at 3 m/s2: 1.67 s and 4.17 m each to accelerate and to brake, 41.7 m cruising
    assert arrived == pytest.approx(2 * 5 / 3 + (50 - 25 / 3) / 5, abs=0.3)


@pytest.mark.parametrize("scale", [0.5, 0.25])
def test_a_speed_scale_slows_the_vehicle_in_proportion(scale: float) -> None:
    normal, slowed = Horizontal(), Horizontal()
    fly(normal, (100.0, 0.0), 10.0)
    fly(slowed, (100.0, 0.0), 10.0, speed_scale=scale)
    assert max(fly(Horizontal(), (100.0, 0.0), 10.0, speed_scale=scale)) <= 5.0 * scale + 1e-9
    assert slowed.north_m < normal.north_m * (scale + 0.1)


def test_a_moving_vehicle_given_its_own_position_brakes_and_holds() -> None:
    h = Horizontal(vn_mps=5.0)
    fly(h, (0.0, 0.0), 10.0)
    assert h.speed_mps == 0.0 and h.distance_to(0.0, 0.0) < 0.05


def test_global_and_local_coordinates_convert_both_ways() -> None:
    home = (47.397742, 8.545594)
    north, east = ned_from_global(*global_from_ned(120.0, -35.0, *home), *home)
    assert north == pytest.approx(120.0, abs=1e-6) and east == pytest.approx(-35.0, abs=1e-6)
    lat, _ = global_from_ned(111.32, 0.0, *home)
    assert lat - home[0] == pytest.approx(0.001, rel=0.01)  # ~111 m per millidegree


@pytest.mark.parametrize("stall_s", [0.25, 0.5, 1.0])
def test_a_stalled_stepper_ends_up_where_a_steady_one_does(stall_s: float) -> None:
    """The simulator steps on its own clock; a busy machine hands it long gaps, and the
    vehicle must not overshoot and ring around its target because of them."""
    steady, stalled = Horizontal(), Horizontal()
    limits = {"max_speed_mps": 5.0, "max_accel_mps2": 3.0}
    for _ in range(round(12.0 / stall_s)):
        stalled.step(stall_s, (20.0, 10.0), **limits)
    fly(steady, (20.0, 10.0), 12.0)
    assert stalled.distance_to(20.0, 10.0) < 0.05 and stalled.speed_mps == 0.0
    assert stalled.north_m == pytest.approx(steady.north_m, abs=0.05)
