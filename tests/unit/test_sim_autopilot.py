"""Decision tables of the simulator's calibrated flight behaviour (fake clock, no sockets).

What the real firmware did in the recordings, pinned here so the agent's tests face it:
ArduCopter's LOITER without RC descends into the ground at ~2.45 m/s while BRAKE and
GUIDED hold; ArduCopter stays in GUIDED after a takeoff while PX4 switches itself to
AUTO.LOITER; a battery failure makes PX4 hold 5 s and land, and a shared battery fails
for every autopilot on it. Plus the control socket's and fault values' validation.
"""

from __future__ import annotations

import math

import pytest

from roost_api.meta import Stack
from roost_mavlink import MavResult, custom_mode
from roost_mavlink.status import MavLandedState, MavState, SensorBit
from roost_sim.autopilot import SimulatedAutopilot
from roost_sim.battery import Battery, ChargeState
from roost_sim.control import handle_request
from roost_sim.faults import FaultKind, check_value, parse_number, parse_sensor, parse_state
from roost_sim.model import AutopilotModel, SimConfig


class FakeClock:
    """Monotonic time the test advances by hand."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def run(model: AutopilotModel, clock: FakeClock, seconds: float, dt: float = 0.02) -> None:
    for _ in range(round(seconds / dt)):
        clock.now += dt
        model.step()


def flying(
    stack: Stack, altitude: float = 5.0, battery: Battery | None = None, **config: object
) -> tuple[AutopilotModel, FakeClock]:
    clock = FakeClock()
    model = AutopilotModel(
        stack, SimConfig.fast(takeoff_alt_m=altitude, **config), clock=clock, battery=battery
    )
    if battery is not None:
        battery._clock = clock  # the pack runs on the same fake time
    run(model, clock, 1.0)
    if stack is Stack.ARDUPILOT:
        assert model.set_mode(custom_mode(stack, "GUIDED")) == MavResult.ACCEPTED
    assert model.arm(arm=True) == MavResult.ACCEPTED
    assert model.takeoff(math.nan) == MavResult.ACCEPTED
    run(model, clock, altitude / 2.5 + 0.5)
    assert model.altitude_m == pytest.approx(altitude)
    return model, clock


def test_after_takeoff_px4_holds_in_auto_loiter_and_ardupilot_stays_in_guided() -> None:
    px4, clock = flying(Stack.PX4)
    assert px4.mode == "AUTO.LOITER"
    run(px4, clock, 3.0)
    assert px4.altitude_m == pytest.approx(5.0)
    ardupilot, clock = flying(Stack.ARDUPILOT)
    assert ardupilot.mode == "GUIDED"
    run(ardupilot, clock, 3.0)
    assert ardupilot.altitude_m == pytest.approx(5.0)


# (mode, throttle stick, altitude after 1.5 s: None = on the ground)
LOITER_TABLE = [
    ("BRAKE", None, 5.0),
    ("GUIDED", None, 5.0),
    ("LOITER", 0.5, 5.0),  # centred stick: hold
    ("LOITER", 0.55, 5.0),  # inside the dead zone
    ("ALT_HOLD", 0.5, 5.0),
    ("LOITER", None, 2.5),  # no RC: stick low, 1 s of acceleration, then 2.5 m/s down
    ("POSHOLD", 0.0, 2.5),
    ("LOITER", 1.0, 7.5),  # full up
]


@pytest.mark.parametrize(("mode", "stick", "altitude"), LOITER_TABLE)
def test_ardupilot_holds_and_stick_modes(mode: str, stick: float | None, altitude: float) -> None:
    model, clock = flying(Stack.ARDUPILOT, throttle=stick)
    assert model.set_mode(custom_mode(Stack.ARDUPILOT, mode)) == MavResult.ACCEPTED
    run(model, clock, 1.5)
    assert model.altitude_m == pytest.approx(altitude, abs=0.15)


def test_ardupilot_loiter_without_rc_flies_into_the_ground_as_recorded() -> None:
    """Recorded: 4.95 m -> ground in ~2.5 s, steady ~2.45 m/s, no flare, hit at 2.43 m/s."""
    model, clock = flying(Stack.ARDUPILOT, altitude=4.95, land_detect_s=2.3)
    entered = clock.now
    assert model.set_mode(custom_mode(Stack.ARDUPILOT, "LOITER")) == MavResult.ACCEPTED
    while not model.touchdowns:
        run(model, clock, 0.02)
        assert clock.now - entered < 5.0
    [touchdown] = model.touchdowns
    assert 2.0 <= touchdown.at - entered <= 3.0
    assert touchdown.speed_mps == pytest.approx(2.5, abs=0.1)
    assert touchdown.mode == "LOITER"
    assert any(text.startswith("SIM Hit ground at 2.") for _, text in model.texts)
    # Landing detector: still "in air" for 2.3 s, then landed (STANDBY while armed).
    run(model, clock, 2.0)
    assert model.landed_state is MavLandedState.IN_AIR and model.armed
    run(model, clock, 0.5)
    assert model.on_ground and model.armed
    assert model.system_status() is MavState.STANDBY
    run(model, clock, 10.0)  # DISARM_DELAY
    assert not model.armed


def test_a_stick_brought_back_to_centre_stops_the_descent() -> None:
    model, clock = flying(Stack.ARDUPILOT)
    model.set_mode(custom_mode(Stack.ARDUPILOT, "LOITER"))
    run(model, clock, 1.0)
    model.config.throttle = 0.5
    run(model, clock, 1.5)
    low = model.altitude_m
    run(model, clock, 2.0)
    assert model.altitude_m == pytest.approx(low) and low > 1.0
    assert not model.touchdowns


def test_px4_battery_failsafe_holds_five_seconds_then_lands() -> None:
    battery = Battery()
    model, clock = flying(Stack.PX4, battery=battery)
    battery.fail()
    run(model, clock, 1.0)
    assert model.battery_reading().voltage_mv == 14400
    assert model.system_status() is MavState.ACTIVE  # not empty yet
    run(model, clock, 4.0)
    assert model.battery_reading().charge_state is ChargeState.EMERGENCY
    assert not model.sensors().health & SensorBit.BATTERY
    assert model.system_status() is MavState.CRITICAL and model.mode == "AUTO.LOITER"
    run(model, clock, 5.1)
    assert model.mode == "AUTO.LAND"


def test_ardupilot_battery_failsafe_only_reports_by_default() -> None:
    battery = Battery()
    model, clock = flying(Stack.ARDUPILOT, battery=battery)
    battery.fail()
    run(model, clock, 12.0)
    assert model.system_status() is MavState.CRITICAL
    assert model.mode == "GUIDED" and model.altitude_m == pytest.approx(5.0)
    lands, clock = flying(Stack.ARDUPILOT, battery=Battery(), battery_failsafe_land=True)
    assert lands.battery is not None
    lands.battery._clock = clock
    lands.battery.fail()
    run(lands, clock, 12.0)
    assert lands.mode == "LAND"


@pytest.mark.parametrize(("layout", "standby_fails"), [("shared", True), ("own", False)])
def test_a_battery_fault_reaches_every_autopilot_on_that_battery(
    layout: str, standby_fails: bool
) -> None:
    """Shared pack: switching autopilots does not help, so a failsafe must land instead."""
    pack = Battery()
    active = SimulatedAutopilot.udp(Stack.PX4, 1, battery=pack)
    standby = SimulatedAutopilot.udp(Stack.PX4, 2, battery=pack if layout == "shared" else None)
    active.inject(FaultKind.BATTERY)
    assert active.snapshot().faults == {"battery": "True"}
    assert ("battery" in standby.snapshot().faults) is standby_fails
    active.clear(FaultKind.BATTERY)
    assert not pack.failed and standby.snapshot().faults == {}


CONTROL_TABLE = [
    ({"op": "fault", "kind": "jitter", "value": "inf"}, "out of range"),
    ({"op": "fault", "kind": "jitter", "value": "nan"}, "out of range"),
    ({"op": "fault", "kind": "jitter", "value": 1e12}, "out of range"),
    ({"op": "fault", "kind": "loss", "value": "lots"}, "takes a number"),
    ({"op": "fault", "kind": "garbage", "value": -5}, "out of range"),
    ({"op": "fault", "kind": "reboot", "value": 1e9}, "out of range"),
    ({"op": "fault", "kind": "spoof", "value": 300}, "system id"),
    ({"op": "fault", "kind": "sensor", "value": math.inf}, "whole number"),
    ({"op": "fault", "kind": "state", "value": 99}, "MavState"),
    ({"op": "fault"}, "missing field"),
    ({"op": "throttle", "value": 2}, "between 0 and 1"),
    # a fly request while starting up waits its timeout in real time: tests/integration
    ({"op": "fly", "value": "high", "timeout": 0.05}, "altitude must be a number"),
]


@pytest.mark.parametrize(("request_", "error"), CONTROL_TABLE)
def test_refused_control_requests_are_answered_and_change_nothing(
    request_: dict[str, object], error: str
) -> None:
    sim = SimulatedAutopilot.udp(Stack.ARDUPILOT, 1)  # not started; realistic 41 s boot
    answer = handle_request(sim, request_)
    assert answer["ok"] is False and error in answer["error"]
    assert handle_request(sim, {"op": "status"})["state"]["faults"] == {}
    assert sim.link.impairment.jitter_ms == 0.0


def test_a_refused_fly_explains_itself() -> None:
    sim = SimulatedAutopilot.udp(Stack.ARDUPILOT, 1, config=SimConfig.fast())
    sim.inject(FaultKind.SENSOR, "gyro")
    with pytest.raises(RuntimeError, match="refused"):
        sim._local(400, (1.0, 0, 0, 0, 0, 0, 0))


def test_fault_value_parsers_refuse_what_would_break_the_link() -> None:
    assert parse_number(FaultKind.JITTER, "20", 50.0) == 20.0
    assert parse_number(FaultKind.JITTER, None, 50.0) == 50.0
    for bad in ("inf", "-inf", "nan", "1e7"):
        with pytest.raises(ValueError):
            parse_number(FaultKind.JITTER, bad, 50.0)
    assert parse_number(FaultKind.SPOOF, "42", 1) == 42
    for bad_id in ("0", "256", "4.5", "x"):
        with pytest.raises(ValueError):
            parse_number(FaultKind.SPOOF, bad_id, 1)
    check_value(FaultKind.BATTERY, None)
    with pytest.raises(ValueError):
        check_value(FaultKind.BATTERY, "3")  # takes no value
    assert parse_sensor(32.0) is SensorBit.GPS
    with pytest.raises(ValueError):
        parse_sensor(math.nan)
    assert parse_state(5.0) is MavState.CRITICAL


@pytest.mark.parametrize(
    ("stack", "descent", "detect", "disarm"),
    [(Stack.PX4, 0.7, 7.0, 2.0), (Stack.ARDUPILOT, 0.5, 2.0, 0.5)],
)
def test_realistic_landing_rate_detector_and_disarm(
    stack: Stack, descent: float, detect: float, disarm: float
) -> None:
    model, clock = flying(stack, altitude=2.0, descent_rate_mps=None, land_detect_s=None)
    model.config.fast_boot = False  # booted already; from here on the firmware's landing
    model.config.auto_disarm_after_land_s = None
    assert model.land() == MavResult.ACCEPTED
    started = clock.now
    run(model, clock, 1.0)
    assert model.climb_mps == pytest.approx(-descent)
    while not model.touchdowns:
        run(model, clock, 0.02)
    assert model.touchdowns[0].at - started == pytest.approx(2.0 / descent, abs=0.05)
    assert model.landed_state is MavLandedState.LANDING  # the detector is not sure yet
    run(model, clock, detect - 0.1)
    assert model.landed_state is MavLandedState.LANDING
    run(model, clock, 0.2)
    assert model.on_ground and model.armed
    run(model, clock, disarm + 0.1)
    assert not model.armed
