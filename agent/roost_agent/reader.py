"""One thread that reads every autopilot link of the agent and runs its decision loop.

Why this module exists apart from the link: the reader knows transports, timers and the
selector, not MAVLink; a link hands it a :class:`Session` and is called back to drain it
or to report a failure (:class:`ReadLink`). Why a single reader: a stream parser holds
the unfinished frame of the last read, so the reader is the only thing that ever parses;
and a thread per link woke once per datagram, which cost more than parsing. The agent
runs its decision loop on it too (:meth:`LinkReader.drive`). It is on the per-message
path, so it is compiled with the link in the images (``setup.py``).
"""

from __future__ import annotations

import contextlib
import heapq
import logging
import math
import select
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

from roost_agent.fastpath import NOT_POSTPONED, Due, FastRoute, Routed, Run, pump
from roost_agent.health import RunState
from roost_agent.transport import Transport
from roost_agent.trust import SourceLock
from roost_mavlink.codec import StreamParser
from roost_mavlink.signing import Verifier

log = logging.getLogger(__name__)

READ_WAIT_S = 0.5  # longest the reader blocks in select() (timers and stop wake it sooner)
# While no hub client waits for routed frames, the reader lets datagrams gather this long
# after each wake-up: one wake-up then reads several (a PX4 onboard stream is ~400 a
# second), which is most of the agent's CPU time. Arrival times come from the kernel's
# receive timestamps, so the health judgement sees when a message arrived, not when it
# was read; only the wake-up for a changed fact (MAV_STATE, sensors) waits this long.
# (Linux turns arrival stamping on globally a moment after the first socket asks for it;
# until then a datagram's stamp is its read time, which is what an unstamped read gets.)
BATCH_S = 0.005
_PUMP_LIMIT = 256  # datagrams the fast path reads before Python takes them


class ReadLink(Protocol):
    """What the reader calls back on the link a session belongs to
    (:class:`roost_agent.link.AutopilotLink`)."""

    def drain(self, session: Session) -> None:
        """Read what the session's transport has; failures propagate."""

    def failed(self, exc: Exception, session: Session | None) -> None:
        """Report a failure, close, and reopen with backoff (on the reader thread)."""

    def run_state(self) -> RunState | None:
        """What the fast path must respect to hand the stream over in runs (None: not)."""


@dataclass
class Session:
    """What one opened transport needs while it reads."""

    transport: Transport
    lock: SourceLock
    verifier: Verifier | None
    parser: StreamParser = field(default_factory=StreamParser)  # streams (TCP, serial) only
    accepted_at_open: int = 0
    link: ReadLink | None = None
    fd: int = -1  # the descriptor the reader selects on
    urgent_fd: int | None = None  # a steered link's urgent socket (it selects on it too)
    arrived: float = float("-inf")  # the time given to the last datagram read
    # What the hub's fast path read of this session in C (roost_agent.fastpath), for the
    # next drain to take instead of reading the transport.
    pushed: list[Routed | Run] | None = None


class Poller:
    """A poll set of descriptors, each with what the reader reads there (a session, or
    None for the wake-up socket): :mod:`selectors` without its key objects. The reader
    waits in it at every wake-up, which while a hub client waits for routed frames is
    once per datagram; the selectors module is interpreted and built a key tuple per
    ready descriptor, this is compiled with the reader. ``poll`` rather than ``epoll``:
    the set is a few descriptors, and poll exists wherever the agent runs."""

    def __init__(self) -> None:
        self._poll = select.poll()
        self._data: dict[int, Session | None] = {}

    def register(self, fd: int, data: Session | None) -> None:
        """Watch ``fd`` for reading (KeyError: already watched)."""
        if fd in self._data:
            raise KeyError(fd)
        self._poll.register(fd, select.POLLIN)
        self._data[fd] = data

    def unregister(self, fd: int) -> None:
        """Stop watching ``fd`` (KeyError: not watched)."""
        del self._data[fd]
        self._poll.unregister(fd)

    def select(self, timeout: float) -> list[Session | None]:
        """What is readable (or failed: a read tells how), waiting up to ``timeout`` s."""
        events = self._poll.poll(math.ceil(timeout * 1000) if timeout > 0 else 0)
        data = self._data
        return [data[fd] for fd, _ in events if fd in data]

    def close(self) -> None:
        for fd in list(self._data):
            self.unregister(fd)


def _no_route() -> FastRoute | None:
    return None


Split = tuple[object, float, float, float, float]
"""After a tick (``Agent.postponable``): the link whose message age the tick's due is (or
may be), the first due no message postpones, that age, frozen telemetry's due and the
age of the last ``time_boot_ms`` advance at which it falls."""


def _no_split() -> Split | None:
    return None


class LinkReader:
    """One thread that reads every link: a selector over their transports.

    Why one thread, not one per link: a thread per link woke once per datagram and
    handed the GIL over each time, which cost several times the parsing itself. Here one
    wake-up reads whatever every link has. Driven by a tick (:meth:`drive`, the agent's
    decision loop) it wakes once per tick, reads, then ticks; on its own it lets
    datagrams gather for :data:`BATCH_S` after each read. Either way it wakes for every
    datagram while :attr:`hurry` says a client waits for routed frames, and messages keep
    their kernel arrival time.

    Opening a transport can block (a TCP connect, a serial port), so it happens on a
    short-lived thread per attempt; the opened session is handed to the reader. Failures
    and reopen timers are the links' (:meth:`ReadLink.failed`); the reader only
    runs them. Everything that touches the selector runs on the reader thread
    (:meth:`call`), so a closed file descriptor is never polled.
    """

    def __init__(
        self,
        *,
        hurry: Callable[[], bool] = lambda: False,
        batch_s: float = BATCH_S,
        name: str = "link-reader",
    ) -> None:
        self.hurry = hurry
        # While hurried, the hub's route for the fast path (roost_agent.fastpath), if any.
        self.fast_route: Callable[[], FastRoute | None] = _no_route
        self.postponable: Callable[[], Split | None] = _no_split
        self._periodic_tick = math.nan  # the next tick the read interval alone sets
        self._tick_due = math.inf  # when the last tick said it is next due (inf: never)
        self.batch_s = batch_s
        self._name = name
        self._selector = Poller()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._selector.register(self._wake_r.fileno(), None)
        self._calls: deque[tuple[Callable[[], None], threading.Event]] = deque()
        self._timers: list[tuple[float, int, Callable[[], None]]] = []
        self._timer_serial = 0
        # While nothing hurries it, the reader sleeps on the wake-up socket and the
        # steered links' urgent sockets; for the short interval after an urgent socket
        # woke it, on the wake-up socket alone (_calls_only): a sender flooding the
        # urgent socket (heartbeats are easy to forge) cannot make it wake more often
        # than the unsteered reader would.
        self._idle = Poller()
        self._idle.register(self._wake_r.fileno(), None)
        self._calls_only = Poller()
        self._calls_only.register(self._wake_r.fileno(), None)
        self._urgent_quiet_until = -math.inf
        self._sessions: dict[int, Session] = {}
        self._stopping = False
        self._serving_thread: threading.Thread | None = None
        self._tick: Callable[[], float | None] | None = None
        self._tick_s = self._short_tick_s = self._steered_tick_s = self._routed_tick_s = 0.0
        self._steered = False
        self._urgent = False
        # When (time.monotonic) the last read of every link began: what had arrived by
        # then has been read (the ticking loop only).
        self._read_at = -math.inf

    def drive(
        self,
        tick: Callable[[], float | None],
        tick_s: float,
        steered_tick_s: float | None = None,
        routed_tick_s: float | None = None,
    ) -> None:
        """Run ``tick`` on the reader thread every ``tick_s`` (and at once when :meth:`poke`
        d), right after reading: the agent's decision loop. Every datagram that arrived by
        then is read first, so one wake-up per tick serves reading and deciding. ``tick``
        returns when (``time.monotonic``) it is next due sooner than that, if it is.
        While every link read is steered (an urgent socket wakes the reader for what must
        be read at once: :mod:`roost_agent.steering`), the interval is ``steered_tick_s``;
        while, besides, the hub's fast path takes the active autopilot's stream in runs
        (and so returns at once with whatever Python must read whole), ``routed_tick_s``.
        Call before :meth:`start`."""
        self._tick, self._short_tick_s = tick, tick_s
        self._steered_tick_s = tick_s if steered_tick_s is None else steered_tick_s
        self._routed_tick_s = self._steered_tick_s if routed_tick_s is None else routed_tick_s
        self._tick_s = tick_s

    @property
    def tick_s(self) -> float:
        """The read interval now (it depends on whether every link read is steered)."""
        return self._tick_s

    def as_of(self, now: float) -> float:
        """The time a health judgement made at ``now`` (``time.monotonic``) outside the
        decision loop stands for: the start of the last read, as what arrived since is
        not read yet, so a message age does not grow between reads, nor while a loaded
        machine runs the reader late. Never more than :data:`READ_WAIT_S` before
        ``now``: the links of a reader stalled longer than that still age."""
        if self._serving_thread is None or self._tick is None:
            return now
        return max(min(now, self._read_at), now - READ_WAIT_S)

    def poke(self) -> None:
        """Tick as soon as possible (from any thread; on the reader thread: after reading)."""
        self._urgent = True
        if threading.current_thread() is not self._serving_thread:
            self._wake()

    def look_again(self) -> None:
        """Wake the reader to look again at what it waits for, without a tick (from any
        thread): the hub's clients changed, and the fast path waits with a route made
        for the ones before."""
        if threading.current_thread() is not self._serving_thread:
            self._wake()

    def start(self) -> None:
        self._serving_thread = threading.Thread(target=self._serve, name=self._name, daemon=True)
        self._serving_thread.start()

    def stop(self) -> None:
        self._stopping = True
        self._wake()
        if self._serving_thread is not None:
            self._serving_thread.join(timeout=2)
        self._selector.close()
        self._idle.close()
        self._calls_only.close()
        self._wake_r.close()
        self._wake_w.close()

    def call(self, fn: Callable[[], None], timeout_s: float = 2.0) -> None:
        """Run ``fn`` on the reader thread and wait for it (at once when already there)."""
        thread = self._serving_thread
        if thread is None or threading.current_thread() is thread or not thread.is_alive():
            fn()
            return
        done = threading.Event()
        self._calls.append((fn, done))
        self._wake()
        done.wait(timeout_s)

    def after(self, delay_s: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the reader thread ``delay_s`` from now (reader thread only)."""
        self._timer_serial += 1
        heapq.heappush(self._timers, (time.monotonic() + delay_s, self._timer_serial, fn))

    def attach(self, session: Session) -> None:
        """Read ``session``'s transport from now on (reader thread only)."""
        fd = session.transport.fileno()
        self._sessions[fd] = session
        session.fd = fd
        self._selector.register(fd, session)
        session.urgent_fd = session.transport.urgent_fileno()
        if session.urgent_fd is not None:  # wakes the reader whether it hurries or not
            self._selector.register(session.urgent_fd, session)
            self._idle.register(session.urgent_fd, session)
        self._choose_interval()

    def detach(self, session: Session) -> None:
        """Stop reading ``session`` (reader thread only; closing it is the caller's)."""
        for fd, known in list(self._sessions.items()):
            if known is session:
                del self._sessions[fd]
                with contextlib.suppress(KeyError, ValueError):
                    self._selector.unregister(fd)
        if session.urgent_fd is not None:
            for selector in (self._selector, self._idle):
                with contextlib.suppress(KeyError, ValueError):
                    selector.unregister(session.urgent_fd)
            session.urgent_fd = None
        self._choose_interval()

    def _choose_interval(self) -> None:
        sessions = self._sessions.values()
        steered = bool(sessions) and all(s.urgent_fd is not None for s in sessions)
        self._steered = steered
        self._tick_s = self._steered_tick_s if steered else self._short_tick_s

    def _wake(self) -> None:
        with contextlib.suppress(OSError):  # already awake (full), or closing
            self._wake_w.send(b"\0")

    def _run_calls(self) -> None:
        try:
            while self._wake_r.recv(4096):
                pass
        except BlockingIOError:
            pass
        while self._calls:
            fn, done = self._calls.popleft()
            try:
                fn()
            except Exception:
                log.exception("link reader call failed")
            finally:
                done.set()

    def _run_timers(self) -> float:
        """Run due timers; seconds until the next one (capped at READ_WAIT_S)."""
        timers = self._timers
        while timers and timers[0][0] <= time.monotonic():
            _, _, fn = heapq.heappop(timers)
            try:
                fn()
            except Exception:
                log.exception("link reader timer failed")
        return (
            READ_WAIT_S
            if not timers
            else max(0.0, min(READ_WAIT_S, timers[0][0] - time.monotonic()))
        )

    def _serve(self) -> None:
        if self._tick is not None:
            self._serve_ticking(self._tick)
        else:
            self._serve_reading()
        for session in list(self._sessions.values()):
            self.detach(session)

    def _read(self, ready: list[Session | None]) -> None:
        if len(ready) == 1:  # most wake-ups: one link's socket, or the wake-up socket
            only = ready[0]
            if only is None:
                self._run_calls()
            else:
                self._drain(only)
            return
        drained: set[int] = set()  # a steered link can be ready on both of its sockets
        for session in ready:
            if session is None:
                self._run_calls()
            elif id(session) not in drained:
                drained.add(id(session))
                self._drain(session)

    def _drain(self, session: Session) -> None:
        if self._sessions.get(session.fd) is not session:
            return  # detached since the select (a link stopped by a call): not ours to read
        link = session.link
        assert link is not None
        try:
            link.drain(session)
            if session.transport.fileno() != session.fd:  # a TCP listener took a client
                self.detach(session)
                self.attach(session)
        except Exception as exc:  # every failure: the link reports and reopens
            self.detach(session)
            link.failed(exc, session)

    def _drain_ready(self) -> None:
        """Read the links that have data: one poll that does not wait asks which, cheaper
        than a failing read of every idle link at every tick."""
        self._read(self._select(self._selector, 0.0))

    def _select(self, selector: Poller, timeout: float) -> list[Session | None]:
        try:
            return selector.select(timeout)
        except OSError:
            if self._stopping:
                return []
            raise

    def _serve_reading(self) -> None:
        """Read as datagrams come (batched while nothing hurries)."""
        while not self._stopping:
            timeout = self._run_timers()
            self._read(self._select(self._selector, timeout))
            if self.batch_s > 0 and not self._calls and not self.hurry():
                time.sleep(self.batch_s)

    def _sleep(self, timeout: float) -> None:
        """Wait up to ``timeout`` for a call, a timer or an urgent datagram (urgent
        datagrams at most once per short interval), reading what woke the reader."""
        now = time.monotonic()
        if now < self._urgent_quiet_until:
            self._read(self._select(self._calls_only, min(timeout, self._urgent_quiet_until - now)))
            return
        ready = self._select(self._idle, timeout)
        if any(session is not None for session in ready):
            self._urgent_quiet_until = time.monotonic() + self._short_tick_s
        self._read(ready)

    def _pump(self, route: FastRoute, timeout: float, next_tick: float) -> list[Session | None]:
        """Wait for the next tick in C (:mod:`roost_agent.fastpath`): the active
        autopilot's frames are routed as they come; what C read is the fast session's
        next drain. Wakes early for a call (the wake-up socket), for what must be read at
        once (another link's urgent socket, a heartbeat or command answer on the fast
        link's, a datagram C did not route), at most once per short interval for the
        urgent sockets as the unhurried reader, or when the batch is full. Then every
        other link with data is read too (as an unhurried reader reads them).

        When the tick is due for the fast link's message age (a late or silent stream),
        C keeps postponing it while that link's frames come, so a stream that flows wakes
        the reader at the read interval only, and a silence at the moment it falls due;
        while C takes runs, frozen telemetry's due likewise with each frame whose
        ``time_boot_ms`` advances. Every other deadline (timers, the read interval,
        thresholds no message postpones) stays as it was. While C takes runs and every
        link is steered, the read interval is the routed one: C returns at once with
        whatever Python must read whole (but for the short interval after an early
        return, when urgent datagrams wait, as does the read, for the steered one)."""
        session = route.session
        now = time.monotonic()
        link = session.link
        runs = link.run_state() if link is not None else None
        periodic = self._periodic_tick
        timers = self._timers
        timer_at = timers[0][0] if timers else math.inf
        urgent_ok = now >= self._urgent_quiet_until
        if (
            runs is not None
            and self._steered
            and urgent_ok
            and timeout > 0
            and next_tick in (periodic, self._tick_due)
        ):
            periodic += self._routed_tick_s - self._tick_s
            next_tick = min(periodic, self._tick_due)
            timeout = max(0.0, min(timer_at, now + READ_WAIT_S, next_tick) - now)
        due = NOT_POSTPONED
        split = self.postponable() if next_tick == self._tick_due and timeout > 0 else None
        if split is not None and split[0] is session.link and math.isfinite(split[2]):
            _, fixed, age, frozen, frozen_age = split
            if runs is None or not math.isfinite(frozen_age):
                # C moves frozen telemetry's due only while it takes runs
                fixed, frozen, frozen_age = min(fixed, frozen), math.inf, -1.0
            hard = min(timer_at, now + READ_WAIT_S, periodic, fixed)
            due = Due(next_tick - now, age, frozen - now, frozen_age)
            timeout = max(0.0, hard - now)
        wake = [self._wake_r.fileno()]
        if urgent_ok:
            wake.extend(
                s.urgent_fd
                for s in self._sessions.values()
                if s is not session and s.urgent_fd is not None
            )
        try:
            items, _ = pump(
                route,
                wake,
                timeout,
                due,
                urgent_returns=urgent_ok,
                limit=_PUMP_LIMIT,
                runs=runs,
            )
        except OSError:
            # The link's own read meets the failure again and reports it (ReadLink.failed).
            return [session]
        except Exception:
            # A fault in the fast path itself (not the socket's) would meet every call
            # again, and the thread that decides failovers must not die of it: what this
            # call read is lost, and the link is read and routed in Python from now on.
            log.exception("the hub's fast path failed; the hub routes in Python from now on")
            self.fast_route = _no_route
            return [session]
        if time.monotonic() < now + timeout:  # early: urgent sockets wait a short interval
            self._urgent_quiet_until = time.monotonic() + self._short_tick_s
        ready: list[Session | None] = [
            s for s in self._select(self._selector, 0.0) if s is not session
        ]
        if items:
            previous = session.pushed
            session.pushed = items if previous is None else previous + items
            ready.append(session)
        return ready

    def _serve_ticking(self, tick: Callable[[], float | None]) -> None:
        """Read and decide: wake for the next tick (for data too while hurried), read
        everything that arrived, then tick when due or poked; the next tick is
        ``tick_s`` later, or sooner when the tick says it is due sooner."""
        next_tick = time.monotonic()
        while not self._stopping:
            timeout = min(self._run_timers(), max(0.0, next_tick - time.monotonic()))
            if self.hurry():
                route = self.fast_route()
                if route is not None and self._sessions.get(route.session.fd) is route.session:
                    ready = self._pump(route, 0.0 if self._urgent else timeout, next_tick)
                else:
                    ready = self._select(self._selector, timeout)
                self._read_at = time.monotonic()
                self._read(ready)
            else:
                if timeout > 0 and not self._urgent:
                    self._sleep(timeout)
                self._read_at = time.monotonic()
                self._drain_ready()
            now = time.monotonic()
            if now >= next_tick or self._urgent:
                self._urgent = False
                due = None
                try:
                    due = tick()
                except Exception:  # the loop must outlive any bug in one tick
                    log.exception("decision tick failed")
                now = time.monotonic()
                next_tick = self._periodic_tick = now + self._tick_s
                self._tick_due = math.inf if due is None else due
                if due is not None and now < due < next_tick:
                    next_tick = due
                elif due is not None and due <= now:
                    # A decision the tick waits for is already due (the tick ran late,
                    # or the time it named passed while it ran): look again as soon as
                    # an unsteered reader would, not a whole steered interval later.
                    next_tick = now + self._short_tick_s
