"""Ask every autopilot for the telemetry the health model judges, and check it arrives.

Why: ArduCopter sends nothing but HEARTBEAT on a link until someone requests streams, so
an agent that only listens never learns whether a standby is armed and in the air (it
cannot be a failover target) and notices a dead link only by heartbeat age (seconds). PX4's
onboard link streams by itself, but not necessarily every message the model uses. So the
agent asks, per stack, and verifies:

- an *epoch* starts when the autopilot is first heard (its first heartbeat), after it
  rebooted (the health tracker counts reboots) and when it is heard again after a link
  loss — each is a moment the autopilot's stream configuration may be new;
- each check window (:data:`CHECK_S`) the keeper measures the rate of every wanted
  message from the tracker's per-type counters; a message below
  :data:`RATE_TOLERANCE` of its wanted rate is requested with MAV_CMD_SET_MESSAGE_INTERVAL
  (only what is missing: a faster stream, like PX4's 100 Hz ATTITUDE, is never slowed);
- on ArduPilot, when SET_MESSAGE_INTERVAL was refused (COMMAND_ACK DENIED/UNSUPPORTED/
  FAILED) or did not bring the rates, the request falls back to REQUEST_DATA_STREAM for the
  stream group that carries the message (older firmware, or SRx parameters in the way);
- after each check the tracker is told the rate of the requested streams that arrive,
  and liveness ("silent for N ms") is judged on them; once every wanted rate arrives the
  epoch is *verified*, checks continue at a slower period, and a stream that stops is
  requested again;
- repeated failures back off (up to :data:`MAX_BACKOFF_S`) so a stream the firmware does
  not have (PX4 without ESTIMATOR_STATUS on a link) is not requested forever at 1 Hz.

:class:`StreamKeeper` is a pure state machine (time and counters in, requests out) so its
decision table is unit-tested; :func:`send_requests` turns its output into MAVLink on a
link. The agent runs one keeper per autopilot on its own thread.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol

from roost_agent.health import StreamFacts
from roost_api.core import Stack
from roost_mavlink import MAV_CMD_SET_MESSAGE_INTERVAL, MavResult

CHECK_S = 1.0  # a measuring window
VERIFIED_CHECK_S = 5.0  # how often verified streams are re-checked
RATE_TOLERANCE = 0.6  # a stream counts as arriving at this fraction of its wanted rate
LINK_LOST_S = 3.0  # no message this long: the next message starts a new epoch
MAX_BACKOFF_S = 10.0

# Message ids (common.xml / ardupilotmega.xml).
MESSAGE_IDS: dict[str, int] = {
    "SYS_STATUS": 1,
    "ATTITUDE": 30,
    "GLOBAL_POSITION_INT": 33,
    "ESTIMATOR_STATUS": 230,
    "EXTENDED_SYS_STATE": 245,
    "EKF_STATUS_REPORT": 193,
}

# What the health model reads, per stack, in Hz. ATTITUDE carries the liveness stream
# (at 50 Hz a 500 ms silence is 25 missing messages); GLOBAL_POSITION_INT the altitude
# and vertical speed the safety routine confirms a hold by; SYS_STATUS the sensors;
# EXTENDED_SYS_STATE the landed state; the estimator report its flags.
WANTED: dict[Stack, dict[str, float]] = {
    Stack.PX4: {
        "ATTITUDE": 50.0,
        "GLOBAL_POSITION_INT": 10.0,
        "SYS_STATUS": 5.0,
        "EXTENDED_SYS_STATE": 5.0,
        "ESTIMATOR_STATUS": 1.0,
    },
    Stack.ARDUPILOT: {
        "ATTITUDE": 50.0,
        "GLOBAL_POSITION_INT": 10.0,
        "SYS_STATUS": 5.0,
        "EXTENDED_SYS_STATE": 5.0,
        "EKF_STATUS_REPORT": 2.0,
    },
}

# ArduPilot's REQUEST_DATA_STREAM groups (MAV_DATA_STREAM) that carry each message.
DATA_STREAM_GROUPS: dict[str, int] = {
    "SYS_STATUS": 2,  # EXTENDED_STATUS
    "GLOBAL_POSITION_INT": 6,  # POSITION
    "ATTITUDE": 10,  # EXTRA1
    "EXTENDED_SYS_STATE": 12,  # EXTRA3 (where the firmware sends it at all)
    "EKF_STATUS_REPORT": 12,  # EXTRA3
}

_REFUSALS = {MavResult.DENIED, MavResult.UNSUPPORTED, MavResult.FAILED}


class Method(StrEnum):
    """How a stream is requested."""

    INTERVAL = "SET_MESSAGE_INTERVAL"
    DATA_STREAM = "REQUEST_DATA_STREAM"


@dataclass(frozen=True)
class Request:
    """Ask for ``message`` at ``hz`` by ``method``."""

    message: str
    hz: float
    method: Method


class Why(StrEnum):
    """What started an epoch (logged with the requests)."""

    CONNECT = "connect"
    REBOOT = "reboot"
    RELINK = "link regained"


@dataclass
class StreamKeeper:
    """Decides, per check window, which streams of one autopilot to request."""

    stack: Stack
    wanted: Mapping[str, float] = field(default_factory=dict)
    epoch: Why | None = None
    verified: bool = False
    attempts: int = 0
    fallback: bool = False  # ArduPilot: also REQUEST_DATA_STREAM
    _window_at: float | None = None
    _window_counts: dict[str, int] = field(default_factory=dict)
    _next_check: float = 0.0
    _reboots: int = 0
    _lost: bool = False
    missing: tuple[str, ...] = ()
    rates: dict[str, float] = field(default_factory=dict)
    checks: int = 0  # measurements made (the agent updates the tracker after each)

    def __post_init__(self) -> None:
        self.stack = Stack(self.stack)
        if not self.wanted:
            self.wanted = dict(WANTED[self.stack])

    @property
    def settled(self) -> bool:
        """Whether stepping would ask nothing until something changes: the streams arrive
        as requested, or there is nobody to ask (not heard yet, or the link lost)."""
        return self.verified or self._lost or self.epoch is None

    @property
    def total_rate(self) -> float:
        """Messages per second of all wanted streams."""
        return sum(self.wanted.values())

    @property
    def arriving_rate(self) -> float | None:
        """Messages per second of the wanted streams that arrived in the last check (what
        liveness may expect), None before a check in this epoch or when none arrive."""
        if not self.rates:
            return None
        rate = sum(hz for name, hz in self.wanted.items() if name not in self.missing)
        return rate or None

    def _start(self, why: Why, facts: StreamFacts, now: float) -> None:
        self.epoch = why
        self.verified = False
        self.attempts = 0
        self.fallback = False
        self.missing = ()
        self.rates = {}
        self._window_at = now
        self._window_counts = dict(facts.counts)
        self._next_check = now + CHECK_S

    def step(self, facts: StreamFacts, now: float, last_ack: int | None = None) -> list[Request]:
        """The requests to send now (often none). ``last_ack``: the latest COMMAND_ACK
        result for SET_MESSAGE_INTERVAL from this autopilot, if any."""
        if facts.heartbeat_at is None:
            return []  # not heard yet: nobody to ask
        lost = facts.last_at is None or now - facts.last_at >= LINK_LOST_S
        if lost:
            self._lost = True
            self.verified = False
            return []
        if self.epoch is None:
            self._start(Why.CONNECT, facts, now)
        elif facts.reboots != self._reboots:
            self._start(Why.REBOOT, facts, now)
        elif self._lost:
            self._start(Why.RELINK, facts, now)
        self._reboots = facts.reboots
        self._lost = False
        if now < self._next_check:
            return []
        assert self._window_at is not None
        span = max(now - self._window_at, 1e-6)
        self.rates = {
            name: (facts.counts.get(name, 0) - self._window_counts.get(name, 0)) / span
            for name in self.wanted
        }
        self._window_at, self._window_counts = now, dict(facts.counts)
        self.checks += 1
        self.missing = tuple(
            name for name, hz in self.wanted.items() if self.rates[name] < RATE_TOLERANCE * hz
        )
        if not self.missing:
            self.verified = True
            self.attempts = 0
            self._next_check = now + VERIFIED_CHECK_S
            return []
        self.verified = False
        if self.stack is Stack.ARDUPILOT and (
            self.attempts >= 1 or (last_ack is not None and last_ack in _REFUSALS)
        ):
            self.fallback = True
        self.attempts += 1
        self._next_check = now + min(MAX_BACKOFF_S, CHECK_S * 2 ** max(0, self.attempts - 2))
        requests = [Request(n, self.wanted[n], Method.INTERVAL) for n in self.missing]
        if self.fallback:
            fastest: dict[int, str] = {}  # one request per group, at its fastest member's rate
            for name in self.missing:
                group = DATA_STREAM_GROUPS.get(name)
                if group is not None and (
                    group not in fastest or self.wanted[name] > self.wanted[fastest[group]]
                ):
                    fastest[group] = name
            requests += [
                Request(name, self.wanted[name], Method.DATA_STREAM) for name in fastest.values()
            ]
        return requests


class StreamLink(Protocol):
    """What sending requests needs from an autopilot link (AutopilotLink implements it)."""

    def send_command(
        self,
        command: int,
        params: tuple[float, float, float, float, float, float, float],
        confirmation: int = 0,
    ) -> bool:
        """Send COMMAND_LONG without waiting for the ack."""

    def request_data_stream(self, stream_id: int, hz: int) -> bool:
        """Send REQUEST_DATA_STREAM (start) for one MAV_DATA_STREAM group."""


def send_requests(link: StreamLink, requests: list[Request]) -> None:
    """Put ``requests`` on the wire (acks are read later by the keeper, not waited for)."""
    for request in requests:
        if request.method is Method.INTERVAL:
            interval_us = 1e6 / request.hz
            link.send_command(
                MAV_CMD_SET_MESSAGE_INTERVAL,
                (float(MESSAGE_IDS[request.message]), interval_us, 0.0, 0.0, 0.0, 0.0, 0.0),
            )
        else:
            link.request_data_stream(DATA_STREAM_GROUPS[request.message], max(1, round(request.hz)))
