"""Stand-in streams for the simulator's tick scheduler: one that records its ticks at a
rate, one that fails."""

from __future__ import annotations

import threading


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
