"""The simulator's tick scheduler: rounds on a grid, average rates kept, faults contained.

The tests drive :meth:`TickScheduler.run_round` with a fake clock (no thread), which is
exactly what the scheduler's thread does between sleeps; the thread itself is in
``tests/integration/test_sim_scheduler_thread.py``.
"""

from __future__ import annotations

import pytest

from roost_sim.scheduler import GRID_S, RETRY_S, TickScheduler, on_grid
from tests.support.tickstreams import Broken, Stream


def drive(scheduler: TickScheduler, clock: list[float], until: float) -> list[float]:
    """Run rounds as the thread would, jumping the fake clock to each next round."""
    rounds: list[float] = []
    while clock[0] < until:
        following = scheduler.run_round(clock[0])
        rounds.append(clock[0])
        assert following is not None
        clock[0] = following
    return rounds


@pytest.mark.parametrize(
    ("t", "expected"),
    [(0.0, 0.0), (0.0025, 0.0025), (0.0026, 0.005), (0.0333, 0.035), (1.00001, 1.0025)],
)
def test_a_time_is_rounded_up_to_the_grid(t: float, expected: float) -> None:
    assert on_grid(t) == pytest.approx(expected)


@pytest.mark.parametrize("hz", [100.0, 50.0, 30.0, 8.0, 0.5])
def test_a_stream_keeps_its_average_rate_though_each_round_is_on_the_grid(hz: float) -> None:
    clock = [0.0]
    scheduler = TickScheduler(clock=lambda: clock[0], threaded=False)
    stream = Stream("s", hz, start=0.0)
    scheduler.register(stream)
    rounds = drive(scheduler, clock, until=20.0)
    assert all(r == pytest.approx(on_grid(r)) for r in rounds)  # every round on the grid
    assert len(stream.ticks) == pytest.approx(20.0 * hz, abs=1)
    lateness = [t - d for t, d in zip(stream.ticks, [k / hz for k in range(10**6)], strict=False)]
    assert max(lateness) < GRID_S + 1e-9  # at most one grid step late


def test_autopilots_share_rounds_instead_of_each_waking_at_its_own_times() -> None:
    clock = [0.0]
    scheduler = TickScheduler(clock=lambda: clock[0], threaded=False)
    streams = [Stream(f"ap{k}", 100.0, start=k * 0.0007) for k in range(20)]  # own phases
    for stream in streams:
        scheduler.register(stream)
    rounds = drive(scheduler, clock, until=10.0)
    assert all(len(s.ticks) == pytest.approx(1000, abs=1) for s in streams)
    assert len(rounds) <= 10.0 / GRID_S + 1  # the grid bounds the wake-ups, not 20 x 100/s


def test_one_autopilots_exception_does_not_stop_another() -> None:
    clock = [0.0]
    scheduler = TickScheduler(clock=lambda: clock[0], threaded=False)
    broken, healthy = Broken(), Stream("healthy", 50.0)
    scheduler.register(broken)
    scheduler.register(healthy)
    drive(scheduler, clock, until=1.0)
    assert len(healthy.ticks) == pytest.approx(50, abs=1)
    assert broken.calls == pytest.approx(1.0 / RETRY_S, abs=2)  # retried, not dropped


def test_nothing_registered_means_no_next_round() -> None:
    scheduler = TickScheduler(threaded=False)
    assert scheduler.run_round(0.0) is None
    stream = Stream("s", 10.0)
    scheduler.register(stream)
    scheduler.unregister(stream)
    assert scheduler.run_round(1.0) is None
    assert stream.ticks == []
