"""Health judgement from MAVLink messages (real pymavlink message objects, explicit times)."""

from __future__ import annotations

import math
import os
from typing import Any

os.environ.setdefault("MAVLINK20", "1")

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from roost_agent.health import (
    REBOOT_REMEMBERED_S,
    Assessment,
    HealthTracker,
    tilt_degrees,
)
from roost_api.autopilot import Thresholds
from roost_api.meta import HealthLevel, Stack
from roost_mavlink import LandedState, MavState, SensorBit, custom_mode
from roost_mavlink.status import (
    MAV_AUTOPILOT_ARDUPILOTMEGA,
    MAV_AUTOPILOT_INVALID,
    MAV_AUTOPILOT_PX4,
    stack_sensors,
)

OK, WARN, ERROR, STALE = HealthLevel.OK, HealthLevel.WARN, HealthLevel.ERROR, HealthLevel.STALE
ARMED = 128 | 1
SENSORS = int(stack_sensors(Stack.PX4)) & ~int(SensorBit.RC_RECEIVER | SensorBit.PREARM_CHECK)
LOITER = custom_mode(Stack.PX4, "AUTO.LOITER")
# The numbers these tests assert are these thresholds', not whatever the defaults are.
HEARTBEAT_MS = {"heartbeat_warn_ms": 1500, "heartbeat_error_ms": 3000}
TH = Thresholds(message_warn_ms=200, message_error_ms=500, confirm_ms=100, **HEARTBEAT_MS)


class Vehicle:
    """Feeds one tracker the messages of a PX4-like autopilot at chosen times.

    Every message goes through a real encode and decode, so it carries the next MAVLink
    sequence number of the autopilot's stream (the corroboration rules read it).
    """

    def __init__(self, stack: Stack = Stack.PX4, thresholds: Thresholds | None = None) -> None:
        self.tracker = HealthTracker("fc1", stack, thresholds or TH)
        self.boot_ms = 100_000
        self.t = 0.0
        self.sensors_health = SENSORS
        self.sensors_enabled = SENSORS
        self.encoder = mav.MAVLink(None, srcSystem=1, srcComponent=1)
        self.decoder = mav.MAVLink(None)

    def observe(self, msg: Any, *, seq: int | None = None) -> bool:
        """Deliver ``msg`` as the stream's next frame (or with a forged ``seq``)."""
        if seq is not None:
            saved, self.encoder.seq = self.encoder.seq, seq
        frame = msg.pack(self.encoder)
        if seq is None:
            self.encoder.seq = (self.encoder.seq + 1) % 256
        else:
            self.encoder.seq = saved
        return self.tracker.observe(self.decoder.decode(bytearray(frame)), self.t)

    def heartbeat(
        self,
        *,
        state: int = MavState.ACTIVE,
        base_mode: int = ARMED,
        mode: int = LOITER,
        autopilot: int = MAV_AUTOPILOT_PX4,
    ) -> bool:
        msg = mav.MAVLink_heartbeat_message(2, autopilot, base_mode, mode, state, 3)
        return self.observe(msg)

    def landed(self, state: int = LandedState.IN_AIR) -> bool:
        return self.observe(mav.MAVLink_extended_sys_state_message(0, state))

    def sys_status(self, health: int | None = None, enabled: int | None = None) -> bool:
        if health is not None:
            self.sensors_health = health
        if enabled is not None:
            self.sensors_enabled = enabled
        enabled, health = self.sensors_enabled, self.sensors_health
        msg = mav.MAVLink_sys_status_message(
            enabled, enabled, health, 100, 12000, -1, -1, 0, 0, 0, 0, 0, 0
        )
        return self.observe(msg)

    def attitude(self, roll: float = 0.0, pitch: float = 0.0, *, advance: bool = True) -> None:
        if advance:
            self.boot_ms = 100_000 + round(self.t * 1000)
        msg = mav.MAVLink_attitude_message(self.boot_ms, roll, pitch, 0.0, 0.0, 0.0, 0.0)
        self.observe(msg)

    def attitude_changes(self) -> bool:
        """One ATTITUDE on the current timeline; whether the tracker reported a change."""
        self.boot_ms = 100_000 + round(self.t * 1000)
        return self.observe(mav.MAVLink_attitude_message(self.boot_ms, 0, 0, 0, 0, 0, 0))

    def fly(self, seconds: float, *, rate_hz: float = 50.0, **attitude: float) -> None:
        """Stream ATTITUDE at ``rate_hz`` plus 1 Hz heartbeats and 5 Hz status for ``seconds``."""
        end = self.t + seconds
        n = 0
        while self.t < end:
            if n % round(rate_hz) == 0:
                self.heartbeat()
                self.landed()
            if n % max(1, round(rate_hz / 5)) == 0:
                self.sys_status()
            self.attitude(**attitude)
            self.t += 1 / rate_hz
            n += 1

    def at(self, dt: float) -> Assessment:
        return self.tracker.assess(self.t + dt)


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
    ground.landed(LandedState.ON_GROUND)
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
    v.landed(LandedState.ON_GROUND)
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
    v.landed(LandedState.ON_GROUND)
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
    v.landed(LandedState.ON_GROUND)
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
    v.landed(LandedState.ON_GROUND)
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
    v.landed(LandedState.ON_GROUND)
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
    v.landed(LandedState.IN_AIR)
    v.heartbeat(state=MavState.BOOT, base_mode=DISARMED)
    v.heartbeat(state=MavState.BOOT, base_mode=DISARMED)
    a = v.at(0.0)
    assert a.failing and "rebooted" in a.failure_reason
    assert "disarmed while in the air" not in a.failure_reason


# -- the default thresholds: decision tables at their boundaries ---------------------------

DEFAULTS = Thresholds()
# HEARTBEAT period: nominal 1 Hz on both stacks, and the longest gap in the recorded
# firmware traffic (PX4 v1.16 SIH, ArduCopter SITL; see test_capture_replay).
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
    v = Vehicle(thresholds=DEFAULTS)
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
