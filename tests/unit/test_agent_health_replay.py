"""Recorded real-firmware traffic replayed into the agent's health model and hold check.

The recordings (.tlog: PX4 v1.16 SIH and ArduCopter SITL, one autopilot link each) live
in a ``captures`` directory outside the repository: ``$ROOST_CAPTURES_DIR``, else
``shared/captures`` beside the repository root. They are read where they are, never
copied in; without them these tests skip and say where they looked.

Each replay feeds every frame from the autopilot (system 1, component 1: the link's own
filter; frames of other systems and components are dropped as the link drops them) into
a :class:`HealthTracker` at its recorded time and assesses every 50 ms, as the decision
loop would, then asserts the judgements over time: OK only after the first heartbeat,
no ERROR while the autopilot boots (PX4 UNINIT and estimator start-up, ArduCopter BOOT
and its ~40 s GPS wait), ERROR within the message threshold of a kill, and the battery
failsafe's MAV_STATE CRITICAL reported and corroborated into an ERROR. The hold check
(:func:`roost_agent.safety.judge_hold`) is replayed on ArduCopter's LOITER without RC
(caught long before the ground) and BRAKE (a hold).
"""

from __future__ import annotations

import itertools
import os
from dataclasses import replace
from datetime import UTC, datetime

os.environ.setdefault("MAVLINK20", "1")

import pytest

from roost_agent.health import Assessment, Motion
from roost_agent.report import conditions
from roost_agent.safety import DEFAULT_TIMING, judge_hold
from roost_api.autopilot_enums import LandedState
from roost_api.meta import HealthLevel, Stack
from roost_api.plain import (
    AutopilotHealth,
    RedundantAutopilotSpec,
    RedundantAutopilotStatus,
)
from roost_mavlink import MavState, custom_mode
from tests.support.captures import CAPTURES
from tests.support.replay import (
    RECORDINGS,
    STEP_S,
    TH,
    Replay,
    healthy_until,
    replay,
)

OK, STARTING, ERROR = HealthLevel.OK, HealthLevel.STARTING, HealthLevel.ERROR


def levels(assessments: list[Assessment]) -> set[HealthLevel]:
    return {a.level for a in assessments}


@pytest.mark.parametrize(
    "name",
    [
        "px4-v1.16-sih-boot-arm-takeoff-loiter-land.tlog",
        "px4-v1.16-sih-killed-in-flight.tlog",
        "px4-v1.16-sih-battery-failsafe.tlog",
    ],
)
def test_px4_boot_is_starting_and_ok_comes_only_after_the_first_heartbeat(name: str) -> None:
    r = replay(name, Stack.PX4)
    first_beat = r.first("HEARTBEAT")
    standby = r.up()
    assert r.foreign == r.unknown == 0  # every frame is the autopilot's, of a known message
    assert OK not in levels(r.during(0, first_beat))
    assert levels(r.during(0, standby)) == {STARTING}  # UNINIT, estimator start-up, GPS
    reasons = {x for a in r.during(0, standby) for x in a.reasons}
    assert "booting (MAV_STATE UNINIT)" in reasons
    assert any(x.startswith("estimator starting (ESTIMATOR_STATUS flags") for x in reasons)
    armed = r.first("HEARTBEAT", system_status=MavState.ACTIVE)
    assert levels(r.during(standby + STEP_S, armed + 5)) == {OK}


@pytest.mark.parametrize(
    "name",
    [
        "px4-v1.16-sih-boot-arm-takeoff-loiter-land.tlog",
        "px4-v1.16-sih-battery-failsafe.tlog",
    ],
)
def test_every_px4_frame_is_of_a_message_the_agent_knows(name: str) -> None:
    """PX4 v1.16 sends five messages pymavlink's dialect lacks; with the agent's added
    declarations every one of the autopilot's frames passes its CRC and is counted as the
    autopilot's own. CURRENT_MODE's layout is checked against what it reports: its
    custom_mode is the mode of the heartbeat before it (or, at a mode change, after it),
    its intended_custom_mode one the autopilot flew (after a failsafe: the mode the pilot
    had chosen, not the failsafe's)."""
    r = replay(name, Stack.PX4)
    assert r.unknown == 0
    kinds = {m.get_type() for _, m in r.messages}
    assert kinds >= {
        "CURRENT_MODE",
        "LINK_NODE_STATUS",
        "TIME_ESTIMATE_TO_TARGET",
        "EVENT",
        "CURRENT_EVENT_SEQUENCE",
    }
    modes = [(i, m) for i, (_, m) in enumerate(r.messages) if m.get_type() == "CURRENT_MODE"]
    beats = [
        (i, m.custom_mode) for i, (_, m) in enumerate(r.messages) if m.get_type() == "HEARTBEAT"
    ]
    assert len(modes) >= 10
    assert any(m.intended_custom_mode != m.custom_mode for _, m in modes) == ("failsafe" in name)
    for at, mode in modes:
        before = [c for i, c in beats if i < at][-1:]
        after = [c for i, c in beats if i > at][:1]
        assert mode.custom_mode in before + after, (at, mode.custom_mode, before, after)
        assert mode.intended_custom_mode in {0, *(c for _, c in beats)}
        assert 0 <= mode.standard_mode <= 16


def test_px4_flight_is_ok_throughout_until_the_recording_ends() -> None:
    r = replay("px4-v1.16-sih-boot-arm-takeoff-loiter-land.tlog", Stack.PX4)
    standby = r.up()
    assert levels(r.during(standby + STEP_S, r.last_at)) == {OK}


def test_px4_killed_in_flight_is_an_error_within_the_message_threshold() -> None:
    r = replay("px4-v1.16-sih-killed-in-flight.tlog", Stack.PX4)
    killed = r.last_at
    standby = r.up()
    assert levels(r.during(standby + STEP_S, killed)) == {OK}
    failing = next(a for a in r.timeline if a.at > killed and a.failing)
    assert failing.at - killed <= TH.message_error_ms / 1000 + STEP_S
    assert failing.level == ERROR and failing.onset == killed
    assert "silent" in failing.failure_reason  # the stream, not the heartbeat age
    assert failing.in_air is True and failing.armed is True  # a failover target's state


def test_px4_battery_failsafe_reports_critical_and_an_error() -> None:
    r = replay("px4-v1.16-sih-battery-failsafe.tlog", Stack.PX4)
    critical = r.first("HEARTBEAT", system_status=MavState.CRITICAL)
    standby = r.up()
    assert ERROR not in levels(r.during(0, critical))
    assert STARTING not in levels(r.during(standby + STEP_S, critical))
    judged = r.at(critical)
    assert judged.to_api().system_status == "CRITICAL"
    assert judged.level == ERROR and judged.failing
    assert "MAV_STATE CRITICAL, corroborated by battery unhealthy" in judged.failure_reason
    landing = r.first("HEARTBEAT", custom_mode=custom_mode(Stack.PX4, "AUTO.LAND"))
    assert all(a.failing for a in r.during(critical, landing))


def test_arducopter_heartbeat_only_is_never_a_usable_standby() -> None:
    """Nobody requested streams: BOOT is starting, then only heartbeats — the armed
    state is known, the landed state never, and Redundant says so."""
    r = replay("arducopter-boot-unrequested.tlog", Stack.ARDUPILOT)
    standby = r.up()
    assert levels(r.during(0, standby)) == {STARTING}
    assert ERROR not in levels(r.during(0, r.last_at))
    seen = r.at(r.last_at - 1)
    assert seen.armed is False and seen.landed_state is None
    spec = RedundantAutopilotSpec.from_api(
        {
            "vehicleName": "v1",
            "primary": "fc1",
            "autopilots": [
                {
                    "name": f"fc{i}",
                    "stack": "ardupilot",
                    "connection": f"tcp://127.0.0.1:576{i}",
                    "sysid": 1,
                    "bridgeChannel": i,
                }
                for i in (1, 2)
            ],
        }
    )
    active = AutopilotHealth(name="fc1", level=OK, armed=True, landed_state=LandedState.IN_AIR)
    standby_health = replace(seen.to_api(), name="fc2")
    status = RedundantAutopilotStatus(active_autopilot="fc1", autopilots=[active, standby_health])
    (redundant,) = [
        c
        for c in conditions(
            [], spec=spec, status=status, generation=1, now=datetime(2026, 1, 1, tzinfo=UTC)
        )
        if c.type == "Redundant"
    ]
    assert (redundant.status, redundant.reason) == ("False", "StandbyStateUnknown")


@pytest.mark.parametrize(
    "name", ["arducopter-streams-arm-takeoff-brake-land.tlog", "arducopter-loiter-no-rc.tlog"]
)
def test_arducopter_boot_and_gps_wait_are_starting_never_errors(name: str) -> None:
    r = replay(name, Stack.ARDUPILOT)
    armed = next(t for t, m in r.messages if m.get_type() == "HEARTBEAT" and m.base_mode & 128)
    assert ERROR not in levels(r.during(0, armed))
    starting = {x for a in r.during(0, armed) if a.level == STARTING for x in a.reasons}
    assert "booting (MAV_STATE BOOT)" in starting
    assert "waiting for an absolute position estimate (GPS)" in starting
    assert any(x.startswith("estimator starting (EKF_STATUS_REPORT flags 0x400") for x in starting)
    assert r.at(armed).level == OK


def test_arducopter_brake_flight_and_landing_are_never_errors() -> None:
    r = replay("arducopter-streams-arm-takeoff-brake-land.tlog", Stack.ARDUPILOT)
    assert ERROR not in levels(r.during(0, r.last_at))


def _hold_verdicts(r: Replay, mode: str) -> tuple[float, list[tuple[float, str, float]]]:
    """Replay judge_hold from the heartbeat showing ``mode``: (entered, failing verdicts
    as (time, reason, altitude lost))."""
    entered = r.first("HEARTBEAT", custom_mode=custom_mode(Stack.ARDUPILOT, mode))
    samples: list[Motion] = []
    failures: list[tuple[float, str, float]] = []
    reference: float | None = None
    left = next(
        (
            t
            for t, m in r.messages
            if t > entered
            and m.get_type() == "HEARTBEAT"
            and m.custom_mode != custom_mode(Stack.ARDUPILOT, mode)
        ),
        r.last_at,
    )
    for t, m in r.messages:
        if not entered <= t < left or m.get_type() != "GLOBAL_POSITION_INT":
            continue
        sample = Motion(m.relative_alt / 1000, -m.vz / 100, t)
        reference = sample.altitude_m if reference is None else reference
        samples.append(sample)
        verdict = judge_hold(samples, reference, t, DEFAULT_TIMING)
        if verdict is not None:
            failures.append((t, verdict.reason, reference - sample.altitude_m))
    return entered, failures


def test_loiter_without_rc_is_caught_long_before_the_ground() -> None:
    r = replay("arducopter-loiter-no-rc.tlog", Stack.ARDUPILOT)
    entered, failures = _hold_verdicts(r, "LOITER")
    assert failures, "the sink into the ground was never judged as not holding"
    caught_at, reason, lost = failures[0]
    ground = next(
        t
        for t, m in r.messages
        if t > entered and m.get_type() == "GLOBAL_POSITION_INT" and m.relative_alt < 100
    )
    assert caught_at < ground - 1.0  # more than a second of altitude still left
    assert lost <= DEFAULT_TIMING.hold_band_m + 0.3, reason


def test_brake_is_a_hold() -> None:
    r = replay("arducopter-streams-arm-takeoff-brake-land.tlog", Stack.ARDUPILOT)
    _, failures = _hold_verdicts(r, "BRAKE")
    assert failures == []


LOST_IN_A_ROW = 3  # the most the default heartbeat error tolerates (test_agent_health)


def test_every_recording_there_is_replayed() -> None:
    """A recording added to the captures directory is judged by the tests below too."""
    if not CAPTURES.is_dir():
        pytest.skip(f"no captures directory {CAPTURES} (set ROOST_CAPTURES_DIR)")
    assert {p.name for p in CAPTURES.glob("*.tlog")} <= {name for name, _ in RECORDINGS}


def heartbeat_times(r: Replay) -> list[float]:
    return [t for t, m in r.messages if m.get_type() == "HEARTBEAT"]


@pytest.mark.parametrize(("name", "stack"), RECORDINGS)
def test_healthy_recorded_flight_is_never_an_error_at_the_default_thresholds(
    name: str, stack: Stack
) -> None:
    r = replay(name, stack)
    healthy = r.during(0, healthy_until(r))
    assert ERROR not in levels(healthy) and HealthLevel.STALE not in levels(healthy)
    heartbeat_findings = {f.code for a in healthy for f in a.findings} & {
        "heartbeat-late",
        "heartbeat-lost",
    }
    assert heartbeat_findings == set()  # lossless recordings: nothing near either threshold
    beats = heartbeat_times(r)
    # 1 Hz, as the loss table in test_agent_health assumes (its longest period: 1.015 s)
    assert max(b - a for a, b in itertools.pairwise(beats)) < 1.02


@pytest.mark.parametrize(("name", "stack"), RECORDINGS)
def test_three_heartbeats_lost_in_a_row_in_recorded_flight_only_warn(
    name: str, stack: Stack
) -> None:
    """The widest stretch of three consecutive heartbeats after boot, dropped as a lossy
    link would: the judgement goes to WARN (heartbeat late), never to ERROR."""
    r = replay(name, stack)
    end, beats = healthy_until(r), heartbeat_times(r)
    after = LOST_IN_A_ROW + 1  # the heartbeat that arrives after the gap
    first = max(
        (i for i in range(len(beats) - after) if beats[i] > r.up() and beats[i + after] < end),
        key=lambda i: beats[i + after] - beats[i],
    )
    lost = frozenset(range(first + 1, first + after))
    gap_s = beats[first + after] - beats[first]
    lossy = replay(name, stack, lose_heartbeats=lost)
    healthy = lossy.during(0, end)
    assert ERROR not in levels(healthy) and HealthLevel.STALE not in levels(healthy)
    late = [a for a in healthy if "heartbeat-late" in {f.code for f in a.findings}]
    assert late, f"no heartbeat-late in the {gap_s:.2f} s gap"
    assert max(a.heartbeat_age_s or 0.0 for a in late) < TH.heartbeat_error_ms / 1000
