"""The simulator's tick scheduler: rounds on a grid, average rates kept, faults contained.

Most tests drive :meth:`TickScheduler.run_round` with a fake clock (no thread), which is
exactly what the scheduler's thread does between sleeps; the last ones run the real
thread with real autopilot stand-ins (an autopilot needs sockets; the stand-ins count
ticks the way a stream does).
"""

from __future__ import annotations

import threading

import pytest

from roost_sim.scheduler import GRID_S, RETRY_S, TickScheduler, on_grid
from tests.support.waiting import wait_until


class Stream:
    """Ticks like one stream of a simulated autopilot: due times advance by the period,
    and after falling behind by a whole period it restarts from now (no burst)."""

    def __init__(self, name: str, hz: float, start: float = 0.0) -> None:
        self.label = name
        self.period = 1.0 / hz
        self.due = start
        self.ticks: list[float] = []
        self.lock = threading.Lock()

    def tick(self, now: float) -> float:
        with self.lock:
            self.ticks.append(now)
            following = self.due + self.period
            self.due = following if following > now else now + self.period
            return self.due


class Broken:
    label = "broken"

    def __init__(self) -> None:
        self.calls = 0

    def tick(self, now: float) -> float:
        self.calls += 1
        raise RuntimeError("a bug in one message builder")


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


def test_the_thread_ticks_until_unregistered_and_then_never_again() -> None:
    scheduler = TickScheduler()
    broken, first, second = Broken(), Stream("first", 100.0), Stream("second", 100.0)
    for each in (broken, first, second):
        scheduler.register(each)
    wait_until("both ticked", lambda: len(first.ticks) >= 20 and len(second.ticks) >= 20, 10)
    scheduler.unregister(first)
    after = len(first.ticks)  # unregister returned: no tick of it is running any more
    seen = len(second.ticks)
    wait_until("the other goes on", lambda: len(second.ticks) >= seen + 20, 10)
    assert len(first.ticks) == after
    assert broken.calls > 1
    scheduler.unregister(second)
    scheduler.unregister(broken)
    wait_until("the thread ends", lambda: not scheduler.running, 10)
    scheduler.register(first)  # a later registration starts a new thread
    wait_until("ticked again", lambda: len(first.ticks) > after, 10)
    scheduler.unregister(first)


def test_unregistering_from_inside_a_tick_does_not_deadlock() -> None:
    scheduler = TickScheduler()
    done = threading.Event()

    class Quitter:
        label = "quitter"

        def tick(self, now: float) -> float:
            scheduler.unregister(self)
            done.set()
            return now + 0.01

    scheduler.register(Quitter())
    assert done.wait(10)
    wait_until("unregistered", lambda: scheduler.registered == 0, 10)


class Sleepy(Stream):
    """A stream due again only after a minute: the thread waits a long time after it."""

    def __init__(self) -> None:
        super().__init__("sleepy", 1 / 60)


def test_a_registration_while_the_thread_waits_is_ticked_in_the_next_round() -> None:
    scheduler = TickScheduler()
    sleepy, late = Sleepy(), Stream("late", 100.0)
    scheduler.register(sleepy)
    wait_until("the first round", lambda: len(sleepy.ticks) == 1, 10)
    scheduler.register(late)  # the thread now waits a minute for sleepy's next round
    wait_until("the late one ticked", lambda: len(late.ticks) >= 5, 10)
    scheduler.unregister(late)
    scheduler.unregister(sleepy)


def test_a_registration_between_a_round_and_the_wait_is_not_left_for_the_next_round() -> None:
    """The thread waits for the next round run_round computed; a registration after that
    computation (its notify finds no one waiting) must still move the next round."""
    late = Stream("late", 100.0)

    class RegisterAfterTheRound(TickScheduler):
        def run_round(self, now: float) -> float | None:
            following = super().run_round(now)
            if not late.ticks and self.rounds == 1:
                self.register(late)  # on the thread, after the next round was computed
            return following

    scheduler = RegisterAfterTheRound()
    sleepy = Sleepy()
    scheduler.register(sleepy)
    wait_until("the late one ticked", lambda: len(late.ticks) >= 5, 10)
    assert len(sleepy.ticks) == 1  # its next round is a minute away: not what woke the thread
    scheduler.unregister(late)
    scheduler.unregister(sleepy)
