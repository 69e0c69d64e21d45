"""The learnt silence threshold (roost_agent.health): a decision table, then properties.

Every message here is a real encoded and decoded MAVLink frame delivered at an explicit
arrival time (a kernel receive stamp in the agent); judgements are made at explicit
times. The silence threshold is ``silence_margin`` times the worst gap of the last
seconds, held between ``message_error_min_ms`` and ``message_error_ms``.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from roost_agent.health import LEARN_WINDOWS, Assessment, HealthTracker
from roost_api.autopilot import Thresholds
from roost_api.meta import HealthLevel, Stack
from roost_api.plain import Thresholds as PlainThresholds
from tests.support.feed import Feed

OK, WARN, ERROR = HealthLevel.OK, HealthLevel.WARN, HealthLevel.ERROR
# The defaults: learning is on (the floor below the ceiling).
DEFAULTS = Thresholds()
FLOOR_S = DEFAULTS.message_error_min_ms / 1000  # 60 ms
CEILING_S = DEFAULTS.message_error_ms / 1000  # 200 ms
MARGIN = DEFAULTS.silence_margin  # 2.5


def vehicle(thresholds: Thresholds = DEFAULTS) -> Feed:
    return Feed(HealthTracker("fc1", Stack.PX4, thresholds))


def arrive(v: Feed, times: list[float]) -> None:
    """ATTITUDE at each of ``times`` (ascending), with a heartbeat and the landed state
    at every whole second crossed, as a flying PX4 streams them."""
    for t in times:
        if int(t) != int(v.t) or v.t == 0.0:
            v.t = float(int(t))
            v.heartbeat()
            v.landed()
        v.t = t
        v.attitude()


def steady(start: float, seconds: float, gap_s: float) -> list[float]:
    n = round(seconds / gap_s)
    return [start + i * gap_s for i in range(1, n + 1)]


def silent(a: Assessment) -> bool:
    return "silent" in {f.code for f in a.findings if f.triggers_failover}


def first_error_after(v: Feed, step_s: float = 0.001) -> float:
    """How long after the last message the judgement becomes a silence ERROR."""
    dt = 0.0
    while not silent(v.at(dt)):
        dt += step_s
    return dt


# -- decision table ------------------------------------------------------------------


def test_until_two_windows_are_learnt_the_ceiling_applies() -> None:
    v = vehicle()
    arrive(v, steady(0.0, 1.5, 0.01))  # one rate window: a fast stream, one window learnt
    assert v.tracker.silence_threshold_s() == CEILING_S
    assert not silent(v.at(CEILING_S - 0.002)) and silent(v.at(CEILING_S + 1e-6))


def test_a_clean_100_hz_stream_is_silent_at_the_floor() -> None:
    v = vehicle()
    arrive(v, steady(0.0, 3.0, 0.01))
    assert v.tracker.silence_threshold_s() == FLOOR_S
    a = v.at(FLOOR_S - 0.001)
    assert a.level == WARN and not silent(a)  # late: half the threshold, as 100/200 ms
    assert silent(v.at(FLOOR_S + 1e-6)) and v.at(FLOOR_S + 1e-6).onset == v.t


def test_a_jittery_link_is_given_its_margin() -> None:
    """Gaps up to 50 ms (jitter): silent only after 2.5 x 50 ms."""
    v = vehicle()
    gaps = ([0.01] * 9 + [0.05]) * 22  # every tenth message held back 40 ms
    times = [sum(gaps[: i + 1]) for i in range(len(gaps))]
    arrive(v, times)
    learnt = v.tracker.silence_threshold_s()
    assert learnt == pytest.approx(MARGIN * 0.05, abs=0.002)
    assert not silent(v.at(learnt - 0.002)) and silent(v.at(learnt + 1e-6))


def test_the_ceiling_bounds_a_link_with_long_gaps() -> None:
    v = vehicle()
    arrive(v, steady(0.0, 3.0, 0.1))  # 10 Hz: 250 ms learnt, held at 200
    assert v.tracker.silence_threshold_s() == CEILING_S


def test_learning_is_on_by_default() -> None:
    """The default floor sits under the ceiling, at twice PX4's learnt 30 ms (2.5 x its
    12 ms worst healthy gap) and under ArduCopter's ~63 ms (docs/health-model.md)."""
    assert FLOOR_S == 0.06 and FLOOR_S < CEILING_S
    assert Thresholds().message_error_min_ms == PlainThresholds().message_error_min_ms


def test_floor_equal_to_ceiling_is_a_fixed_threshold() -> None:
    v = vehicle(Thresholds(message_error_min_ms=200))
    arrive(v, steady(0.0, 3.0, 0.01))
    assert v.tracker.silence_threshold_s() == CEILING_S


def test_a_requested_rate_change_relearns_from_the_ceiling() -> None:
    """The agent asks for other rates (the stream keeper's new epoch): the threshold
    learnt on 100 Hz must not judge a 20 Hz stream, so the ceiling applies until the new
    rates are learnt."""
    v = vehicle()
    arrive(v, steady(0.0, 3.0, 0.01))
    v.tracker.expect_streams(None)
    assert v.tracker.silence_threshold_s() == CEILING_S
    slower = steady(v.t, 3.0, 0.05)
    for t in slower:
        arrive(v, [t])
        assert not silent(v.at(0.049))
    assert v.tracker.silence_threshold_s() == pytest.approx(MARGIN * 0.05)


def test_verified_streams_do_not_forget_what_was_learnt() -> None:
    v = vehicle()
    arrive(v, steady(0.0, 3.0, 0.01))
    v.tracker.expect_streams(100.0)
    assert v.tracker.silence_threshold_s() == FLOOR_S


def test_a_reboot_relearns_from_the_ceiling() -> None:
    v = vehicle()
    arrive(v, steady(0.0, 3.0, 0.01))
    for _ in range(2):  # time_boot_ms restarts: a reboot claim, settled by the next message
        v.t += 0.01
        v.boot_ms = 500
        v.attitude(advance=False)
    assert "reboot" in {f.code for f in v.at(0.0).findings}
    assert v.tracker.silence_threshold_s() == CEILING_S


def test_a_burst_after_a_stall_keeps_the_margin_the_stall_taught() -> None:
    """A 50 ms stall (under the floor, not an error), then everything it held at once:
    for the next seconds the threshold stays at 2.5 x the stall."""
    v = vehicle()
    arrive(v, steady(0.0, 3.0, 0.01))
    stall_end = v.t + 0.05
    arrive(v, [stall_end] * 5)  # the burst: five messages with one arrival time
    arrive(v, steady(v.t, 2.0, 0.01))
    assert v.tracker.silence_threshold_s() == pytest.approx(MARGIN * 0.05)
    arrive(v, steady(v.t, LEARN_WINDOWS + 1.0, 0.01))  # the stall leaves the windows
    assert v.tracker.silence_threshold_s() == FLOOR_S


def test_an_outage_is_not_learnt_as_the_streams_rhythm() -> None:
    """An autopilot silent for a second (a failover's worth) comes back: it is judged by
    the rhythm it had, not by 2.5 x its outage (which the ceiling would cap at 200 ms)."""
    v = vehicle()
    arrive(v, steady(0.0, 3.0, 0.01))
    arrive(v, steady(v.t + 1.0, 2.0, 0.01))
    assert v.tracker.silence_threshold_s() == FLOOR_S


def test_a_silence_ends_the_moment_a_message_arrives() -> None:
    v = vehicle()
    arrive(v, steady(0.0, 3.0, 0.01))
    assert silent(v.at(0.1))
    v.t += 0.1
    assert v.heartbeat()  # wakes the decision loop: the autopilot is back
    assert not silent(v.at(0.0))


# -- properties ----------------------------------------------------------------------

# A window's worst gap as a fraction of the previous window's: a link that degrades
# (or recovers) by at most this much per second. Below the margin, with room for where
# in the window the worst gap falls.
GROWTH = st.floats(min_value=0.5, max_value=MARGIN / 1.25)


@settings(max_examples=15, deadline=None)
@given(
    first_gap_ms=st.floats(min_value=5.0, max_value=40.0),
    growth=st.lists(GROWTH, min_size=3, max_size=5),
)
def test_a_slowly_degrading_link_is_never_called_silent(
    first_gap_ms: float, growth: list[float]
) -> None:
    """Each second the worst gap may grow by less than the margin over the last: the
    link is judged at every instant just before each next message, and never silent."""
    v = vehicle()
    gap = first_gap_ms / 1000
    t = 0.0
    for factor in [1.0, *growth]:
        gap = min(gap * factor, 0.15)
        end = t + 1.0
        while t < end:
            if t > 2.0:
                assert not silent(v.at(t + gap - v.t - 1e-6)), (t, gap)
            t += gap
            arrive(v, [t])


@settings(max_examples=15, deadline=None)
@given(
    gaps_ms=st.lists(st.floats(min_value=0.0, max_value=90.0), min_size=150, max_size=400),
    burst=st.integers(min_value=1, max_value=30),
)
def test_a_burst_never_lowers_the_threshold(gaps_ms: list[float], burst: int) -> None:
    v = vehicle()
    t = 0.0
    for gap in gaps_ms:
        t += gap / 1000
        arrive(v, [t])
    before = v.tracker.silence_threshold_s()
    arrive(v, [v.t] * burst)
    assert v.tracker.silence_threshold_s() >= before


@settings(max_examples=15, deadline=None)
@given(
    gaps_ms=st.lists(st.floats(min_value=0.0, max_value=60.0), min_size=30, max_size=400),
    floor_ms=st.integers(min_value=10, max_value=300),
    ceiling_ms=st.integers(min_value=20, max_value=300),
)
def test_the_detector_is_never_slower_than_the_ceiling_nor_faster_than_the_floor(
    gaps_ms: list[float], floor_ms: int, ceiling_ms: int
) -> None:
    """Whatever it learnt: a fast stream silent for ``message_error_ms`` is an ERROR, and
    one silent for less than min(floor, ceiling) is not."""
    th = Thresholds(message_error_min_ms=floor_ms, message_error_ms=ceiling_ms)
    v = vehicle(th)
    t = 0.0
    for gap in gaps_ms:
        t += gap / 1000
        arrive(v, [t])
    if not v.at(0.0).findings and v.tracker.assess(v.t).level == OK:
        learnt = v.tracker.silence_threshold_s()
        assert min(floor_ms, ceiling_ms) / 1000 <= learnt <= ceiling_ms / 1000
        assert not silent(v.at(min(floor_ms, ceiling_ms) / 1000 - 1e-4))
    fast = v.tracker._o.stream_rate is not None and v.tracker._o.stream_rate * 0.1 >= 4
    if fast:
        assert silent(v.at(ceiling_ms / 1000 + 1e-6))


@settings(max_examples=10, deadline=None)
@given(
    lateness_ms=st.lists(st.floats(min_value=0.0, max_value=400.0), min_size=5, max_size=20),
)
def test_a_starved_agent_judges_as_an_agent_on_time_would(lateness_ms: list[float]) -> None:
    """The agent reads late (a starved CPU): the messages of a 100 Hz stream carry their
    kernel arrival stamps, and each judgement stands for the start of its read (what
    arrived since is not read yet). Reading late in batches gives exactly the judgements
    of reading every message on time: its lateness is never the autopilot's silence."""
    late = vehicle()
    arrivals = steady(0.0, 3.0 + sum(lateness_ms) / 1000 + 0.02 * len(lateness_ms), 0.01)
    pending = list(arrivals)
    read_at = 0.0
    for lateness in lateness_ms:
        read_at += 0.02 + lateness / 1000
        batch = [t for t in pending if t <= read_at]
        pending = pending[len(batch) :]
        arrive(late, batch)
        judged = late.tracker.assess(read_at)
        assert not judged.failing, (read_at, judged.failure_reason)
    arrive(late, pending)
    on_time = vehicle()
    arrive(on_time, arrivals)
    assert late.tracker.silence_threshold_s() == on_time.tracker.silence_threshold_s()
