"""Decision tables of the simulated autopilot's flight-controller rules (no sockets).

The simulator decides when to arm, refuse, disarm and land; agent tests trust those
decisions, so they are pinned here with a fake clock: each stack's refusal codes, forced
disarm, position-dependent modes, kinematics, auto-disarm, MAV_STATE and sensor bits.
"""

from __future__ import annotations

import math
import struct
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from roost_api.meta import Stack
from roost_mavlink import FORCE_DISARM_MAGIC, MavResult, custom_mode
from roost_mavlink.status import MavLandedState, MavState, SensorBit
from roost_sim.autopilot import SimulatedAutopilot
from roost_sim.control import handle_request
from roost_sim.faults import FaultKind, parse_number, parse_sensor, parse_state
from roost_sim.model import AutopilotModel, SimConfig
from roost_sim.params import ParamStore


class FakeClock:
    """Monotonic time the test advances by hand."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def make(stack: Stack, **config: Any) -> tuple[AutopilotModel, FakeClock]:
    clock = FakeClock()
    model = AutopilotModel(stack, SimConfig.fast(**config), clock=clock)
    clock.now += 1.0  # past the fast start-up (boot and position estimate)
    return model, clock


def run(model: AutopilotModel, clock: FakeClock, seconds: float, dt: float = 0.02) -> None:
    for _ in range(round(seconds / dt)):
        clock.now += dt
        model.step()


def airborne(stack: Stack) -> tuple[AutopilotModel, FakeClock]:
    model, clock = make(stack)
    if stack is Stack.ARDUPILOT:
        assert model.set_mode(custom_mode(stack, "GUIDED")) == MavResult.ACCEPTED
    assert model.arm(arm=True) == MavResult.ACCEPTED
    assert model.takeoff(math.nan) == MavResult.ACCEPTED
    run(model, clock, 2.0)
    assert model.landed_state is MavLandedState.IN_AIR
    return model, clock


REFUSED = {Stack.PX4: MavResult.TEMPORARILY_REJECTED, Stack.ARDUPILOT: MavResult.FAILED}


# Realistic start-up, as measured on the firmware: (seconds after boot, MAV_STATE,
# estimator flags, arm result).
BOOT_TIMELINE = {
    Stack.PX4: [
        (0.5, MavState.UNINIT, 0x400, MavResult.TEMPORARILY_REJECTED),
        (2.5, MavState.UNINIT, 0xE5, MavResult.TEMPORARILY_REJECTED),
        (3.5, MavState.UNINIT, 0x3FF, MavResult.TEMPORARILY_REJECTED),
        (4.1, MavState.STANDBY, 0x3FF, MavResult.ACCEPTED),
    ],
    Stack.ARDUPILOT: [
        (1.0, MavState.BOOT, 0x400, MavResult.FAILED),
        (3.0, MavState.STANDBY, 0x400, MavResult.FAILED),
        (10.0, MavState.STANDBY, 0xA7, MavResult.FAILED),
        (30.0, MavState.STANDBY, 0xA7, MavResult.FAILED),
        (40.7, MavState.STANDBY, 0x33F, MavResult.ACCEPTED),
    ],
}


@pytest.mark.parametrize("stack", list(Stack))
def test_realistic_boot_timeline(stack: Stack) -> None:
    for at, state, flags, arm in BOOT_TIMELINE[stack]:
        clock = FakeClock()
        model = AutopilotModel(stack, clock=clock)
        clock.now += at
        model.step()
        assert (model.system_status(), model.estimator_flags()) == (state, flags), at
        assert model.arm(arm=True) == arm, at
    assert model.mode == {Stack.PX4: "AUTO.LOITER", Stack.ARDUPILOT: "STABILIZE"}[stack]


def test_ardupilot_refuses_to_arm_with_its_own_texts_until_it_has_a_position() -> None:
    clock = FakeClock()
    model = AutopilotModel(Stack.ARDUPILOT, clock=clock)
    texts = []
    for at in (1.0, 10.0, 25.0):
        clock.now = 100.0 + at
        model.step()
        model.texts.clear()
        assert model.arm(arm=True) == MavResult.FAILED
        texts.append([text for _, text in model.texts])
    assert texts == [
        ["Arm: System not initialised"],
        ["Arm: AHRS: waiting for home"],
        ["Arm: Need Position Estimate"],
    ]


def test_ardupilot_mode_set_during_boot_is_overwritten_with_stabilize() -> None:
    clock = FakeClock()
    model = AutopilotModel(Stack.ARDUPILOT, clock=clock)
    clock.now += 0.5
    assert model.set_mode(custom_mode(Stack.ARDUPILOT, "GUIDED")) == MavResult.ACCEPTED
    clock.now += 2.0
    model.step()
    assert model.mode == "STABILIZE"
    assert model.set_mode(custom_mode(Stack.ARDUPILOT, "GUIDED")) == MavResult.ACCEPTED
    clock.now += 1.0
    model.step()
    assert model.mode == "GUIDED"


@pytest.mark.parametrize("stack", list(Stack))
def test_fast_boot_keeps_the_order_of_the_start_up_steps(stack: Stack) -> None:
    times = SimConfig.fast().boot_times(stack)
    real = SimConfig().boot_times(stack)
    assert times.standby_s < 1.0 and times.position_s < 1.0
    if stack is Stack.PX4:
        assert times.first_heartbeat_s < times.attitude_s < times.position_s < times.standby_s
        assert real.first_heartbeat_s < real.attitude_s < real.position_s < real.standby_s
    else:
        assert times.standby_s <= times.attitude_s < times.position_s
        assert real.standby_s < real.attitude_s < real.origin_s < real.position_s


@pytest.mark.parametrize("stack", list(Stack))
def test_arm_refused_with_a_failed_sensor_unless_forced(stack: Stack) -> None:
    model, _ = make(stack)
    model.sensor_faults = SensorBit.GYRO
    assert model.arm(arm=True) == REFUSED[stack]
    assert not model.armed
    assert model.arm(arm=True, magic=FORCE_DISARM_MAGIC) == MavResult.ACCEPTED
    assert model.armed


@pytest.mark.parametrize("stack", list(Stack))
def test_ignored_sensor_bits_do_not_block_arming(stack: Stack) -> None:
    model, _ = make(stack)
    model.sensor_faults = SensorBit.LOGGING
    assert model.arm(arm=True) == MavResult.ACCEPTED


@pytest.mark.parametrize("state", [MavState.CRITICAL, MavState.EMERGENCY])
def test_arm_refused_under_injected_bad_state(state: MavState) -> None:
    model, _ = make(Stack.PX4)
    model.state_override = state
    assert model.arm(arm=True) == MavResult.TEMPORARILY_REJECTED
    assert model.system_status() is state


def test_ardupilot_cannot_arm_in_land_mode() -> None:
    model, _ = make(Stack.ARDUPILOT)
    model.set_mode(custom_mode(Stack.ARDUPILOT, "LAND"))
    assert model.arm(arm=True) == MavResult.FAILED


@pytest.mark.parametrize("stack", list(Stack))
def test_disarm_in_air_needs_the_force_magic(stack: Stack) -> None:
    model, clock = airborne(stack)
    assert model.arm(arm=False) == REFUSED[stack]
    assert model.armed
    assert model.arm(arm=False, magic=math.nan) == REFUSED[stack]
    assert model.arm(arm=False, magic=FORCE_DISARM_MAGIC) == MavResult.ACCEPTED
    run(model, clock, 1.0)  # unpowered: it falls
    assert model.on_ground and not model.armed


@pytest.mark.parametrize("stack", list(Stack))
def test_takeoff_hold_land_and_auto_disarm(stack: Stack) -> None:
    model, clock = airborne(stack)
    assert model.altitude_m == pytest.approx(2.5)
    assert model.system_status() is MavState.ACTIVE
    hold = {Stack.PX4: "AUTO.LOITER", Stack.ARDUPILOT: "BRAKE"}[stack]
    assert model.set_mode(custom_mode(stack, hold)) == MavResult.ACCEPTED
    run(model, clock, 1.0)
    assert model.altitude_m == pytest.approx(2.5)
    assert model.land() == MavResult.ACCEPTED
    run(model, clock, 0.5)
    assert model.landed_state is MavLandedState.LANDING
    run(model, clock, 1.5)
    assert model.on_ground and model.armed  # touched down; disarms a moment later
    run(model, clock, 1.1)
    assert not model.armed
    modes = [change.mode for change in model.mode_history]
    land = {Stack.PX4: "AUTO.LAND", Stack.ARDUPILOT: "LAND"}[stack]
    assert modes[-2:] == [hold, land]


def test_px4_takeoff_goes_to_hold_and_uses_amsl_param7() -> None:
    model, clock = make(Stack.PX4)
    model.arm(arm=True)
    assert model.takeoff(model.config.home_amsl_m + 4.0) == MavResult.ACCEPTED
    assert model.mode == "AUTO.TAKEOFF"
    run(model, clock, 0.5)
    assert model.landed_state is MavLandedState.TAKEOFF
    run(model, clock, 2.0)
    assert model.altitude_m == pytest.approx(4.0)
    assert model.mode == "AUTO.LOITER"
    assert model.takeoff(model.config.home_amsl_m - 1.0) == MavResult.DENIED


def test_px4_takeoff_before_arming_climbs_once_armed() -> None:
    model, clock = make(Stack.PX4)
    assert model.takeoff(math.nan) == MavResult.ACCEPTED
    run(model, clock, 0.5)
    assert model.on_ground
    model.arm(arm=True)
    run(model, clock, 1.5)
    assert model.altitude_m == pytest.approx(2.5)


def test_ardupilot_takeoff_rules() -> None:
    model, clock = make(Stack.ARDUPILOT)
    assert model.takeoff(3.0) == MavResult.FAILED  # disarmed
    model.arm(arm=True)
    assert model.takeoff(3.0) == MavResult.FAILED  # STABILIZE has no user takeoff
    model.set_mode(custom_mode(Stack.ARDUPILOT, "GUIDED"))
    assert model.takeoff(3.0) == MavResult.ACCEPTED
    assert model.system_status() is MavState.STANDBY  # still on the ground
    run(model, clock, 2.0)
    assert model.altitude_m == pytest.approx(3.0)
    assert model.mode == "GUIDED"
    assert model.system_status() is MavState.ACTIVE
    assert model.takeoff(5.0) == MavResult.FAILED  # already flying


@pytest.mark.parametrize(
    ("stack", "hold", "land"),
    [(Stack.PX4, "AUTO.LOITER", "AUTO.LAND"), (Stack.ARDUPILOT, "LOITER", "LAND")],
)
def test_position_modes_refused_without_gps_but_land_works(
    stack: Stack, hold: str, land: str
) -> None:
    model, _ = airborne(stack)
    model.sensor_faults = SensorBit.GPS
    assert model.set_mode(custom_mode(stack, hold)) == REFUSED[stack]
    assert model.return_to_launch() == REFUSED[stack]
    assert model.set_mode(custom_mode(stack, land)) == MavResult.ACCEPTED


def test_unknown_mode_is_invalid() -> None:
    px4, _ = make(Stack.PX4)
    assert px4.set_mode(0x12345678) == MavResult.DENIED
    ardu, _ = make(Stack.ARDUPILOT)
    assert ardu.set_mode(8) == MavResult.FAILED


@pytest.mark.parametrize("stack", list(Stack))
def test_rtl_descends_and_lands_at_home(stack: Stack) -> None:
    model, clock = airborne(stack)
    assert model.return_to_launch() == MavResult.ACCEPTED
    run(model, clock, 3.0)
    assert model.on_ground


def test_idle_armed_on_the_ground_disarms() -> None:
    model, clock = make(Stack.PX4, idle_disarm_s=2.0)
    model.arm(arm=True)
    run(model, clock, 1.5)
    assert model.armed
    run(model, clock, 0.6)
    assert not model.armed


@pytest.mark.parametrize("stack", list(Stack))
def test_critical_sensor_in_flight_reports_critical(stack: Stack) -> None:
    model, _ = airborne(stack)
    model.sensor_faults = SensorBit.ACCEL
    assert model.system_status() is MavState.CRITICAL
    model.sensor_faults = SensorBit.MAG
    assert model.system_status() is MavState.ACTIVE


def test_sensor_bits_per_stack() -> None:
    px4, _ = make(Stack.PX4)
    s = px4.sensors()
    assert s.present == s.enabled
    assert s.enabled & SensorBit.RC_RECEIVER and not s.health & SensorBit.RC_RECEIVER
    assert s.health & SensorBit.GYRO
    px4.sensor_faults = SensorBit.GYRO | SensorBit.GYRO2
    s = px4.sensors()
    assert s.enabled & SensorBit.GYRO2 and not s.health & (SensorBit.GYRO | SensorBit.GYRO2)


@pytest.mark.parametrize("stack", list(Stack))
def test_prearm_bit_tracks_the_arming_checks(stack: Stack) -> None:
    model, _ = make(stack)
    assert model.sensors().health & SensorBit.PREARM_CHECK
    model.sensor_faults = SensorBit.MAG
    assert not model.sensors().health & SensorBit.PREARM_CHECK  # a pre-arm check fails
    model.arm(arm=True, magic=FORCE_DISARM_MAGIC)
    assert model.sensors().health & SensorBit.PREARM_CHECK  # not judged once armed
    model.sensor_faults = SensorBit(0)
    model.reboot()
    assert not model.sensors().health & SensorBit.PREARM_CHECK  # still booting


@pytest.mark.parametrize("stack", list(Stack))
def test_reboot_forgets_the_flight(stack: Stack) -> None:
    model, clock = airborne(stack)
    model.state_override = MavState.CRITICAL
    model.reboot()
    assert (model.armed, model.altitude_m, model.time_boot_ms()) == (False, 0.0, 0)
    booting = {Stack.PX4: MavState.UNINIT, Stack.ARDUPILOT: MavState.BOOT}[stack]
    assert model.system_status() is booting
    clock.now += 1.0
    assert model.system_status() is MavState.STANDBY


@settings(max_examples=60, deadline=None)
@given(
    actions=st.lists(
        st.sampled_from(["arm", "disarm", "takeoff", "land", "hold", "rtl", "wait", "gps"]),
        max_size=25,
    ),
    stack=st.sampled_from(list(Stack)),
)
def test_a_disarmed_vehicle_never_climbs_and_the_landed_state_matches_altitude(
    actions: list[str], stack: Stack
) -> None:
    model, clock = make(stack)
    for action in actions:
        before = model.altitude_m
        if action == "arm":
            model.arm(arm=True)
        elif action == "disarm":
            model.arm(arm=False)
        elif action == "takeoff":
            model.takeoff(math.nan)
        elif action == "land":
            model.land()
        elif action == "hold":
            model.set_mode(custom_mode(stack, "AUTO.LOITER" if stack is Stack.PX4 else "LOITER"))
        elif action == "rtl":
            model.return_to_launch()
        elif action == "gps":
            model.sensor_faults ^= SensorBit.GPS
        run(model, clock, 0.3, dt=0.05)
        assert model.altitude_m >= 0.0
        if not model.armed:
            assert model.altitude_m <= before
        assert not model.on_ground or model.altitude_m == 0.0
        assert (
            model.altitude_m > 0.0
            or model.detecting_landing  # still LANDING / IN_AIR, as the firmware reports
            or model.landed_state in (MavLandedState.ON_GROUND, MavLandedState.TAKEOFF)
        )


def test_fault_values_parse() -> None:
    assert parse_sensor(None) is SensorBit.GYRO
    assert parse_sensor("ahrs") is SensorBit.AHRS
    assert parse_sensor("0x20") is SensorBit.GPS
    with pytest.raises(ValueError):
        parse_sensor("3")  # two bits
    assert parse_state("emergency") is MavState.EMERGENCY
    assert parse_state(None) is MavState.CRITICAL
    with pytest.raises(ValueError):
        parse_state("panic")
    assert parse_number(FaultKind.LOSS, "5", 0.0) == 5.0
    with pytest.raises(ValueError):
        parse_number(FaultKind.LOSS, "150", 0.0)
    with pytest.raises(ValueError):
        parse_number(FaultKind.JITTER, "-1", 0.0)


def _param_set(name: str, value: float, param_type: int) -> Any:
    return mavlink.MAVLink_param_set_message(1, 1, name.encode(), value, param_type)


def test_params_drive_the_config_with_each_stacks_int_encoding() -> None:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    config = SimConfig()
    px4 = ParamStore(Stack.PX4, sysid=7, config=config)
    [reply] = px4.handle(
        _param_set("MIS_TAKEOFF_ALT", 6.0, mavlink.MAV_PARAM_TYPE_REAL32), mav, 1, 1
    )
    assert reply.param_value == 6.0 and config.takeoff_alt_m == 6.0
    read = mavlink.MAVLink_param_request_read_message(1, 1, b"MAV_SYS_ID", -1)
    [value] = px4.handle(read, mav, 1, 1)
    # PX4 copies the int32 bytes into the float field.
    assert struct.unpack("<i", struct.pack("<f", value.param_value))[0] == 7
    ardu = ParamStore(Stack.ARDUPILOT, sysid=7, config=config)
    listing = ardu.handle(mavlink.MAVLink_param_request_list_message(1, 1), mav, 1, 1)
    assert [m.param_id for m in listing] == ardu.names()
    by_name = {m.param_id: m.param_value for m in listing}
    assert by_name["SYSID_THISMAV"] == 7.0  # ArduPilot converts the number
    assert by_name["PILOT_TKOFF_ALT"] == pytest.approx(600.0)
    assert px4.handle(_param_set("NOPE", 1.0, mavlink.MAV_PARAM_TYPE_REAL32), mav, 1, 1) == []
    other = mavlink.MAVLink_param_request_list_message(9, 1)
    assert px4.handle(other, mav, 1, 1) == []


def test_control_requests_are_validated() -> None:
    sim = SimulatedAutopilot.udp(Stack.PX4, 1)  # not started: no socket is opened
    ok = handle_request(sim, {"op": "fault", "kind": "sensor", "value": "accel"})
    assert ok["ok"] and ok["state"]["unhealthy_sensors"] == ["accel"]
    assert handle_request(sim, {"op": "clear", "kind": None})["state"]["faults"] == {}
    assert not handle_request(sim, {"op": "fault", "kind": "meteor"})["ok"]
    assert not handle_request(sim, {"op": "explode"})["ok"]
    assert not handle_request(sim, {"op": "fault", "kind": "state", "value": "panic"})["ok"]


@pytest.mark.parametrize(
    ("kind", "value"),
    [
        ("jitter", "inf"),
        ("jitter", float("inf")),
        ("loss", "nan"),
        ("garbage", 1e12),
        ("reboot", -1),
    ],
)
def test_a_fault_value_that_could_stall_the_link_is_refused_and_changes_nothing(
    kind: str, value: object
) -> None:
    sim = SimulatedAutopilot.udp(Stack.PX4, 1)  # not started: no socket is opened
    answer = handle_request(sim, {"op": "fault", "kind": kind, "value": value})
    assert not answer["ok"] and "out of range" in answer["error"]
    assert handle_request(sim, {"op": "status"})["state"]["faults"] == {}
    assert (sim.link.impairment.jitter_ms, sim.link.impairment.loss_percent) == (0.0, 0.0)


# ---- horizontal flight and position setpoints --------------------------------------------


def _setpoint_mode(model: AutopilotModel, clock: FakeClock, north: float, east: float) -> None:
    """Into the stack's setpoint mode, streaming one target as a client would."""
    mode = "OFFBOARD" if model.stack is Stack.PX4 else "GUIDED"
    model.position_setpoint(north, east, 5.0, None)
    assert model.set_mode(custom_mode(model.stack, mode)) == MavResult.ACCEPTED
    model.position_setpoint(north, east, 5.0, None)


def _stream(model: AutopilotModel, clock: FakeClock, target: tuple[float, float], s: float) -> None:
    for _ in range(round(s / 0.1)):
        model.position_setpoint(*target, 5.0, None)
        run(model, clock, 0.1)


@pytest.mark.parametrize("stack", [Stack.PX4, Stack.ARDUPILOT])
def test_position_setpoints_are_flown_in_the_setpoint_mode(stack: Stack) -> None:
    model, clock = airborne(stack)
    _setpoint_mode(model, clock, 20.0, -10.0)
    _stream(model, clock, (20.0, -10.0), 15.0)
    assert model.horizontal.distance_to(20.0, -10.0) < 0.1
    assert model.altitude_m == pytest.approx(5.0, abs=0.1)


def test_px4_refuses_offboard_without_a_setpoint_stream() -> None:
    model, clock = airborne(Stack.PX4)
    offboard = custom_mode(Stack.PX4, "OFFBOARD")
    assert model.set_mode(offboard) == MavResult.TEMPORARILY_REJECTED
    model.position_setpoint(1.0, 1.0, 3.0, None)
    run(model, clock, 1.5)  # longer than COM_OF_LOSS_T: the stream is stale again
    assert model.set_mode(offboard) == MavResult.TEMPORARILY_REJECTED
    model.position_setpoint(1.0, 1.0, 3.0, None)
    assert model.set_mode(offboard) == MavResult.ACCEPTED


def test_px4_holds_where_it_is_when_the_offboard_stream_stops() -> None:
    model, clock = airborne(Stack.PX4)
    _setpoint_mode(model, clock, 50.0, 0.0)
    _stream(model, clock, (50.0, 0.0), 4.0)
    run(model, clock, 1.2)  # no setpoints for longer than COM_OF_LOSS_T
    assert model.mode == "AUTO.LOITER"
    assert any("offboard" in text for _, text in model.texts)
    stopped_at = model.horizontal.north_m
    run(model, clock, 10.0)
    assert 0.0 < stopped_at < 50.0
    assert model.horizontal.speed_mps == 0.0 and model.horizontal.north_m < 50.0


def test_ardupilot_ignores_setpoints_outside_guided_and_keeps_the_last_one_in_it() -> None:
    model, clock = airborne(Stack.ARDUPILOT)
    assert model.set_mode(custom_mode(Stack.ARDUPILOT, "BRAKE")) == MavResult.ACCEPTED
    model.position_setpoint(30.0, 0.0, 5.0, None)
    run(model, clock, 5.0)
    assert model.horizontal.distance_to(0.0, 0.0) < 0.01  # BRAKE holds
    assert model.set_mode(custom_mode(Stack.ARDUPILOT, "GUIDED")) == MavResult.ACCEPTED
    model.position_setpoint(30.0, 0.0, 5.0, None)
    run(model, clock, 15.0)  # one setpoint, no stream: GUIDED flies to it
    assert model.horizontal.distance_to(30.0, 0.0) < 0.1


@pytest.mark.parametrize("stack", [Stack.PX4, Stack.ARDUPILOT])
def test_rtl_flies_home_at_altitude_then_lands_there(stack: Stack) -> None:
    model, clock = airborne(stack)
    _setpoint_mode(model, clock, 25.0, 25.0)
    _stream(model, clock, (25.0, 25.0), 12.0)
    altitude = model.altitude_m
    assert model.return_to_launch() == MavResult.ACCEPTED
    run(model, clock, 3.0)
    assert model.altitude_m == pytest.approx(altitude, abs=0.2)  # not descending yet
    assert model.horizontal.distance_to(0.0, 0.0) < 25 * math.sqrt(2)
    run(model, clock, 30.0)
    assert model.on_ground and model.horizontal.distance_to(0.0, 0.0) < 0.6


@pytest.mark.parametrize("stack", [Stack.PX4, Stack.ARDUPILOT])
def test_holds_keep_the_position_the_mode_was_entered_at(stack: Stack) -> None:
    model, clock = airborne(stack)
    _setpoint_mode(model, clock, 40.0, 0.0)
    _stream(model, clock, (40.0, 0.0), 3.0)
    hold = custom_mode(stack, "AUTO.LOITER" if stack is Stack.PX4 else "BRAKE")
    assert model.set_mode(hold) == MavResult.ACCEPTED
    entered_at = model.horizontal.north_m
    run(model, clock, 10.0)
    assert model.horizontal.speed_mps == 0.0
    # it brakes from its speed, so it ends a little beyond the entry point, never at 40
    assert entered_at <= model.horizontal.north_m < entered_at + 5.0


def test_a_lagging_vehicle_is_slower_by_the_scale() -> None:
    normal, clock = airborne(Stack.PX4)
    lagging, lag_clock = airborne(Stack.PX4)
    lagging.speed_scale = 0.5
    for model, c in ((normal, clock), (lagging, lag_clock)):
        _setpoint_mode(model, c, 100.0, 0.0)
        _stream(model, c, (100.0, 0.0), 8.0)
    assert lagging.horizontal.north_m < 0.6 * normal.horizontal.north_m
