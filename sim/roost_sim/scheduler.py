"""One tick loop per simulator process: every autopilot's streams sent from rounds on a grid.

Why: a thread per autopilot that wakes at each stream's exact due time wakes about 190
times a second for PX4's table (100, 50 and 30 Hz streams with independent phases), and
on a small VM a thread's wake-up costs more CPU than the messages it sends
(docs/scale.md#a-bigger-sandbox). Twenty-five vehicles of two autopilots are then about
9,500 wake-ups a second -- most of the simulators' CPU. Real
firmware does not work that way either:

- PX4's MAVLink module runs one main loop per link that sleeps between rounds
  (``mavlink_main.cpp``: a delay derived from the link's data rate, clamped to
  1.5-10 ms) and in each round sends every stream whose interval has passed.
- ArduCopter's main loop runs at 400 Hz (2.5 ms) and sends its streams from it.

So one thread per process (:class:`TickScheduler`) runs rounds on a fixed grid of
:data:`GRID_S` (2.5 ms, ArduCopter's loop period): each round ticks every registered
autopilot whose next due time has come, then sleeps until the earliest next due time
rounded up to the grid. A stream therefore leaves at most one grid step late, but its
due times still advance by its period (``SimulatedAutopilot._next_due``), so its average
rate is kept. Rounds are shared: a process hosting many autopilots wakes at most
400 times a second, whatever their number.

An autopilot is anything with ``tick(now) -> next due time`` (:class:`Tickable`). An
exception from one is logged and it is tried again :data:`RETRY_S` later; the others go
on. :meth:`TickScheduler.unregister` returns only once that autopilot's tick is no
longer running and will not run again, so a stopped autopilot sends nothing more. The
thread starts with the first registration and ends with the last unregistration.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Protocol

_log = logging.getLogger(__name__)

GRID_S = 0.0025
"""Round period: ArduCopter's 400 Hz main loop; inside PX4's 1.5-10 ms MAVLink loop."""
RETRY_S = 0.01
"""After a failed tick, the autopilot is tried again this much later."""
_SAME_TIME_S = 1e-6  # due times this close to a round are due in it (floating-point sums)


class Tickable(Protocol):
    """What the scheduler drives: one autopilot's round of work."""

    label: str  # what its log lines call it

    def tick(self, now: float) -> float:
        """Do what is due at ``now``; return the monotonic time it next has work."""
        ...


def on_grid(t: float, grid_s: float = GRID_S) -> float:
    """``t`` rounded up to the next multiple of ``grid_s`` (``t`` itself when on it)."""
    steps = math.ceil(round(t / grid_s, 9))  # 0.010000000000000002 is on the grid
    return float(steps * grid_s)


class TickScheduler:
    """Ticks registered autopilots from one thread, in rounds on a grid of ``grid_s``."""

    def __init__(
        self,
        grid_s: float = GRID_S,
        clock: Callable[[], float] = time.monotonic,
        *,
        threaded: bool = True,
    ) -> None:
        self.grid_s = grid_s
        self._clock = clock
        self._threaded = threaded  # False: the caller drives run_round (tests)
        self._due: dict[Tickable, float] = {}
        self._changed = threading.Condition()
        self._round = threading.RLock()  # held while ticking: unregister waits for it
        self._thread: threading.Thread | None = None
        self._due_changed = False  # registrations changed since the next round was computed
        self.rounds = 0  # rounds run so far (how often the thread woke with work)

    def register(self, tickable: Tickable) -> None:
        """Tick ``tickable`` from the next round on (now)."""
        with self._changed:
            self._due[tickable] = self._clock()
            self._due_changed = True
            if self._thread is None and self._threaded:
                self._thread = threading.Thread(target=self._run, name="sim-ticks", daemon=True)
                self._thread.start()
            self._changed.notify()

    def unregister(self, tickable: Tickable) -> None:
        """Stop ticking ``tickable``; once this returns, its tick runs no more."""
        with self._changed:
            self._due.pop(tickable, None)
            self._due_changed = True
            self._changed.notify()
        with self._round:  # a round that already picked it finishes first
            pass

    @property
    def registered(self) -> int:
        with self._changed:
            return len(self._due)

    @property
    def running(self) -> bool:
        """Whether its thread is running (from the first registration to the last
        unregistration)."""
        with self._changed:
            return self._thread is not None

    def run_round(self, now: float) -> float | None:
        """Tick everything due at ``now``; the grid time of the next round (None: nothing
        registered). The thread calls this; tests call it with a fake clock."""
        with self._round:
            with self._changed:
                due = [t for t, at in self._due.items() if at <= now + _SAME_TIME_S]
            for tickable in due:
                try:
                    following = tickable.tick(now)
                except Exception:  # one autopilot's bug must not stop the others
                    _log.exception("%s: tick failed", tickable.label)
                    following = now + RETRY_S
                with self._changed:
                    if tickable in self._due:  # not unregistered meanwhile
                        self._due[tickable] = following
            self.rounds += 1
        with self._changed:
            return self._next_round()

    def _next_round(self) -> float | None:
        """The grid time of the earliest due time, None when nothing is registered (called
        with ``_changed`` held)."""
        self._due_changed = False
        if not self._due:
            return None
        return on_grid(min(self._due.values()), self.grid_s)

    def _run(self) -> None:
        while True:
            next_round = self.run_round(self._clock())
            with self._changed:
                while True:
                    # A registration since the round ended (whose notify found no waiter)
                    # or during the wait moves the next round: only then recompute it.
                    if self._due_changed:
                        next_round = self._next_round()
                    if next_round is None:
                        self._thread = None  # the next register starts a new thread
                        return
                    delay = next_round - self._clock()
                    if delay <= 0:
                        break
                    self._changed.wait(delay)


_SHARED = TickScheduler()  # its thread starts with the first autopilot


def shared_scheduler() -> TickScheduler:
    """The process's scheduler, which every autopilot uses unless given its own."""
    return _SHARED
