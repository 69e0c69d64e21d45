"""Recorded real-firmware traffic (.tlog) replayed into the agent's health model.

Each replay feeds every frame from the autopilot (system 1, component 1: the link's own
filter; frames of other systems and components are dropped as the link drops them) into
a :class:`HealthTracker` at its recorded time and assesses every :data:`STEP_S`, as the
decision loop would. Used by the replay tests and by the benchmark that counts false
ERROR judgements over every recording (``failover.replay_false_errors``).
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil

from roost_agent.health import Assessment, HealthTracker
from roost_api.meta import Stack
from roost_api.plain import Thresholds
from roost_mavlink import MavState
from roost_mavlink.codec import BadData, UnknownFrame, scan
from tests.support.captures import capture

STEP_S = 0.05
# The default thresholds: the silence threshold learnt from each recording's stream.
TH = Thresholds()


@dataclass
class Replay:
    """Messages of one recording (autopilot's own only) and the judgements over time."""

    messages: list[tuple[float, Any]]
    timeline: list[Assessment]
    foreign: int
    unknown: int  # frames of ids the agent's codec does not know

    @property
    def last_at(self) -> float:
        return self.messages[-1][0]

    def first(self, kind: str, **fields: int) -> float:
        return next(
            t
            for t, m in self.messages
            if m.get_type() == kind and all(getattr(m, k) == v for k, v in fields.items())
        )

    def up(self) -> float:
        """The first heartbeat out of boot (STANDBY, or ACTIVE when armed at once)."""
        return next(
            t
            for t, m in self.messages
            if m.get_type() == "HEARTBEAT"
            and m.system_status in (MavState.STANDBY, MavState.ACTIVE)
        )

    def during(self, start: float, end: float) -> list[Assessment]:
        return [a for a in self.timeline if start <= a.at < end]

    def at(self, t: float) -> Assessment:
        return next(a for a in self.timeline if a.at >= t)


@functools.cache
def recording(path: Path) -> tuple[tuple[float, bytes], ...]:
    """The recording's (time, frame bytes), read once per file: pymavlink's reading of a
    .tlog is the same every time, while the agent's reading below runs for every test."""
    conn: Any = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    frames: list[tuple[float, bytes]] = []
    while (msg := conn.recv_match()) is not None:
        frames.append((msg._timestamp, bytes(msg.get_msgbuf())))
    conn.close()
    return tuple(frames)


def replay(
    name: str, stack: Stack, tail_s: float = 4.0, lose_heartbeats: frozenset[int] = frozenset()
) -> Replay:
    """``lose_heartbeats``: which of the autopilot's HEARTBEATs (0 = its first) a lossy
    link drops before the tracker sees them."""
    tracker = HealthTracker("fc1", stack, TH)
    messages: list[tuple[float, Any]] = []
    timeline: list[Assessment] = []
    start: float | None = None
    next_at = 0.0
    foreign = unknown = 0
    heartbeats = 0
    for stamp, buf in recording(capture(name)):
        start = stamp if start is None else start
        t = stamp - start
        while next_at < t:
            timeline.append(tracker.assess(next_at))
            next_at += STEP_S
        # the recording's framing and times, the agent's reading (as the link reads it)
        for frame in scan(buf)[0]:
            if isinstance(frame, UnknownFrame):
                unknown += 1
                continue
            if isinstance(frame, BadData) or (
                frame.get_srcSystem(),
                frame.get_srcComponent(),
            ) != (1, 1):
                foreign += 1
                continue
            if frame.get_type() == "HEARTBEAT":
                heartbeats += 1
                if heartbeats - 1 in lose_heartbeats:
                    continue
            tracker.observe(frame, t)
            messages.append((t, frame))
    end = next_at + tail_s
    while next_at < end:
        timeline.append(tracker.assess(next_at))
        next_at += STEP_S
    return Replay(messages, timeline, foreign, unknown)


# Every recording, up to where its autopilot reports trouble itself (MAV_STATE CRITICAL)
# or the recording ends (the killed PX4's recording ends with the kill).
RECORDINGS = [
    ("px4-v1.16-sih-boot-arm-takeoff-loiter-land.tlog", Stack.PX4),
    ("px4-v1.16-sih-killed-in-flight.tlog", Stack.PX4),
    ("px4-v1.16-sih-battery-failsafe.tlog", Stack.PX4),
    ("arducopter-boot-unrequested.tlog", Stack.ARDUPILOT),
    ("arducopter-streams-arm-takeoff-brake-land.tlog", Stack.ARDUPILOT),
    ("arducopter-loiter-no-rc.tlog", Stack.ARDUPILOT),
]


def healthy_until(r: Replay) -> float:
    critical = [
        t
        for t, m in r.messages
        if m.get_type() == "HEARTBEAT" and m.system_status == MavState.CRITICAL
    ]
    return min(critical, default=r.last_at)


def stack_of(name: str) -> Stack:
    """The flight stack a recording's name says (``px4-...``, ``arducopter-...``)."""
    return Stack.PX4 if name.startswith("px4") else Stack.ARDUPILOT
