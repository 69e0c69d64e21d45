"""Whom a link believes: the source lock and the alarm for traffic it refuses.

Why this module exists apart from the link: the rules for which sender is the autopilot
are pure bookkeeping with explicit times, so they are unit-tested without sockets
(tests/unit/test_agent_trust.py), and a reviewer of the trust rules reads them here in
one place. The link (:mod:`roost_agent.link`) applies them to every datagram, so this
module is compiled with it in the images (``setup.py``).

Trust, on UDP, where anyone who can reach the port can send:

- **Each datagram on its own.** A datagram is parsed by itself, and whatever it leaves
  unfinished is discarded with it and counted ``truncated`` (MAVLink over UDP never
  splits a frame across datagrams). Garbage, truncated or bad-CRC frames therefore cost
  only their own datagram; the autopilot's next frame always starts clean.
- **Source lock.** A link hears one address: the autopilot's. ``udpout://`` is locked to
  its destination, ``udp://HOST:PORT@PEER:PORT`` to the configured peer (``@PEER`` alone:
  any port of that host may prove itself). Otherwise the lock goes to the first address
  that proves itself: :data:`PROOF_HEARTBEATS` autopilot HEARTBEATs of the configured
  system and component id (``autopilot`` not INVALID; signed when signing is required),
  each no more than the heartbeat-error threshold after the previous one. Re-lock: when
  the locked address has sent nothing acceptable for the heartbeat-error threshold (the
  autopilot rebooted onto another port, or was replaced), the next address to prove itself
  takes the lock, with a warning Event. While the autopilot is alive nothing can take its
  lock. Until the first lock nothing reaches the health tracker, so a link counts as
  silent (not healthy) until its autopilot proved itself.
- **Foreign traffic** (datagrams from any other address while locked) is dropped unparsed
  and counted (``foreign``); more than :data:`FOREIGN_ALERT_PER_S` per second over
  :data:`ALERT_WINDOW_S` raises a warning Event (at most one per
  :data:`ALERT_QUIET_S`): a second sender is misconfigured or someone injects MAVLink.
- **Replies** go to the locked address only; before a lock a UDP listener sends nothing.
- **Signing** (:mod:`roost_agent.signing`): every frame sent is signed; while signing is
  required, unsigned, badly signed and replayed frames are dropped and counted, and
  repeated ones raise a warning Event the same way (:class:`RateAlarm`; the check itself
  is the link's, as it answers with the key the autopilot proved).

Without signing, the lock keeps off-path senders out but cannot stop a host that forges
the autopilot's own address and port; signing can.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from typing import Final

from roost_agent.transport import Address

MAX_SENDERS: Final = 16  # candidate addresses a source lock remembers
PROOF_HEARTBEATS: Final = 2
ALERT_WINDOW_S: Final = 10.0
FOREIGN_ALERT_PER_S: Final = 1.0
ALERT_QUIET_S: Final = 60.0


class SourceLock:
    """Which sender address a link believes is its autopilot (rules: module docstring).

    Pure bookkeeping with explicit times, so the rule is unit-tested without sockets.
    """

    def __init__(
        self,
        *,
        relock_after_s: float,
        fixed: Address | None = None,
        host: str | None = None,
        proof_heartbeats: int = PROOF_HEARTBEATS,
    ) -> None:
        self.relock_after_s = relock_after_s
        self.fixed = fixed
        self.host = host
        self.proof_heartbeats = proof_heartbeats
        self.locked: Address | None = fixed
        self.last_seen: float | None = None
        self._candidates: OrderedDict[Address, tuple[int, float]] = OrderedDict()

    def open_to_candidates(self, now: float) -> bool:
        """Whether another address may prove itself now."""
        if self.fixed is not None:
            return False
        if self.locked is None:
            return True
        return self.last_seen is None or now - self.last_seen >= self.relock_after_s

    def hears(self, address: Address, now: float) -> bool:
        """Whether frames from ``address`` are parsed at all."""
        if address == self.locked:
            return True
        if self.host is not None and address[0] != self.host:
            return False
        return self.open_to_candidates(now)

    def seen(self, now: float) -> None:
        """The locked address delivered an acceptable message."""
        self.last_seen = now

    def prove(self, address: Address, now: float) -> bool:
        """A valid autopilot heartbeat from a candidate; True when it takes the lock now."""
        if not self.hears(address, now) or address == self.locked:
            return False
        count, last = self._candidates.pop(address, (0, now))
        count = count + 1 if now - last <= self.relock_after_s else 1
        if count < self.proof_heartbeats:
            self._candidates[address] = (count, now)
            while len(self._candidates) > MAX_SENDERS:
                self._candidates.popitem(last=False)
            return False
        self._candidates.clear()
        self.locked, self.last_seen = address, now
        return True


class RateAlarm:
    """Counts events in a window; fires when the rate passes a bound, then stays quiet."""

    def __init__(self, per_s: float, window_s: float = ALERT_WINDOW_S) -> None:
        self.threshold = max(1, round(per_s * window_s))
        self.window_s = window_s
        self._times: deque[float] = deque()
        self._quiet_until = 0.0
        self.sources: OrderedDict[str, int] = OrderedDict()

    def note(self, now: float, source: str) -> str | None:
        """Record one; "N in S s" when the alarm fires, else None."""
        times = self._times
        times.append(now)
        while times and now - times[0] > self.window_s:
            times.popleft()
        self.sources[source] = self.sources.pop(source, 0) + 1
        while len(self.sources) > 4:
            self.sources.popitem(last=False)
        if len(times) < self.threshold or now < self._quiet_until:
            return None
        self._quiet_until = now + ALERT_QUIET_S
        text = f"{len(times)} in {max(now - times[0], 0.001):.2f} s"
        times.clear()
        return text

    def describe(self) -> str:
        text = ", ".join(self.sources)
        self.sources.clear()
        return text


def address_text(address: Address | None) -> str:
    return "the serial/TCP peer" if address is None else f"{address[0]}:{address[1]}"
