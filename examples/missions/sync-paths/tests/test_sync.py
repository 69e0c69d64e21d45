"""The synchronisation rule on a fake clock with point-mass vehicles (no sockets)."""

from __future__ import annotations

import json
import math

import pytest
from syncpaths.channel import bind_towards
from syncpaths.monitor import results_from_log
from syncpaths.sync import Follower, Membership, Phase
from syncpaths.trajectory import Task, TrajectoryError, parse, setpoint

DT = 0.05


def line(offset_east: float) -> list[Task]:
    """Four tasks 20 s apart, 20 m apart northwards."""
    return [Task(20.0 * k, (20.0 * k, offset_east, -5.0)) for k in range(4)]


def test_trajectories_parse_and_interpolate() -> None:
    tasks = parse(
        [["time_s", "north_m", "east_m", "down_m"], ["0", "0", "0", "-5"], ["10", "10", "0", "-5"]]
    )
    assert setpoint(tasks, 5.0) == (5.0, 0.0, -5.0)
    assert setpoint(tasks, -1.0) == (0.0, 0.0, -5.0) and setpoint(tasks, 99) == (10.0, 0.0, -5.0)
    with pytest.raises(TrajectoryError, match=r"row 3: time 5\.0 does not increase"):
        parse([["0", "0", "0", "0"], ["5", "1", "0", "0"], ["5", "2", "0", "0"]])
    with pytest.raises(TrajectoryError, match="at least two"):
        parse([["0", "0", "0", "0"]])


class PointMass:
    """Flies at ``speed`` towards the setpoint; ``slow`` scales it between two times."""

    def __init__(self, point: tuple[float, float, float], speed: float = 4.0) -> None:
        self.position = point
        self.speed = speed
        self.slow: tuple[float, float, float] | None = None  # (from, to, scale)

    def fly(self, target: tuple[float, float, float], now: float) -> None:
        scale = self.slow[2] if self.slow and self.slow[0] <= now < self.slow[1] else 1.0
        gap = math.dist(self.position, target)
        step = min(gap, self.speed * scale * DT)
        if gap > 0:
            self.position = tuple(  # type: ignore[assignment]
                p + (t - p) * step / gap for p, t in zip(self.position, target, strict=True)
            )


def run(followers: list[Follower], masses: list[PointMass], until: float) -> None:
    """Step everyone; delays are exchanged instantly (the monitor's part)."""
    reports: dict[int, dict[str, float]] = {}
    now = 0.0
    while now < until and not all(f.phase is Phase.DONE for f in followers):
        now += DT
        members = [f.name for f in followers]
        for f, m in zip(followers, masses, strict=True):
            m.fly(f.setpoint(now), now)
            delay = f.step(now, m.position)
            if delay is not None:
                reports.setdefault(f.task, {})[f.name] = delay
            f.try_depart(now, reports.get(f.task, {}), members)


def test_a_slowed_vehicle_delays_everyone_and_transits_stay_the_planned_ones() -> None:
    followers = [Follower(f"v{i}", line(5.0 * i), start=0.0) for i in range(3)]
    # the plan flies 1 m/s; the vehicles can do 1.2
    masses = [PointMass(f.tasks[0].point, speed=1.2) for f in followers]
    masses[1].slow = (5.0, 15.0, 0.1)  # v1 loses ~6 s on its way to task 1
    run(followers, masses, 200.0)
    assert all(f.phase is Phase.DONE for f in followers)
    first = {f.name: f.records[0] for f in followers}
    assert first["v1"].delay_s > 4.0 and first["v1"].wait_s < 0.1
    for name in ("v0", "v2"):  # they waited for v1
        assert first[name].wait_s == pytest.approx(
            first["v1"].delay_s - first[name].delay_s, abs=0.1
        )
    departures = [f.records[0].departure_s for f in followers]
    assert max(departures) - min(departures) < 0.1  # left task 1 together
    for f in followers:
        for record in f.records:
            assert record.transit_s == pytest.approx(record.planned_transit_s, abs=DT * 2)


def test_nobody_waits_for_a_vehicle_that_left() -> None:
    followers = [Follower(f"v{i}", line(5.0 * i), start=0.0) for i in range(2)]
    masses = [PointMass(f.tasks[0].point) for f in followers]
    masses[1].speed = 0.0  # v1 never arrives
    now = 0.0
    while followers[0].phase is not Phase.WAITING:
        now += DT
        masses[0].fly(followers[0].setpoint(now), now)
        followers[0].step(now, masses[0].position)
    assert not followers[0].try_depart(now + 1, {}, ["v0", "v1"])  # waits for v1's report
    assert followers[0].try_depart(now + 1, {}, ["v0"])  # v1 left: go on
    assert followers[0].records[0].wait_s == pytest.approx(1.0)


def test_a_silent_member_is_bounded_by_the_longest_wait() -> None:
    f = Follower("v0", line(0.0), start=0.0, max_wait_s=5.0)
    assert f.step(20.0, f.tasks[1].point) == 0.0
    assert not f.try_depart(24.0, {}, ["v0", "v1"])
    assert f.try_depart(25.0, {}, ["v0", "v1"])


def test_membership_drops_the_silent_and_the_leaving() -> None:
    m = Membership(silent_after_s=3.0)
    assert m.heard("a", 0.0) and m.heard("b", 0.0) and not m.heard("a", 1.0)
    assert m.expire(3.5) == ["b"] and m.members == ["a"]
    assert m.leave("a") and m.members == [] and not m.heard("a", 4.0)  # left for good


def test_a_client_binds_where_its_peer_can_answer() -> None:
    assert bind_towards(("127.0.0.1", 7700)) == ("127.0.0.1", 0)
    assert bind_towards(("localhost", 7700)) == ("127.0.0.1", 0)
    # A Service's address or name: any address of the pod's (or vehicle's) network.
    assert bind_towards(("10.96.0.12", 7700)) == ("0.0.0.0", 0)
    assert bind_towards(("sync-monitor.default.svc.cluster.local", 7700)) == ("0.0.0.0", 0)


def test_results_are_read_back_from_the_monitors_log() -> None:
    results = {"drone-1": {"type": "done", "records": [], "path": []}}
    log = "\n".join(
        [
            '{"listening": "0.0.0.0:7700"}',
            "2026-01-01 syncpaths.monitor: starting 1 vehicles in 2 s",
            "| vehicle | task |",
            json.dumps({"results": results}),
            '{"vehicles": ["drone-1"], "output": "/tmp/sync-results"}',
        ]
    )
    assert results_from_log(log) == results
    assert results_from_log(log.rsplit("\n", 2)[0]) is None  # not finished yet
