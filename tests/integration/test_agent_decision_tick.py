"""The decision loop's skipped ticks decide exactly what full ticks decide (decision table).

A tick in which nothing can have changed returns at once (``Agent._nothing_new``,
``HealthTracker.holds``). Each row below flies two autopilots into an agent (not started:
no threads, no sockets; real MAVLink messages fed into its trackers, a clock the test
sets) and ticks every 10 ms, twice: as the agent does, and with every tick a full one.
The failovers (at which tick, from and to, why), the health events and the arbiter's
final state must be the same, and the skipping agent must have skipped most ticks.
In particular an autopilot that goes silent is judged at the first tick past its
threshold although no message arrives to wake anything. The last tables tick as the
loop does while the hub's fast path routes the active autopilot's frames in C: it wakes
for a standby's silence (the arbiter must see a failure begin) but not for its
lateness, a warning.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime

import pytest

from roost_agent.agent import ROUTED_TICK_S, Agent
from roost_agent.bridge import SimulatedBridge
from roost_agent.events import AgentEvent
from roost_api.autopilot import (
    Thresholds,
)
from roost_mavlink import MavLandedState, MavState, SensorBit
from tests.support.feed import SENSORS, Feed, two_px4_spec

# serial: a silence judged at its threshold in real time
pytestmark = pytest.mark.serial

TICK_S = 0.01
RATE_HZ = 50
# A fixed silence threshold (floor = ceiling): the ticks are what is tested here; the
# learnt threshold has tests of its own (test_agent_health_silence, test_agent_silence).
TH = Thresholds(
    message_warn_ms=100, message_error_ms=200, message_error_min_ms=200, confirm_ms=20, clear_ms=300
)
WALL = datetime(2026, 5, 1, 12, 0, tzinfo=UTC)


@dataclass
class Clock:
    now: float = 0.0

    def __call__(self) -> float:
        return self.now


@dataclass
class Fault:
    """From ``at`` seconds on, what one autopilot does instead of streaming normally."""

    autopilot: str
    at: float
    kind: str  # silence | emergency | gyro | resume


@dataclass
class Run:
    agent: Agent
    events: list[AgentEvent] = field(default_factory=list)
    full_ticks: int = 0
    ticks: int = 0


def _fly(faults: list[Fault], seconds: float, *, skipping: bool) -> Run:
    clock = Clock()
    agent = Agent(
        two_px4_spec(15100, TH), SimulatedBridge([0, 1]), clock=clock, wall_clock=lambda: WALL
    )
    run = Run(agent)
    if not skipping:
        agent._nothing_new = lambda *_: None  # type: ignore[method-assign]
    full = agent.tick

    def counted_assess(tracker_assess: Callable[[float], object]) -> Callable[[float], object]:
        def assess(now: float) -> object:
            run.full_ticks += 1
            return tracker_assess(now)

        return assess

    fc1 = agent.links["fc1"].tracker
    fc1.assess = counted_assess(fc1.assess)  # type: ignore[method-assign,assignment]
    feeds = {name: Feed(link.tracker) for name, link in agent.links.items()}
    step = 0
    while step * TICK_S < seconds:
        t = step * TICK_S
        for name, feed in feeds.items():
            feed.t = t
            state = "stream"
            for fault in faults:
                if fault.autopilot == name and t >= fault.at:
                    state = fault.kind
            if state == "silence":
                continue
            if step % round(1 / (RATE_HZ * TICK_S)) == 0:
                feed.attitude()
            if step % 100 == 0:
                status = MavState.EMERGENCY if state == "emergency" else MavState.ACTIVE
                feed.heartbeat(state=status)
                feed.landed(MavLandedState.IN_AIR)
            if step % 20 == 0:
                gyro = state == "gyro"
                feed.sys_status(health=SENSORS & ~int(SensorBit.GYRO) if gyro else SENSORS)
        clock.now = t
        full()
        run.ticks += 1
        step += 1
    while not agent._events.empty():
        event = agent._events.get()
        if event is not None:
            run.events.append(event)
    return run


def _decided(run: Run) -> list[tuple[object, ...]]:
    return [
        (
            e.kind,
            e.reason,
            e.autopilot,
            e.message,
            None if e.failover is None else e.failover.detected_at,
        )
        for e in run.events
    ]


ROWS: list[tuple[str, list[Fault], str]] = [
    ("healthy flight", [], "fc1"),
    ("the active autopilot falls silent", [Fault("fc1", 3.0, "silence")], "fc2"),
    ("the active autopilot declares EMERGENCY", [Fault("fc1", 3.05, "emergency")], "fc2"),
    ("the active autopilot's gyro fails", [Fault("fc1", 3.0, "gyro")], "fc2"),
    ("the standby falls silent", [Fault("fc2", 3.0, "silence")], "fc1"),
    (
        "the standby falls silent and comes back",
        [Fault("fc2", 3.0, "silence"), Fault("fc2", 3.6, "resume")],
        "fc1",
    ),
]


@pytest.mark.interpreted_only  # counts full ticks by wrapping HealthTracker.assess
@pytest.mark.parametrize(("what", "faults", "active"), ROWS, ids=[r[0] for r in ROWS])
def test_skipped_ticks_decide_what_full_ticks_decide(
    what: str, faults: list[Fault], active: str
) -> None:
    skipping = _fly(faults, 6.0, skipping=True)
    full = _fly(faults, 6.0, skipping=False)
    assert _decided(skipping) == _decided(full), what
    assert skipping.agent.active == full.agent.active == active
    assert skipping.agent._state == full.agent._state
    assert full.full_ticks == full.ticks
    assert skipping.full_ticks < full.ticks / 2  # most ticks of these flights skip


@pytest.mark.interpreted_only  # counts full ticks by wrapping HealthTracker.assess
def test_a_silent_active_autopilot_is_judged_at_its_threshold_without_any_message() -> None:
    """fc1's last message arrives at 2.98 s. Nothing from fc1 arrives after it; the
    switch comes at the first tick past message_error_ms (200 ms) plus confirm_ms
    (20 ms) — the tick of a loop that judges every tick."""
    run = _fly([Fault("fc1", 3.0, "silence")], 4.0, skipping=True)
    (failover,) = [e.failover for e in run.events if e.failover is not None]
    last = 2.98
    assert failover.record.from_autopilot == "fc1" and failover.record.to_autopilot == "fc2"
    assert "silent" in failover.record.reason
    error_tick = last + TH.message_error_ms / 1000
    assert error_tick <= failover.detected_at <= error_tick + TH.confirm_ms / 1000 + 2 * TICK_S
    assert failover.onset_at == pytest.approx(last)


def _stream(feed: Feed, t: float, step: int) -> None:
    """Step ``step`` of a 50 Hz flight at ``t``: ATTITUDE, and every 10th step
    SYS_STATUS, every 50th a heartbeat and the landed state (in the air)."""
    feed.t = t
    feed.attitude()
    if step % 50 == 0:
        feed.heartbeat()
        feed.landed(MavLandedState.IN_AIR)
    if step % 10 == 0:
        feed.sys_status()


def test_a_loop_ticking_only_when_due_judges_a_silence_at_its_threshold() -> None:
    """With nothing arriving from the active autopilot, nothing pokes the loop: it ticks
    when the last tick said it is next due, and no sooner. A silent active autopilot must
    still switch at its last message + the error threshold + the confirm time."""
    clock = Clock()
    agent = Agent(
        two_px4_spec(15100, TH), SimulatedBridge([0, 1]), clock=clock, wall_clock=lambda: WALL
    )
    feeds = {name: Feed(link.tracker) for name, link in agent.links.items()}

    def stream(name: str, t: float, step: int) -> None:
        _stream(feeds[name], t, step)

    step = 0
    while step * 0.02 < 3.0:  # both stream at 50 Hz; the loop ticks with every message
        clock.now = step * 0.02
        for name in feeds:
            stream(name, clock.now, step)
        due = agent.tick()
        step += 1
    last_message = (step - 1) * 0.02
    ticks: list[float] = []
    while agent.active == "fc1" and len(ticks) < 50:  # fc1 is silent; fc2 streams unread
        assert due is not None and due > clock.now, "a silent autopilot must be due a tick"
        while step * 0.02 <= due:
            clock.now = step * 0.02
            stream("fc2", clock.now, step)
            step += 1
        clock.now = due
        ticks.append(due)
        due = agent.tick()
    switched = [e for e in _events(agent) if e.failover is not None]
    assert agent.active == "fc2" and len(switched) == 1
    expected = last_message + (TH.message_error_ms + TH.confirm_ms) / 1000
    detected = switched[0].failover.detected_at  # type: ignore[union-attr]
    assert detected == pytest.approx(expected, abs=1e-3)
    assert len(ticks) <= 4  # the warning, the error, the end of the confirm window


def _events(agent: Agent) -> list[AgentEvent]:
    events = []
    while not agent._events.empty():
        event = agent._events.get()
        if event is not None:
            events.append(event)
    return events


def _fly_as_the_fast_path(
    standby_gaps: list[tuple[float, float]], seconds: float
) -> tuple[Agent, list[float], list[AgentEvent]]:
    """Both autopilots stream at 50 Hz and the loop ticks with every message for 2 s;
    then it ticks as the reader does while the hub's fast path routes the active
    autopilot's frames in C: that stream keeps pushing its own deadlines ahead, so the
    loop wakes at ``Agent.postponable``'s other deadlines (the standby's among them), at
    an arbiter's due, or after the routed read interval. The standby sends nothing
    during each (start, end) of ``standby_gaps``. The wake-up times and events."""
    clock = Clock()
    agent = Agent(
        two_px4_spec(15100, TH), SimulatedBridge([0, 1]), clock=clock, wall_clock=lambda: WALL
    )
    feeds = {name: Feed(link.tracker) for name, link in agent.links.items()}

    def stream(name: str, t: float, step: int) -> None:
        if name != "fc2" or not any(start <= t < end for start, end in standby_gaps):
            _stream(feeds[name], t, step)

    step = 0
    due = None
    while step * 0.02 < 2.0:
        clock.now = step * 0.02
        for name in feeds:
            stream(name, clock.now, step)
        due = agent.tick()
        step += 1
    wakes: list[float] = []
    while clock.now < seconds:
        split = agent.postponable()
        routed_read = clock.now + ROUTED_TICK_S
        if split is None:
            wake = routed_read if due is None else min(due, routed_read)
        else:
            wake = min(split[1], routed_read)
        while step * 0.02 <= wake:
            for name in feeds:
                stream(name, step * 0.02, step)
            step += 1
        clock.now = wake
        wakes.append(wake)
        due = agent.tick()
    return agent, wakes, _events(agent)


def _standby_errors(events: list[AgentEvent]) -> list[AgentEvent]:
    return [e for e in events if e.autopilot == "fc2" and "ERROR" in e.message]


def test_with_the_fast_path_a_standby_wakes_the_loop_at_its_silence_not_its_lateness() -> None:
    """A standby's late stream is a warning the arbiter does not act on (its time free of
    failures runs on; whether it is OK is judged afresh when it is to become the
    target), so the fast path's loop does not wake for it: at most once per silence
    threshold (200 ms, less a 20 ms message period) while the standby streams, not once
    per late threshold (100 ms)."""
    agent, wakes, events = _fly_as_the_fast_path([], 5.0)
    span = wakes[-1] - wakes[0]
    silence_wakes = span / ((TH.message_error_ms - 20) / 1000)
    assert len(wakes) <= silence_wakes + 2
    assert not _standby_errors(events)
    assert agent.active == "fc1"


STANDBY_GAP_ROWS = [
    # (what, standby gap seconds, the arbiter sees a failure)
    ("late only: 150 ms, past the 100 ms warning, short of the 200 ms silence", 0.15, False),
    ("silent for 240 ms, then back", 0.24, True),
    ("silent for 1 s, then back", 1.0, True),
]


@pytest.mark.parametrize(
    ("what", "gap", "failed"), STANDBY_GAP_ROWS, ids=[r[0] for r in STANDBY_GAP_ROWS]
)
def test_with_the_fast_path_a_standbys_silence_restarts_its_time_free_of_failures(
    what: str, gap: float, failed: bool
) -> None:
    """The standby's silence is still a deadline the loop wakes for: the arbiter sees it
    fail and restarts its time free of failures when it is back; a lateness alone
    restarts nothing."""
    start = 3.0
    agent, _, events = _fly_as_the_fast_path([(start, start + gap)], 5.0)
    since = agent._state.ok_since.get("fc2")
    assert since is not None, what  # back and free of failures again by 5 s
    assert (since >= start) == failed, what
    assert bool(_standby_errors(events)) == failed, what
    assert agent.active == "fc1", what
