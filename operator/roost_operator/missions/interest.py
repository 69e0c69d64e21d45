"""Which Missions an event concerns, and when a Mission is looked at without one.

Missions run on the engine's work queue (:mod:`roost_operator.engine.workqueue`): kopf's
event handlers and the claim watch only add Mission keys (``namespace/name``) to it.
A Mission's progress depends on other objects, so an event on one of them queues only
the Missions that read it:

* a RedundantAutopilot or Vehicle → the Mission holding that vehicle (known from its
  last reconcile, or from the Vehicle's ``claimedBy``);
* a Vehicle or a claim → also every Mission still waiting for vehicles (it has not
  started), since a vehicle turning Ready or being released may be the one it needs;
* a Job → the Mission that owns it; the Mission's own spec or deletion → that Mission.

:class:`Interest` keeps what the last reconciles said; it is written by the queue's
workers and read by kopf's event loop and the claim watch's thread, hence its lock.
:func:`next_look` is the time-driven part: a Mission that waits for something no event
announces (an abort's timeout, a records round) is looked at again after the delay its
plan asked for, any other unfinished Mission after the resync period, a finished one
that holds nothing never again.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable


class Interest:
    """Which Mission holds which vehicle, and which Missions await vehicles."""

    def __init__(self) -> None:
        self._holder: dict[str, str] = {}
        self._waiting: set[str] = set()
        self._lock = threading.Lock()

    def track(self, key: str, *, vehicles: Iterable[str], waiting: bool) -> None:
        """After a reconcile: the vehicles ``key`` holds, and whether it awaits vehicles."""
        with self._lock:
            self._holder = {v: k for v, k in self._holder.items() if k != key}
            self._holder.update(dict.fromkeys(vehicles, key))
            if waiting:
                self._waiting.add(key)
            else:
                self._waiting.discard(key)

    def forget(self, key: str) -> None:
        """Mission ``key`` is finished or gone."""
        self.track(key, vehicles=(), waiting=False)

    def holder(self, vehicle: str) -> set[str]:
        """The Mission holding ``vehicle`` (a RedundantAutopilot changed)."""
        with self._lock:
            key = self._holder.get(vehicle)
        return set() if key is None else {key}

    def for_vehicle(self, vehicle: str, claimant: str | None) -> set[str]:
        """A Vehicle or its claim changed: its holder, its claimant, every waiting Mission."""
        with self._lock:
            keys = set(self._waiting)
            holder = self._holder.get(vehicle)
        if holder is not None:
            keys.add(holder)
        if claimant is not None:
            keys.add(claimant)
        return keys

    def waiting(self) -> frozenset[str]:
        """Missions that await vehicles (for tests and logs)."""
        with self._lock:
            return frozenset(self._waiting)


def next_look(*, finished: bool, requeue_after: float | None, resync_s: float) -> float | None:
    """Seconds until a Mission is reconciled again without an event (None: only on one).

    ``finished``: the Mission has ended and holds nothing; ``requeue_after``: the delay
    its plan asked for (an abort's poll, a records round, a lost claim race)."""
    if finished:
        return None
    if requeue_after is not None:
        return requeue_after
    return resync_s if resync_s > 0 else None
