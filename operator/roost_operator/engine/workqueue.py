"""A work queue between kopf's watch events and the Vehicle controller's reconciles.

Why: kopf calls a handler per watch event, in a thread of its executor. A handler
that reconciled right there would, at fleet scale, mean one full reconcile per
event (a component pod's way to Ready alone sends several), handlers of one vehicle queueing up
behind its lock in kopf's threads, and a periodic timer per Vehicle to catch what an
event handler dropped (kopf never retries event handlers). This queue is the model of
controller-runtime's: handlers only *add the vehicle's name*, and a fixed pool of
workers reconciles.

* **Coalescing**: a name is queued at most once. Ten events about one vehicle before a
  worker picks it up cost one reconcile; an event while it is being reconciled marks it
  dirty, and it is reconciled once more afterwards (never twice at once).
* **Back-pressure**: the queue holds at most one entry per vehicle, and ``workers``
  threads bound how many reconciles (and so API requests) run at once, whatever the
  event rate. kopf's own handlers return at once.
* **Retries**: a temporary failure re-queues the name after a per-name exponential
  backoff (``base`` doubling to ``cap``); a permanent one is reported once through
  ``on_permanent`` and not retried until something about the vehicle changes (the next
  event adds it again). Success resets the backoff.
* **Deadlines** (:meth:`WorkQueue.add_at`): "reconcile this vehicle at time T" for
  things that happen without an event (an agent that stopped reporting goes stale). A
  name has one deadline; a later :meth:`add_at` moves it, so a vehicle whose agent keeps
  reporting is never reconciled by its deadline.

Pure threading and a clock; it knows nothing of kopf or Kubernetes, so it is unit-tested
with a fake reconcile.
"""

from __future__ import annotations

import heapq
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

log = logging.getLogger(__name__)


class Permanent(Exception):  # noqa: N818 - the name says what the reconcile reports
    """Raised by a reconcile whose failure will repeat until the object changes."""


@dataclass(frozen=True)
class Backoff:
    """Per-name retry delays after temporary failures: ``base`` · 2ⁿ, at most ``cap``."""

    base_s: float = 1.0
    cap_s: float = 60.0

    def delay(self, failures: int) -> float:
        return float(min(self.cap_s, self.base_s * 2 ** max(0, failures - 1)))


Reconcile = Callable[[str], None]
"""Reconcile one name; raise :class:`Permanent` (or a subclass) for a permanent failure,
anything else for a temporary one."""


class WorkQueue:
    """Coalescing, rate-limited reconcile queue with a fixed worker pool (see module doc)."""

    def __init__(
        self,
        reconcile: Reconcile,
        *,
        workers: int = 4,
        backoff: Backoff | None = None,
        is_permanent: Callable[[BaseException], bool] = lambda error: isinstance(error, Permanent),
        on_permanent: Callable[[str, BaseException], None] = lambda name, error: None,
        clock: Callable[[], float] = time.monotonic,
        name: str = "workqueue",
    ) -> None:
        self._reconcile = reconcile
        self._workers = workers
        self._backoff = backoff or Backoff()
        self._is_permanent = is_permanent
        self._on_permanent = on_permanent
        self._clock = clock
        self._name = name
        self._cond = threading.Condition()
        self._ready: deque[str] = deque()
        self._queued: set[str] = set()
        self._processing: set[str] = set()
        self._dirty: set[str] = set()
        self._deadlines: dict[str, float] = {}
        self._timers: list[tuple[float, str]] = []
        self._failures: dict[str, int] = {}
        self._threads: list[threading.Thread] = []
        self._stopping = False
        self.reconciles = 0
        """Reconciles run so far (for tests and benchmarks)."""

    # -- adding ----------------------------------------------------------------------

    def add(self, key: str) -> None:
        """Reconcile ``key`` soon (at most once more, however often it is added)."""
        with self._cond:
            self._add_locked(key)

    def add_at(self, key: str, when: float) -> None:
        """Reconcile ``key`` at ``when`` (this queue's clock); replaces its earlier deadline."""
        with self._cond:
            self._deadlines[key] = when
            heapq.heappush(self._timers, (when, key))
            self._cond.notify_all()

    def cancel_at(self, key: str, when: float) -> None:
        """Drop ``key``'s deadline if it is still ``when`` (one moved since stays)."""
        with self._cond:
            if self._deadlines.get(key) == when:
                del self._deadlines[key]

    def forget(self, key: str) -> None:
        """The object is gone: drop its deadline and backoff (a queued run still happens)."""
        with self._cond:
            self._deadlines.pop(key, None)
            self._failures.pop(key, None)

    def _add_locked(self, key: str) -> None:
        if key in self._processing:
            self._dirty.add(key)
        elif key not in self._queued:
            self._queued.add(key)
            self._ready.append(key)
            self._cond.notify()

    def _retry_locked(self, key: str, delay: float) -> None:
        when = self._clock() + delay
        current = self._deadlines.get(key)
        if current is None or when < current:
            self._deadlines[key] = when
            heapq.heappush(self._timers, (when, key))

    # -- running ---------------------------------------------------------------------

    def start(self) -> None:
        """Start the workers (idempotent)."""
        with self._cond:
            if self._threads:
                return
            self._stopping = False
            self._threads = [
                threading.Thread(target=self._work, name=f"{self._name}-{i}", daemon=True)
                for i in range(self._workers)
            ]
        for thread in self._threads:
            thread.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop the workers after the reconciles they are running."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        for thread in self._threads:
            thread.join(timeout=timeout_s)
        self._threads = []

    def depth(self) -> int:
        """Names waiting to be reconciled now."""
        with self._cond:
            return len(self._ready)

    def idle(self) -> bool:
        """Nothing queued, nothing running (deadlines may be pending)."""
        with self._cond:
            return not self._ready and not self._processing

    def _due_locked(self) -> float | None:
        """Move due deadlines to the ready queue; seconds until the next one (None: none)."""
        now = self._clock()
        while self._timers:
            when, key = self._timers[0]
            if self._deadlines.get(key) != when:  # moved or forgotten: a stale entry
                heapq.heappop(self._timers)
                continue
            if when > now:
                return when - now
            heapq.heappop(self._timers)
            del self._deadlines[key]
            self._add_locked(key)
        return None

    def _next(self) -> str | None:
        with self._cond:
            while not self._stopping:
                wait = self._due_locked()
                if self._ready:
                    key = self._ready.popleft()
                    self._queued.discard(key)
                    self._processing.add(key)
                    return key
                self._cond.wait(wait)
            return None

    def _work(self) -> None:
        while (key := self._next()) is not None:
            self._run(key)

    def _run(self, key: str) -> None:
        failed: BaseException | None = None
        try:
            self._reconcile(key)
        except Exception as error:  # every failure is the queue's to retry or report
            failed = error
        permanent = failed is not None and self._is_permanent(failed)
        delay = 0.0
        with self._cond:
            self.reconciles += 1
            self._processing.discard(key)
            if failed is None or permanent:
                self._failures.pop(key, None)
            else:
                failures = self._failures.get(key, 0) + 1
                self._failures[key] = failures
                delay = self._backoff.delay(failures)
                self._retry_locked(key, delay)
            if key in self._dirty:
                self._dirty.discard(key)
                self._add_locked(key)
            self._cond.notify_all()
        if failed is None:
            return
        if permanent:
            try:
                self._on_permanent(key, failed)
            except Exception:
                log.exception("%s: reporting the permanent failure of %s failed", self._name, key)
        else:
            log.warning("%s: %s failed, retrying in %.1f s: %s", self._name, key, delay, failed)
