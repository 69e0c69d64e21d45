"""The sync-paths reference mission against simulated autopilots (real UDP MAVLink and
real UDP between its follower and monitor; their code runs on threads, see
:mod:`tests.support.syncrun`)."""

from __future__ import annotations

import pytest

from tests.support.syncrun import Task, fly_mission

pytestmark = pytest.mark.slow

TRANSIT_S = 8.0


def square(east: float) -> list[Task]:
    """Three tasks 8 s apart, 8 m apart (1 m/s planned; the simulator flies 5 m/s)."""
    corners = [(0.0, 0.0), (8.0, 0.0), (8.0, 8.0)]
    return [Task(TRANSIT_S * k, (n, e + east, -4.0)) for k, (n, e) in enumerate(corners)]


def test_a_lagging_vehicle_is_waited_for_and_transits_stay_the_planned_ones() -> None:
    # 12 % of 5 m/s is 0.6 m/s: drone-2 arrives at task 1 about 5 s late
    run = fly_mission({"drone-1": square(0.0), "drone-2": square(2.0)}, lags={("drone-2", 1): 12})
    assert sorted(run.results) == ["drone-1", "drone-2"]
    assert all(r["type"] == "done" for r in run.results.values())
    first = {name: result["records"][0] for name, result in run.results.items()}
    assert first["drone-2"]["delay_s"] > 2.0
    assert (
        first["drone-1"]["wait_s"] > first["drone-2"]["delay_s"] - first["drone-1"]["delay_s"] - 0.5
    )
    departures = [r["departure_s"] for r in first.values()]
    assert max(departures) - min(departures) < 0.5  # they left task 1 together
    for record in run.records():
        assert abs(record["transit_s"] - record["planned_transit_s"]) <= 0.5, record


def test_the_others_go_on_when_a_vehicle_leaves_the_mission() -> None:
    """drone-2's workload stops on its way to task 2 (as after a failover with
    onFailover: AbortVehicle): drone-1 does not wait for its report at task 2."""
    run = fly_mission(
        {"drone-1": square(0.0), "drone-2": square(2.0)}, leave_at_task={"drone-2": 2}
    )
    assert run.results["drone-2"]["type"] == "leave"
    assert run.results["drone-1"]["type"] == "done"
    assert [r["task"] for r in run.results["drone-1"]["records"]] == [1, 2]
    assert run.results["drone-1"]["records"][1]["wait_s"] < 1.0
