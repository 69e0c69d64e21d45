"""Health judgement from MAVLink messages (real pymavlink message objects, explicit times)."""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Callable
from typing import Any

os.environ.setdefault("MAVLINK20", "1")

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mav

from roost_agent.health import (
    REBOOT_REMEMBERED_S,
    Assessment,
    HealthTracker,
    tilt_degrees,
)
from roost_api.autopilot import Thresholds
from roost_api.meta import HealthLevel, Stack
from roost_mavlink import MavLandedState, MavState, SensorBit, custom_mode
from roost_mavlink.status import (
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    MAV_AUTOPILOT_INVALID,
    MAV_AUTOPILOT_PX4,
)
from tests.support.feed import ARMED, LOITER, SENSORS, Feed

OK, WARN, ERROR, STALE = HealthLevel.OK, HealthLevel.WARN, HealthLevel.ERROR, HealthLevel.STALE
# The numbers these tests assert are these thresholds', not whatever the defaults are.
HEARTBEAT_MS = {"heartbeat_warn_ms": 1500, "heartbeat_error_ms": 3000}
# Fixed silence thresholds (floor = ceiling): the adaptive threshold has tests of its own
# (test_agent_health_silence).
TH = Thresholds(
    message_warn_ms=200,
    message_error_ms=500,
    message_error_min_ms=500,
    confirm_ms=100,
    **HEARTBEAT_MS,
)


class Vehicle(Feed):
    """A feed into a tracker of its own with this module's thresholds."""

    def __init__(
        self,
        stack: Stack = Stack.PX4,
        thresholds: Thresholds | None = None,
        *,
        codec: bool = False,
        summarise: bool = False,
        runs: bool = False,
    ) -> None:
        super().__init__(
            HealthTracker("fc1", stack, thresholds or TH),
            codec=codec,
            summarise=summarise,
            runs=runs,
        )


def codes(a: Assessment) -> set[str]:
    return {f.code for f in a.findings}


def failing_codes(a: Assessment) -> set[str]:
    return {f.code for f in a.findings if f.triggers_failover}


def test_nothing_heard_is_stale_and_failing() -> None:
    a = Vehicle().tracker.assess(5.0)
    assert a.level == STALE and a.failing and codes(a) == {"no-data"}


def test_healthy_streaming_autopilot_is_ok_and_described() -> None:
    v = Vehicle()
    v.fly(2.0)
    a = v.at(0.01)
    assert a.level == OK and not a.findings and not a.failing
    health = a.to_api()
    assert health.mode == "AUTO.LOITER" and health.armed is True
    assert health.landed_state == "InAir" and health.system_status == "ACTIVE"
    assert health.heartbeat_age_ms is not None and health.unhealthy_sensors == []
    assert a.in_air is True and not a.pilot_in_control


def test_silence_on_a_fast_link_goes_warn_error_stale() -> None:
    v = Vehicle()
    v.fly(2.0)
    last = v.t - 1 / 50
    assert v.at(0.1).level == OK
    assert codes(v.at(0.25)) == {"late"} and v.at(0.25).level == WARN
    silent = v.at(0.55)
    assert silent.level == ERROR and "silent" in failing_codes(silent)
    assert silent.onset == pytest.approx(last)
    lost = v.at(3.2)
    assert lost.level == STALE and {"link-lost", "heartbeat-lost"} <= failing_codes(lost)


def test_heartbeat_only_link_is_judged_by_heartbeat_age_alone() -> None:
    v = Vehicle()
    for _ in range(5):
        v.heartbeat()
        v.t += 1.0
    v.t -= 1.0
    assert v.at(0.95).level == OK  # no "silent" although > message_error_ms
    assert codes(v.at(1.6)) == {"heartbeat-late"}
    lost = v.at(3.1)
    assert lost.failing and "heartbeat-lost" in failing_codes(lost)


def test_one_hertz_bursts_are_not_a_fast_stream() -> None:
    """HEARTBEAT, SYS_STATUS and EXTENDED_SYS_STATE arriving together once a second must
    not make the any-message age apply (it would call the link silent every second)."""
    v = Vehicle()
    for _ in range(6):
        v.heartbeat()
        v.sys_status()
        v.landed()
        v.t += 1.0
    v.t -= 1.0
    assert v.at(0.9).level == OK


def test_frozen_telemetry_is_an_error_although_messages_keep_coming() -> None:
    v = Vehicle()
    v.fly(1.0)
    frozen_since = v.t - 1 / 50
    for _ in range(30):  # 0.6 s of ATTITUDE repeating one time_boot_ms
        v.attitude(advance=False)
        v.t += 1 / 50
    a = v.at(0.0)
    assert "frozen" in failing_codes(a) and a.level == ERROR
    assert a.onset == pytest.approx(frozen_since, abs=0.03)


def test_reboot_from_time_boot_going_back_is_remembered_for_a_while() -> None:
    v = Vehicle()
    v.fly(1.0)
    claimed_at = v.t
    assert v.observe(mav.MAVLink_attitude_message(1200, 0, 0, 0, 0, 0, 0)) is False
    assert "reboot" not in codes(v.at(0.0))  # one message is a claim, not yet evidence
    v.t += 0.02
    assert v.observe(mav.MAVLink_attitude_message(1220, 0, 0, 0, 0, 0, 0)) is True
    reboot = [f for f in v.at(0.0).findings if f.code == "reboot"]
    assert reboot and reboot[0].triggers_failover and reboot[0].onset == claimed_at
    v.t += REBOOT_REMEMBERED_S + 0.1
    v.fly(1.0)
    assert "reboot" not in codes(v.at(0.0))


def test_reordered_packets_are_not_a_reboot() -> None:
    v = Vehicle()
    v.fly(1.0)
    late = mav.MAVLink_attitude_message(v.boot_ms - 60, 0, 0, 0, 0, 0, 0)
    assert v.observe(late) is False
    assert v.at(0.0).level == OK


def test_boot_state_after_being_up_is_a_reboot() -> None:
    v = Vehicle()
    v.fly(1.0)
    v.heartbeat(state=MavState.BOOT, base_mode=1)
    assert "reboot" not in codes(v.at(0.0))
    v.sys_status()  # the next frame of the same stream corroborates it
    assert "reboot" in failing_codes(v.at(0.0))


@pytest.mark.parametrize(
    "state", [MavState.EMERGENCY, MavState.POWEROFF, MavState.FLIGHT_TERMINATION]
)
def test_fatal_mav_states_are_errors(state: MavState) -> None:
    v = Vehicle()
    v.fly(1.0)
    claimed_at = v.t
    assert v.heartbeat(state=state) is False  # a claim, not yet evidence
    assert v.at(0.0).level == OK
    v.t += 0.02
    assert v.attitude_changes() is True  # corroborated: a change wakes the arbiter
    a = v.at(0.0)
    assert a.level == ERROR and "mav-state" in failing_codes(a)
    assert a.onset == claimed_at


def test_critical_alone_warns_but_corroborated_is_an_error() -> None:
    v = Vehicle()
    v.fly(1.0)
    v.heartbeat(state=MavState.CRITICAL)
    alone = v.at(0.0)
    assert alone.level == WARN and not alone.failing
    v.sys_status(health=SENSORS & ~int(SensorBit.GPS))
    corroborated = v.at(0.0)
    assert corroborated.level == ERROR and "mav-state" in failing_codes(corroborated)


def test_boot_like_state_in_the_air_is_an_error_on_the_ground_it_is_not() -> None:
    v = Vehicle()
    v.fly(0.5)
    v.heartbeat(state=MavState.CALIBRATING)
    assert "mav-state" in failing_codes(v.at(0.0))
    ground = Vehicle()
    ground.landed(MavLandedState.ON_GROUND)
    ground.heartbeat(state=MavState.CALIBRATING, base_mode=1)
    assert "mav-state" not in codes(ground.at(0.0))


def test_critical_sensor_must_persist_before_it_triggers() -> None:
    v = Vehicle()
    v.fly(1.0)
    assert v.sys_status(health=SENSORS & ~int(SensorBit.GYRO)) is True
    early = v.at(0.3)
    assert early.level == WARN and not early.failing and "gyro" in early.to_api().unhealthy_sensors
    late = v.at(0.61)
    assert late.level == ERROR and "sensor:gyro" in failing_codes(late)
    v.t += 0.7
    v.sys_status(health=SENSORS)
    v.fly(0.5)
    assert v.at(0.0).level == OK


@pytest.mark.parametrize(
    ("bit", "level"),
    [
        (SensorBit.GPS, WARN),
        (SensorBit.MAG, WARN),
        (SensorBit.GYRO2, WARN),
        (SensorBit.RC_RECEIVER, OK),
        (SensorBit.PREARM_CHECK, OK),
    ],
)
def test_non_critical_sensors_only_warn_or_are_ignored(bit: SensorBit, level: HealthLevel) -> None:
    v = Vehicle()
    v.fly(1.0)
    enabled = SENSORS | int(bit)
    v.sys_status(health=enabled & ~int(bit), enabled=enabled)
    v.fly(1.5)  # well past sensor_persist_ms: still only a warning (or nothing)
    a = v.at(0.0)
    assert a.level == level and not a.failing


def test_disarmed_in_the_air_until_it_reports_the_ground() -> None:
    v = Vehicle()
    v.fly(1.0)
    v.heartbeat(base_mode=1)
    assert "disarmed-in-air" in failing_codes(v.at(0.0))
    v.landed(MavLandedState.ON_GROUND)
    assert "disarmed-in-air" not in codes(v.at(0.0))


def test_attitude_envelope() -> None:
    v = Vehicle()
    v.fly(1.0)
    v.fly(0.2, roll=math.radians(40))
    assert codes(v.at(0.0)) == {"tilt"} and v.at(0.0).level == WARN
    v.fly(0.4, roll=math.radians(70))
    a = v.at(0.0)
    assert a.level == ERROR and "tilt" in failing_codes(a)
    assert tilt_degrees(math.radians(30), math.radians(40)) > 40


def test_estimator_attitude_loss_persisting_is_an_error() -> None:
    v = Vehicle()
    v.fly(1.0)
    good = 0x1 | 0x2 | 0x4 | 0x8 | 0x10 | 0x20
    status = mav.MAVLink_estimator_status_message(0, good, 0, 0, 0, 0, 0, 0, 0, 0)
    v.observe(status)
    assert v.at(0.0).level == OK
    lost = mav.MAVLink_estimator_status_message(0, good & ~0x1 & ~0x10, 0, 0, 0, 0, 0, 0, 0, 0)
    v.observe(lost)
    assert v.at(0.1).level == WARN and not v.at(0.1).failing
    assert "estimator" in failing_codes(v.at(0.7))
    assert "position" in codes(v.at(0.7))


def test_non_autopilot_heartbeat_is_ignored() -> None:
    v = Vehicle()
    v.fly(1.0)
    v.heartbeat(state=MavState.EMERGENCY, autopilot=MAV_AUTOPILOT_INVALID)
    assert v.at(0.0).level == OK


def test_stack_mismatch_warns() -> None:
    v = Vehicle()
    v.fly(0.5)
    v.heartbeat(autopilot=MAV_AUTOPILOT_ARDUPILOTMEGA)
    a = v.at(0.0)
    assert codes(a) == {"stack-mismatch"} and a.level == WARN


def test_pilot_mode_is_recognised_per_stack() -> None:
    px4 = Vehicle()
    px4.heartbeat(mode=custom_mode(Stack.PX4, "POSCTL"))
    assert px4.at(0.0).pilot_in_control
    ardu = Vehicle(Stack.ARDUPILOT)
    ardu.heartbeat(
        mode=custom_mode(Stack.ARDUPILOT, "ALT_HOLD"), autopilot=MAV_AUTOPILOT_ARDUPILOTMEGA
    )
    assert ardu.at(0.0).pilot_in_control and ardu.at(0.0).mode == "ALT_HOLD"
    ardu.heartbeat(
        mode=custom_mode(Stack.ARDUPILOT, "LOITER"), autopilot=MAV_AUTOPILOT_ARDUPILOTMEGA
    )
    assert not ardu.at(0.0).pilot_in_control


def test_observe_reports_only_changes_that_matter_to_the_arbiter() -> None:
    v = Vehicle()
    assert v.heartbeat() is True
    assert v.heartbeat() is False
    assert v.landed() is True
    assert v.landed() is False
    assert v.sys_status() is True
    assert v.sys_status() is False
    assert v.heartbeat(mode=custom_mode(Stack.PX4, "AUTO.LAND")) is True


def test_thresholds_come_from_the_spec() -> None:
    tight = Thresholds(message_warn_ms=100, message_error_ms=200)
    v = Vehicle(thresholds=tight)
    v.fly(1.5)
    assert v.at(0.22).level == ERROR
    v.tracker.set_thresholds(TH)
    assert v.at(0.22).level == WARN


def test_one_forged_low_time_boot_is_refuted_by_the_stream_that_follows() -> None:
    v = Vehicle()
    v.fly(1.0)
    forged_seq = (v.encoder.seq + 100) % 256  # not the stream's next number
    v.observe(mav.MAVLink_attitude_message(5, 0, 0, 0, 0, 0, 0), seq=forged_seq)
    v.fly(0.5)
    assert "reboot" not in codes(v.at(0.0)) and v.tracker.refuted == 1


def test_a_forged_frame_that_guessed_the_sequence_is_refuted_by_the_old_timeline() -> None:
    v = Vehicle()
    v.fly(1.0)
    v.observe(mav.MAVLink_attitude_message(5, 0, 0, 0, 0, 0, 0), seq=v.encoder.seq)
    v.fly(0.2)  # the genuine frames continue on the old timeline
    assert "reboot" not in codes(v.at(0.0)) and v.tracker.refuted == 1


@pytest.mark.parametrize("follow_up", ["old-sequence", "healthy-heartbeat"])
def test_a_lone_emergency_heartbeat_is_refuted(follow_up: str) -> None:
    v = Vehicle()
    v.fly(1.0)
    if follow_up == "old-sequence":
        v.observe(
            mav.MAVLink_heartbeat_message(2, MAV_AUTOPILOT_PX4, ARMED, LOITER, 6, 3),
            seq=(v.encoder.seq + 128) % 256,
        )
        v.fly(0.3)
    else:
        v.heartbeat(state=MavState.EMERGENCY)
        v.heartbeat()  # the autopilot's next heartbeat says it is fine
        v.fly(0.3)
    assert v.at(0.0).level == OK and v.tracker.refuted == 1


def test_a_second_fatal_heartbeat_confirms_when_sequence_numbers_say_nothing() -> None:
    v = Vehicle()
    v.fly(1.0)
    v.observe(mav.MAVLink_heartbeat_message(2, MAV_AUTOPILOT_PX4, ARMED, LOITER, 6, 3), seq=7)
    v.observe(mav.MAVLink_heartbeat_message(2, MAV_AUTOPILOT_PX4, ARMED, LOITER, 6, 3), seq=7)
    assert "mav-state" in failing_codes(v.at(0.0))


# -- no health without evidence: start-up is STARTING, not OK and not failed -----------

STARTING = HealthLevel.STARTING
DISARMED = 1 | 28  # custom mode enabled + PX4's usual bits, not armed


def estimator(v: Vehicle, flags: int, kind: str = "ESTIMATOR_STATUS") -> None:
    if kind == "ESTIMATOR_STATUS":
        msg = mav.MAVLink_estimator_status_message(0, flags, 0, 0, 0, 0, 0, 0, 0, 0)
    else:
        msg = mav.MAVLink_ekf_status_report_message(flags, 0, 0, 0, 0, 0)
    v.tracker.observe(msg, v.t)


def test_messages_before_the_first_heartbeat_are_starting_not_ok() -> None:
    v = Vehicle()
    v.attitude()
    a = v.at(0.01)
    assert a.level == STARTING and codes(a) == {"starting"} and not a.failing
    assert a.reasons == ("no heartbeat yet",)


@pytest.mark.parametrize(
    ("stack", "state", "level"),
    [
        (Stack.PX4, MavState.UNINIT, STARTING),  # PX4 v1.16 reports UNINIT for ~4 s
        (Stack.PX4, MavState.BOOT, STARTING),
        (Stack.ARDUPILOT, MavState.BOOT, STARTING),
        (Stack.PX4, MavState.STANDBY, OK),
        (Stack.ARDUPILOT, MavState.STANDBY, OK),
    ],
)
def test_booting_on_the_ground_is_starting(stack: Stack, state: int, level: HealthLevel) -> None:
    v = Vehicle(stack)
    autopilot = MAV_AUTOPILOT_PX4 if stack == Stack.PX4 else MAV_AUTOPILOT_ARDUPILOTMEGA
    mode = custom_mode(stack, "AUTO.LOITER" if stack == Stack.PX4 else "STABILIZE")
    v.heartbeat(state=state, base_mode=DISARMED, mode=mode, autopilot=autopilot)
    v.landed(MavLandedState.ON_GROUND)
    a = v.at(0.01)
    assert a.level == level and not a.failing


def test_booting_state_in_the_air_is_still_an_error() -> None:
    v = Vehicle()
    v.fly(1.0)
    v.heartbeat(state=MavState.UNINIT)
    a = v.at(0.0)
    assert a.level == ERROR and a.failing


@pytest.mark.parametrize(
    ("kind", "flags"),
    [("ESTIMATOR_STATUS", 0x480), ("EKF_STATUS_REPORT", 0x400)],  # seen at boot
)
def test_estimator_start_up_is_starting_then_a_later_loss_is_an_error(
    kind: str, flags: int
) -> None:
    v = Vehicle()
    v.heartbeat(state=MavState.STANDBY, base_mode=DISARMED)
    v.landed(MavLandedState.ON_GROUND)
    estimator(v, flags, kind)
    v.t += 5.0  # far beyond sensor_persist_ms: still only starting
    v.heartbeat(state=MavState.STANDBY, base_mode=DISARMED)
    a = v.at(0.0)
    assert a.level == STARTING and "estimator-starting" in codes(a) and not a.failing
    estimator(v, 0x1 | 0x2 | 0x4 | 0x8 | 0x10 | 0x20, kind)  # attitude and position good
    assert v.at(0.0).level == OK
    estimator(v, flags, kind)  # lost after it worked
    v.t += 1.0
    v.heartbeat(state=MavState.STANDBY, base_mode=DISARMED)
    a = v.at(0.0)
    assert a.level == ERROR and "estimator" in codes(a)


def test_gps_wait_is_starting_and_losing_position_later_only_warns() -> None:
    v = Vehicle(Stack.ARDUPILOT)
    v.heartbeat(
        state=MavState.STANDBY,
        base_mode=DISARMED,
        mode=custom_mode(Stack.ARDUPILOT, "STABILIZE"),
        autopilot=MAV_AUTOPILOT_ARDUPILOTMEGA,
    )
    v.landed(MavLandedState.ON_GROUND)
    estimator(v, 0x1 | 0x2 | 0x4, "EKF_STATUS_REPORT")  # attitude, no absolute position
    a = v.at(0.0)
    assert a.level == STARTING and a.reasons == ("waiting for an absolute position estimate (GPS)",)
    estimator(v, 0x1 | 0x2 | 0x4 | 0x10, "EKF_STATUS_REPORT")
    assert v.at(0.0).level == OK
    estimator(v, 0x1 | 0x2 | 0x4, "EKF_STATUS_REPORT")
    assert v.at(0.0).level == WARN


def test_px4_uninit_after_a_failsafe_landing_is_not_a_reboot() -> None:
    """PX4 v1.16 reports UNINIT once disarmed after a battery-failsafe landing."""
    v = Vehicle()
    v.fly(1.0)
    v.landed(MavLandedState.ON_GROUND)
    v.heartbeat(state=MavState.UNINIT, base_mode=DISARMED)
    a = v.at(0.0)
    assert "reboot" not in codes(a) and v.tracker.stream_facts().reboots == 0
    assert a.level == STARTING and not a.failing


def test_boot_after_being_up_is_a_reboot_and_counted() -> None:
    v = Vehicle()
    v.fly(1.0)
    v.heartbeat(state=MavState.BOOT)
    assert v.tracker.stream_facts().reboots == 0  # one message is a claim, not evidence
    v.heartbeat(state=MavState.BOOT)  # the next heartbeat in sequence corroborates it
    a = v.at(0.0)
    assert "reboot" in codes(a) and a.failing
    assert v.tracker.stream_facts().reboots == 1


def test_motion_and_per_type_counts_are_kept() -> None:
    v = Vehicle()
    assert v.tracker.motion() is None
    v.fly(1.0)
    v.tracker.observe(
        mav.MAVLink_global_position_int_message(0, 0, 0, 600_000, 4_800, 0, 0, 245, 0), v.t
    )
    motion = v.tracker.motion()
    assert motion is not None and motion.altitude_m == 4.8 and motion.climb_mps == -2.45
    facts = v.tracker.stream_facts()
    assert facts.counts["ATTITUDE"] == 50 and facts.counts["GLOBAL_POSITION_INT"] == 1


def test_liveness_follows_the_verified_requested_streams() -> None:
    v = Vehicle()
    for _ in range(3):  # heartbeats only: a slow link, silence is judged by heartbeat age
        v.heartbeat()
        v.t += 1.0
    assert "silent" not in codes(v.at(0.6))
    v.tracker.expect_streams(72.0)  # the keeper verified 72 msg/s of requested streams
    assert "silent" in codes(v.at(0.6))
    v.tracker.expect_streams(None)
    assert "silent" not in codes(v.at(0.6))


def test_a_reboot_in_the_air_is_reported_as_the_reboot_not_as_a_disarm() -> None:
    """A rebooting autopilot comes back disarmed: the reason is the reboot."""
    v = Vehicle()
    v.fly(1.0)
    v.landed(MavLandedState.IN_AIR)
    v.heartbeat(state=MavState.BOOT, base_mode=DISARMED)
    v.heartbeat(state=MavState.BOOT, base_mode=DISARMED)
    a = v.at(0.0)
    assert a.failing and "rebooted" in a.failure_reason
    assert "disarmed while in the air" not in a.failure_reason


# -- holds: when the decision loop may keep a judgement (decision table, then property) ----


def judgement(a: Assessment) -> tuple[object, ...]:
    """What the decision loop reads of an assessment (everything but its ages)."""
    return (a.level, a.findings, a.custom_mode, a.armed, a.landed_state, a.system_status)


def _estimator(v: Vehicle, flags: int) -> None:
    v.observe(mav.MAVLink_estimator_status_message(0, flags, 0, 0, 0, 0, 0, 0, 0, 0))


GOOD_ESTIMATOR = 0x1 | 0x2 | 0x4 | 0x8 | 0x10 | 0x20
HOLD_TABLE: list[tuple[str, Any, float, bool]] = [
    # (what happens after the judgement at v.t, then the check dt later, holds?)
    ("nothing new, no threshold reached", lambda v: None, 0.1, True),
    ("silence up to just before the warn threshold", lambda v: None, 0.17, True),
    ("silence reaches the warn threshold (200 ms after the last message)", None, 0.18, False),
    ("a message that only arrives", lambda v: v.attitude(), 0.05, True),
    ("the same heartbeat again", lambda v: v.heartbeat(), 0.05, True),
    ("MAV_STATE CRITICAL", lambda v: v.heartbeat(state=MavState.CRITICAL), 0.05, False),
    ("disarmed", lambda v: v.heartbeat(base_mode=0), 0.05, False),
    ("another mode", lambda v: v.heartbeat(mode=custom_mode(Stack.PX4, "POSCTL")), 0.05, False),
    ("the same SYS_STATUS again", lambda v: v.sys_status(), 0.05, True),
    (
        "a sensor goes unhealthy",
        lambda v: v.sys_status(health=SENSORS & ~int(SensorBit.GYRO)),
        0.05,
        False,
    ),
    ("landed", lambda v: v.landed(MavLandedState.ON_GROUND), 0.05, False),
    ("tilted past the warning", lambda v: v.attitude(roll=math.radians(40)), 0.05, False),
    ("a small tilt", lambda v: v.attitude(roll=math.radians(5)), 0.05, True),
    ("estimator flags change", lambda v: _estimator(v, GOOD_ESTIMATOR & ~0x10), 0.05, False),
    ("requested streams verified", lambda v: v.tracker.expect_streams(50.0), 0.05, False),
    ("new thresholds", lambda v: v.tracker.set_thresholds(Thresholds()), 0.05, False),
]


@pytest.mark.parametrize(
    ("what", "action", "dt", "holds"), HOLD_TABLE, ids=[row[0] for row in HOLD_TABLE]
)
def test_a_judgement_holds_until_something_it_reads_changes_or_a_threshold_passes(
    what: str, action: Any, dt: float, holds: bool
) -> None:
    v = Vehicle()
    _estimator(v, GOOD_ESTIMATOR)
    v.fly(2.0)  # the last ATTITUDE 20 ms before v.t
    judged = v.at(0.0)
    assert judged.level == OK and not judged.findings
    if action is not None:
        action(v)
    now = v.t + dt
    assert v.tracker.holds(judged, now) is holds, what
    if holds:
        assert judgement(v.tracker.assess(now)) == judgement(judged)


def test_frozen_telemetry_ends_the_hold_at_its_threshold() -> None:
    v = Vehicle()
    v.fly(2.0)
    judged = v.at(0.0)
    frozen_at = v.t - 1 / 50  # the last time_boot_ms advance
    for _ in range(30):  # messages keep coming, time_boot_ms stuck
        v.attitude(advance=False)
        v.t += 1 / 50
    assert v.tracker.holds(judged, frozen_at + 0.49)
    assert not v.tracker.holds(judged, frozen_at + 0.5)
    assert "frozen" in codes(v.tracker.assess(frozen_at + 0.5))


def test_a_judgement_whose_text_reads_the_clock_never_holds() -> None:
    v = Vehicle()
    v.fly(2.0)
    late = v.at(0.25)
    assert codes(late) == {"late"}
    assert not v.tracker.holds(late, late.at)


STEP = st.tuples(
    st.floats(min_value=0.0, max_value=0.7),
    st.sampled_from(
        [
            "attitude",
            "frozen",
            "tilt",
            "heartbeat",
            "critical",
            "emergency",
            "disarm",
            "gyro",
            "sensors",
            "landed",
            "airborne",
            "estimator-bad",
            "estimator-good",
            "reboot",
            "boot-state",
            "burst",
            "streams",
            "no-streams",
            "nothing",
        ]
    ),
)


def _act(v: Vehicle, action: str) -> None:
    actions: dict[str, Callable[[], object]] = {
        "attitude": v.attitude,
        "frozen": lambda: v.attitude(advance=False),
        "tilt": lambda: v.attitude(roll=math.radians(70)),
        "heartbeat": v.heartbeat,
        "critical": lambda: v.heartbeat(state=MavState.CRITICAL),
        "emergency": lambda: v.heartbeat(state=MavState.EMERGENCY),
        "disarm": lambda: v.heartbeat(base_mode=0),
        "gyro": lambda: v.sys_status(health=SENSORS & ~int(SensorBit.GYRO)),
        "sensors": lambda: v.sys_status(health=SENSORS),
        "landed": lambda: v.landed(MavLandedState.ON_GROUND),
        "airborne": lambda: v.landed(MavLandedState.IN_AIR),
        "estimator-bad": lambda: _estimator(v, 0),
        "estimator-good": lambda: _estimator(v, GOOD_ESTIMATOR),
        "reboot": lambda: v.observe(mav.MAVLink_attitude_message(50, 0, 0, 0, 0, 0, 0)),
        "boot-state": lambda: v.heartbeat(state=MavState.BOOT),
        "burst": lambda: [v.attitude() for _ in range(30)],
        "streams": lambda: v.tracker.expect_streams(50.0),
        "no-streams": lambda: v.tracker.expect_streams(None),
        "nothing": lambda: None,
    }
    actions[action]()


@settings(max_examples=200, deadline=None)
@given(st.lists(STEP, min_size=1, max_size=40))
def test_a_judgement_that_holds_is_the_judgement_made_afresh(
    steps: list[tuple[float, str]],
) -> None:
    """The decision loop's ticks (every 10 ms) over random flights with silences: at
    every tick where the last judgement holds, judging afresh finds exactly the same."""
    v = Vehicle()
    v.fly(1.5)
    judged = v.at(0.0)
    tick = v.t
    for dt, action in steps:
        end = v.t + dt
        while tick <= end:
            fresh = v.tracker.assess(tick)
            if v.tracker.holds(judged, tick):
                assert judgement(fresh) == judgement(judged), (tick, action)
            else:
                judged = fresh
            tick += 0.01
        v.t = end
        _act(v, action)


def _position(v: Vehicle, relative_alt: int, vz: int, hdg: int) -> None:
    """GLOBAL_POSITION_INT; zero ``vz`` and ``hdg`` end a MAVLink 2 payload early."""
    v.observe(
        mav.MAVLink_global_position_int_message(
            v.boot_ms, 473_977_418, 85_455_938, 500_000, relative_alt, 0, 0, vz, hdg
        )
    )


def observed(v: Vehicle) -> dict[str, object]:
    """Everything the tracker remembers but the last position message itself."""
    o = v.tracker._o
    return {f.name: getattr(o, f.name) for f in dataclasses.fields(o) if f.name != "position_msg"}


@settings(max_examples=100, deadline=None)
@given(
    st.lists(STEP, min_size=1, max_size=30),
    st.lists(
        st.tuples(
            st.integers(-(2**31), 2**31 - 1),
            st.integers(-(2**15), 2**15 - 1),
            st.sampled_from([0, 9000, 65535]),
        ),
        min_size=1,
        max_size=5,
    ),
)
def test_the_agents_frames_are_judged_as_pymavlinks_messages(
    steps: list[tuple[float, str]], positions: list[tuple[int, int, int]]
) -> None:
    """The tracker reads the link's frames natively (``time_boot_ms``, attitude and
    vertical state at precomputed offsets, also from payloads MAVLink 2 cut short) and
    any other message by field name: the same flight either way leaves the same
    observations, judgements, motion and fix."""
    theirs, ours = Vehicle(), Vehicle(codec=True)
    for v in (theirs, ours):
        v.fly(1.5, roll=0.3, pitch=-0.2)
    for i, (dt, action) in enumerate(steps):
        for v in (theirs, ours):
            v.t += dt
            _act(v, action)
            _position(v, *positions[i % len(positions)])
        assert observed(ours) == observed(theirs), action
        assert judgement(ours.at(0.01)) == judgement(theirs.at(0.01))
        assert ours.tracker.motion() == theirs.tracker.motion()
        assert ours.tracker.fix() == theirs.tracker.fix()


def _local_position(v: Vehicle, back_ms: int = 0) -> None:
    """LOCAL_POSITION_NED (read by nobody: the fast path's routine kind) saying
    ``back_ms`` before the stream's time (a back-step of more than the reboot rule's is a
    reboot claim)."""
    v.observe(mav.MAVLink_local_position_ned_message(max(0, v.boot_ms - back_ms), 1, 2, 3, 0, 0, 0))


ROUTINE_STEP = st.tuples(
    st.sampled_from([0.001, 0.02, 0.1, 0.3, 0.6, 1.2]),
    st.sampled_from(
        [
            "routine",
            "routine",
            "routine-back",
            "routine-burst",
            "attitude",
            "heartbeat",
            "reboot",
            "boot-state",
            "critical",
            "nothing",
        ]
    ),
)


def _routine(v: Vehicle, action: str) -> None:
    if action == "routine":
        _local_position(v)
    elif action == "routine-back":
        _local_position(v, back_ms=60_000)
    elif action == "routine-burst":
        for _ in range(20):
            v.t += 0.002
            _local_position(v)
    else:
        _act(v, action)


@settings(max_examples=150, deadline=None)
@given(st.lists(ROUTINE_STEP, min_size=1, max_size=40))
def test_routine_frames_summarised_are_judged_as_whole_frames(
    steps: list[tuple[float, str]],
) -> None:
    """The hub's fast path hands the tracker a routine frame (a kind whose content no
    one reads) by its type, ``time_boot_ms`` and sequence number alone
    (``observe_routine``): the same flight, reboot claims by ``time_boot_ms`` going back,
    their corroboration and refutation by sequence numbers, silences and rate windows
    included, leaves the same observations and judgements as the frames observed whole."""
    whole, summarised = Vehicle(codec=True), Vehicle(summarise=True)
    for v in (whole, summarised):
        v.fly(1.5)
    for dt, action in steps:
        changed = []
        for v in (whole, summarised):
            v.t += dt
            _routine(v, action)
            changed.append(observed(v))
        assert changed[0] == changed[1], action
        assert judgement(summarised.at(0.01)) == judgement(whole.at(0.01))


RUN_STEP = st.tuples(
    st.sampled_from([0.001, 0.02, 0.05, 0.1, 0.3, 0.6, 1.2]),
    st.sampled_from(
        [
            "routine",
            "routine-burst",
            "routine-back",
            "burst-back",
            "attitude-burst",
            "tilt-burst",
            "mixed-burst",
            "gap-burst",
            "position",
            "heartbeat",
            "reboot",
            "boot-state",
            "critical",
            "gyro",
            "sensors",
            "landed",
            "airborne",
            "estimator-bad",
            "estimator-good",
            "state-burst",
            "nothing",
        ]
    ),
)


def _moving(v: Vehicle) -> None:
    """GLOBAL_POSITION_INT (read for its latest value only) on the stream's timeline,
    climbing."""
    v.boot_ms = 100_000 + round(v.t * 1000)
    _position(v, round(v.t * 1000), -50, 9000)


def _burst(v: Vehicle, frames: list[Callable[[], object]], spacing_s: float = 0.002) -> None:
    for frame in frames:
        v.t += spacing_s
        frame()


def _run_action(v: Vehicle, action: str) -> None:
    level = v.attitude
    tilted = lambda: v.attitude(roll=math.radians(70))  # noqa: E731
    warned = lambda: v.attitude(roll=math.radians(40))  # noqa: E731
    routine = lambda: _local_position(v)  # noqa: E731
    bursts: dict[str, Callable[[], None]] = {
        "routine-burst": lambda: _burst(v, [routine] * 40),
        "burst-back": lambda: _burst(
            v, [routine] * 10 + [lambda: _local_position(v, back_ms=60_000)] + [routine] * 10
        ),
        "attitude-burst": lambda: _burst(v, [level] * 30),
        "tilt-burst": lambda: _burst(v, [level] * 5 + [tilted] * 10 + [warned] * 5 + [level] * 5),
        "mixed-burst": lambda: _burst(
            v, [level, routine, lambda: _moving(v), tilted, routine, level] * 6, 0.004
        ),
        # frames 30 ms apart, then one 80 ms later: gaps about the learnt silence
        # threshold, and rate windows closing inside the burst
        "gap-burst": lambda: (
            _burst(v, [routine] * 8 + [level] * 4, 0.03) or _burst(v, [routine, level], 0.08)
        ),
        "position": lambda: _moving(v),
        # the state kinds repeated among the bulk (each joins a run while it repeats
        # what the tracker holds)
        "state-burst": lambda: _burst(
            v,
            [
                level,
                v.sys_status,
                routine,
                v.landed,
                lambda: _estimator(v, GOOD_ESTIMATOR),
                level,
            ]
            * 5,
            0.004,
        ),
    }
    burst = bursts.get(action)
    if burst is not None:
        burst()
    else:
        _routine(v, action)


@settings(max_examples=150, deadline=None)
@given(st.sampled_from([TH, Thresholds()]), st.lists(RUN_STEP, min_size=1, max_size=40))
# after a reboot the silence threshold is learnt again: a rate window closing inside a
# burst learns it, and the gaps after it in the same read are silences by it
@example(
    Thresholds(),
    [(0.001, "boot-state"), (0.001, "routine"), (0.3, "routine"), (1.2, "gap-burst")],
)
def test_runs_taken_together_are_judged_as_their_frames_one_by_one(
    thresholds: Thresholds, steps: list[tuple[float, str]]
) -> None:
    """The hub's fast path hands the tracker the bulk of the stream as runs
    (``observe_run``: routine kinds, ATTITUDE and GLOBAL_POSITION_INT of which the last
    counts, and the state kinds while they repeat the state held), ended by the C rules
    (tests/support/feed.py ``RunModel``: before a gap of the silence threshold, at the
    frame that closes a rate window, before a frame read whole; a tilt class change, a
    state that changes, a step back in ``time_boot_ms`` and a HEARTBEAT go whole and end
    the C call). The same flight, silences, rate windows, tilts, reboots and their claims
    included, leaves the same observations and judgements as every frame observed
    whole."""
    whole = Vehicle(thresholds=thresholds, codec=True)
    runs = Vehicle(thresholds=thresholds, runs=True)
    for v in (whole, runs):
        v.fly(9)  # the default thresholds learn the silence threshold from 8 windows
        v.flush()
    for dt, action in steps:
        seen = []
        for v in (whole, runs):
            v.t += dt
            _run_action(v, action)
            v.flush()
            seen.append(observed(v))
        assert seen[0] == seen[1], action
        assert judgement(runs.at(0.01)) == judgement(whole.at(0.01))


def test_a_tilt_beyond_the_envelope_inside_a_run_is_timed_from_its_first_frame() -> None:
    """Decision table: a tilt class change never disappears inside a run; the time the
    attitude left the envelope is that of the first frame beyond it, kept while it
    stays beyond, and gone with the first frame back inside."""
    v = Vehicle(runs=True)
    v.fly(1.5)
    v.flush()
    left_at = None
    rows = [(0, False), (70, True), (70, True), (40, False), (70, True), (0, False)]
    for roll_deg, beyond in rows:
        first = v.t + 0.002
        _burst(v, [lambda r=roll_deg: v.attitude(roll=math.radians(r))] * 5)
        v.flush()
        if beyond and left_at is None:
            left_at = first
        elif not beyond:
            left_at = None
        assert v.tracker._o.tilt_over_since == left_at, roll_deg
        assert v.tracker._o.tilt_deg == pytest.approx(roll_deg, abs=0.01)


def test_a_routine_frames_summary_reports_a_confirmed_reboot_as_a_change() -> None:
    """Decision table: what ``observe_routine`` returns, as ``observe`` would."""
    whole, summarised = Vehicle(codec=True), Vehicle(summarise=True)
    for v in (whole, summarised):
        v.fly(1.5)
    # a frame, a reboot claim (time_boot_ms back a minute), the next frame on the new
    # timeline confirming it, then one after a silence
    rows = [(0.02, 0, False), (0.02, 60_000, False), (0.02, 60_000, True), (0.5, 60_000, True)]
    for dt, back_ms, changes in rows:
        said = []
        for v in (whole, summarised):
            v.t += dt
            said.append(
                v.observe(
                    mav.MAVLink_local_position_ned_message(
                        max(0, v.boot_ms - back_ms), 1, 2, 3, 0, 0, 0
                    )
                )
            )
        assert said == [changes, changes], (dt, back_ms)
    assert summarised.tracker.stream_facts().reboots == whole.tracker.stream_facts().reboots == 1


# -- the default thresholds: decision tables at their boundaries ---------------------------

DEFAULTS = Thresholds()
# The defaults with the silence threshold at its ceiling (as while it learns).
FIXED_DEFAULTS = Thresholds(message_error_min_ms=DEFAULTS.message_error_ms)
# HEARTBEAT period: nominal 1 Hz on both stacks, and the longest gap in the recorded
# firmware traffic (PX4 v1.16 SIH, ArduCopter SITL; see test_agent_health_replay).
HEARTBEAT_PERIOD_S = (1.0, 1.015)
LINK_JITTER_S = 0.05  # the soak's jitter: each frame delayed by 0..50 ms


def streaming(v: Vehicle, start_s: float, end_s: float, beats_until_s: float) -> list[Assessment]:
    """ATTITUDE at 50 Hz and SYS_STATUS at 5 Hz on the exact sample times i/50 from
    ``start_s`` to ``end_s``; HEARTBEAT and landed state each whole second up to
    ``beats_until_s``. Returns the judgement after each sample, as the decision loop
    would see it."""
    seen = []
    for i in range(round(start_s * 50), math.floor(end_s * 50) + 1):
        v.t = i / 50
        if i % 50 == 0 and v.t <= beats_until_s:
            v.heartbeat()
            v.landed()
        if i % 10 == 0:
            v.sys_status()
        v.attitude()
        seen.append(v.at(0.0))
    return seen


def below_at_above(
    clock: str, warn: str, error: str, late: str, lost: str
) -> list[tuple[str, str, int, HealthLevel, set[str]]]:
    """(clock, threshold, ms relative to it, level, findings): 1 ms under, at and 1 ms
    over the warn and the error threshold of one liveness clock."""
    return [
        (clock, warn, -1, OK, set()),
        (clock, warn, 0, WARN, {late}),
        (clock, warn, 1, WARN, {late}),
        (clock, error, -1, WARN, {late}),
        (clock, error, 0, ERROR, {lost}),
        (clock, error, 1, ERROR, {lost}),
    ]


BOUNDARIES = [
    *below_at_above(
        "heartbeat", "heartbeat_warn_ms", "heartbeat_error_ms", "heartbeat-late", "heartbeat-lost"
    ),
    *below_at_above("message", "message_warn_ms", "message_error_ms", "late", "silent"),
]


@pytest.mark.parametrize(("clock", "threshold", "offset_ms", "level", "found"), BOUNDARIES)
def test_liveness_at_the_default_boundaries(
    clock: str, threshold: str, offset_ms: int, level: HealthLevel, found: set[str]
) -> None:
    """At t=0 either the heartbeats stop while telemetry keeps streaming at 50 Hz (only
    the heartbeat age decides) or the whole stream stops (the message age decides).
    Only ERROR may fail over, from the last message of the clock as its onset."""
    age_s = (getattr(DEFAULTS, threshold) + offset_ms) / 1000
    v = Vehicle(thresholds=DEFAULTS if clock == "heartbeat" else FIXED_DEFAULTS)
    streaming(v, -3.0, age_s if clock == "heartbeat" else 0.0, beats_until_s=0.0)
    a = v.tracker.assess(age_s)
    assert (a.level, codes(a), a.failing) == (level, found, level == ERROR)
    assert (a.heartbeat_age_s if clock == "heartbeat" else a.message_age_s) == age_s
    if a.failing:
        assert a.onset == 0.0


@pytest.mark.parametrize("timing", ["shortest", "longest"])
@pytest.mark.parametrize(
    ("lost", "level"), [(0, OK), (1, OK), (2, WARN), (3, WARN), (4, ERROR), (5, ERROR)]
)
def test_consecutive_lost_heartbeats_at_the_defaults(
    lost: int, level: HealthLevel, timing: str
) -> None:
    """The worst judgement while ``lost`` heartbeats in a row are missing, with the gap
    to the next one as short or as long as the period and the link's jitter make it:
    WARN takes two lost in a row, ERROR four (docs/health-model.md has the rates)."""
    shortest = timing == "shortest"
    period = HEARTBEAT_PERIOD_S[0] if shortest else HEARTBEAT_PERIOD_S[1]
    gap_s = (lost + 1) * period + (-LINK_JITTER_S if shortest else LINK_JITTER_S)
    v = Vehicle(thresholds=DEFAULTS)
    streaming(v, -3.0, 0.0, beats_until_s=0.0)
    seen = streaming(v, 0.02, gap_s, beats_until_s=0.0)
    seen.append(v.tracker.assess(math.nextafter(gap_s, 0.0)))  # just before it arrives
    worst = max((a.level for a in seen), key=lambda lv: lv.rank)
    assert worst == level, [a.reasons for a in seen if a.level == worst][:1]


def test_the_first_message_after_a_silence_tells_the_decision_loop() -> None:
    """The arbiter's time free of failures for an autopilot starts at the tick that sees
    it OK: the message that ends a silence wakes the loop, as a changed fact does."""
    v = Vehicle()
    v.fly(2.0)
    v.t += TH.message_error_ms / 1000 + 0.1  # silent past the error threshold
    assert v.at(0.0).level == ERROR
    assert v.attitude_changes() is True  # heard again
    v.t += 0.01
    assert v.attitude_changes() is False  # and then nothing new


# What the hub's fast path postpones (roost_agent.fastpath): the thresholds on the last
# message's age move with each message, frozen telemetry's with each message whose
# time_boot_ms advances; no other threshold does.
def _frozen_for(v: Vehicle, seconds: float) -> float:
    """Messages keep coming for ``seconds``, their time_boot_ms stuck; the last one's time."""
    for _ in range(round(seconds * 50)):
        v.t += 1 / 50
        v.attitude(advance=False)
    return v.t


POSTPONE_TABLE: list[tuple[str, Callable[[Vehicle], float | None], float]] = [
    # (what, then, frozen telemetry's threshold after the last time_boot_ms advance)
    ("a healthy fast stream", lambda _: None, 0.5),
    (
        "frozen for 200 ms: messages that do not advance do not postpone it",
        lambda v: _frozen_for(v, 0.2),
        0.5,
    ),
]


@pytest.mark.parametrize(
    ("what", "then", "frozen_after"), POSTPONE_TABLE, ids=[r[0] for r in POSTPONE_TABLE]
)
def test_only_the_thresholds_on_the_last_messages_age_are_postponed_by_messages(
    what: str, then: Callable[[Vehicle], float | None], frozen_after: float
) -> None:
    v = Vehicle()
    v.fly(2.0)
    advanced = v.t - 1 / 50  # the last ATTITUDE of the flight, its time_boot_ms advancing
    last = then(v) or advanced
    judged = v.tracker.assess(v.t)
    fixed, age, frozen, frozen_age = v.tracker.postponed_by_messages(judged)
    assert age == pytest.approx(0.2, abs=1e-5), what  # late: 200 ms after the last message
    assert frozen - advanced == pytest.approx(frozen_after, abs=1e-5), what
    assert frozen_age == pytest.approx(frozen_after, abs=1e-5), what
    assert fixed > frozen, what  # the heartbeat's thresholds, later here
    # together they are the next threshold
    assert v.tracker.next_threshold(judged) == pytest.approx(min(fixed, last + age, frozen)), what


@pytest.mark.parametrize("learnt", [False, True], ids=["the ceiling", "learnt"])
def test_left_out_the_late_warning_the_next_threshold_is_the_silence(learnt: bool) -> None:
    """What a standby's judgement waits for in the fast path (Agent.postponable): every
    threshold but the late stream's warning. Its silence, a failure, still counts."""
    th = TH.model_copy(update={"message_error_min_ms": 40})  # a floor the stream can learn
    v = Vehicle(thresholds=th)
    v.fly(2.5 if learnt else 1.5)  # a rate window closed: a fast stream, learnt or not
    last = v.t - 1 / 50  # the flight's last message
    judged = v.tracker.assess(last + 0.001)
    silence = v.tracker.silence_threshold_s()
    assert (silence < th.message_error_ms / 1000) == learnt
    late = silence * th.message_warn_ms / th.message_error_ms
    assert v.tracker.next_threshold(judged) == pytest.approx(last + late, abs=1e-5)
    for without_late in (
        v.tracker.next_threshold(judged, late_warning=False),
        v.tracker.holds_until(judged, late_warning=False),
    ):
        assert without_late == pytest.approx(last + silence, abs=1e-5)
    # past the late threshold the judgement is a warning, which does not fail
    late_judged = v.tracker.assess(last + late + 0.001)
    assert late_judged.level == HealthLevel.WARN and not late_judged.failing
    assert v.tracker.assess(last + silence + 0.001).failing


def test_left_out_the_late_warning_a_slow_stream_waits_as_before() -> None:
    """A stream too slow for the any-message age (heartbeats only) has no late warning:
    both ways the next threshold is the same."""
    v = Vehicle()
    for _ in range(5):
        v.t += 1.0
        v.heartbeat()
    judged = v.tracker.assess(v.t)
    assert v.tracker.next_threshold(judged, late_warning=False) == v.tracker.next_threshold(judged)


def test_a_tracker_without_messages_postpones_nothing() -> None:
    v = Vehicle()
    judged = v.tracker.assess(1.0)
    assert v.tracker.postponed_by_messages(judged) == (math.inf,) * 4
