"""The simulator's tick scheduler's own thread: ticks until unregistered, no deadlock
when a tick unregisters, registrations while it waits ticked in the next round.

Rounds driven with a fake clock (no thread) are in ``tests/unit/test_sim_scheduler.py``;
the stand-in streams count ticks the way an autopilot's streams do.
"""

from __future__ import annotations

import threading

from roost_sim.scheduler import TickScheduler
from tests.support.tickstreams import Broken, Stream
from tests.support.waiting import wait_until


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
