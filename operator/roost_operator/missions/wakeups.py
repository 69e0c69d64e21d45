"""Who to wake when something a mission depends on changes.

Each Mission has one long-running reconcile loop (a kopf daemon). Between reconciles it
sleeps until woken or until its resync period passes. Events on other objects wake
only the missions that care:

* a RedundantAutopilot or Vehicle → the mission that holds that vehicle (known from the
  last reconcile, or from the Vehicle's ``claimedBy``);
* a Vehicle → also every mission still waiting for vehicles (Pending or Preflight), since
  a vehicle turning Ready or being released may be the one it needs;
* a Job → the Mission that owns it; a Mission's own spec change → that Mission.

Everything here runs on kopf's event loop (no locks needed); a wake-up is an
``asyncio.Event``, so a burst of events before the loop runs again costs one reconcile.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Iterable


class Wakeups:
    """Per-mission wake-up signals and which mission holds which vehicle."""

    def __init__(self) -> None:
        self._events: dict[str, asyncio.Event] = {}
        self._holder: dict[str, str] = {}
        self._waiting: set[str] = set()

    def register(self, key: str) -> asyncio.Event:
        """The wake-up signal of mission ``key`` (``namespace/name``)."""
        return self._events.setdefault(key, asyncio.Event())

    def forget(self, key: str) -> None:
        """Mission ``key``'s loop has ended."""
        self._events.pop(key, None)
        self._waiting.discard(key)
        self._holder = {v: k for v, k in self._holder.items() if k != key}

    def track(self, key: str, *, vehicles: Iterable[str], waiting: bool) -> None:
        """After a reconcile: the vehicles ``key`` holds, and whether it awaits vehicles."""
        self._holder = {v: k for v, k in self._holder.items() if k != key}
        self._holder.update(dict.fromkeys(vehicles, key))
        if waiting:
            self._waiting.add(key)
        else:
            self._waiting.discard(key)

    def wake(self, key: str) -> None:
        event = self._events.get(key)
        if event is not None:
            event.set()

    def wake_holder(self, vehicle: str) -> None:
        """Wake the mission holding ``vehicle`` (a RedundantAutopilot changed)."""
        key = self._holder.get(vehicle)
        if key is not None:
            self.wake(key)

    def wake_for_vehicle(self, vehicle: str, claimant: str | None) -> None:
        """A Vehicle changed: wake its holder, its claimant and every waiting mission."""
        self.wake_holder(vehicle)
        if claimant is not None:
            self.wake(claimant)
        for key in self._waiting:
            self.wake(key)

    def waiting(self) -> frozenset[str]:
        """Missions that await vehicles (for tests and logs)."""
        return frozenset(self._waiting)


async def sleep_until_woken(
    wakeup: asyncio.Event, stopped: Awaitable[object], delay: float
) -> bool:
    """Sleep up to ``delay`` seconds; return early when woken or stopped. True if woken."""
    waiters = [asyncio.ensure_future(wakeup.wait()), asyncio.ensure_future(stopped)]
    try:
        await asyncio.wait(waiters, timeout=delay, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for waiter in waiters:
            waiter.cancel()
    return wakeup.is_set()
