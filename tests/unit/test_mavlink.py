"""The shared MAVLink tables: values checked against the stacks' published numbers.

The expected numbers come from the MAVLink health reference (PX4 px4_custom_mode.h,
ArduCopter mode.h, common.xml), not from the tables under test, so a typo fails here.
"""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given
from hypothesis import strategies as st

from roost_api.meta import Stack
from roost_api.sitl import sitl_endpoint, sitl_instance
from roost_mavlink import (
    AGENT_COMPONENT_ID,
    FORCE_DISARM_MAGIC,
    MavLandedState,
    ModeIntent,
    SensorBit,
    SensorSeverity,
    api_landed_state,
    classify_sensors,
    custom_mode,
    custom_mode_from_set_mode,
    heartbeat_autopilot,
    hold_modes,
    intent_mode,
    is_manual_mode,
    mav_state_name,
    mode_name,
    pymavlink_device,
    sensor_severity,
    set_mode_params,
    stack_from_heartbeat,
)
from roost_mavlink.modes import mode_names
from roost_mavlink.status import (
    sensor_from_name,
    stack_normally_unhealthy,
    stack_sensors,
)


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("AUTO.LOITER", 0x03040000),
        ("AUTO.LAND", 0x06040000),
        ("AUTO.RTL", 0x05040000),
        ("AUTO.TAKEOFF", 0x02040000),
        ("MANUAL", 0x00010000),
        ("POSCTL", 0x00030000),
        ("OFFBOARD", 0x00060000),
        # PX4 v1.16 px4_custom_mode.h: main 9 SIMPLE (reserved), 10 TERMINATION
        ("SIMPLE", 0x00090000),
        ("TERMINATION", 0x000A0000),
        ("POSCTL.ORBIT", 0x01030000),
        ("POSCTL.SLOW", 0x02030000),
        ("AUTO.VTOL_TAKEOFF", 0x0A040000),
        ("AUTO.EXTERNAL1", 0x0B040000),
        ("AUTO.EXTERNAL8", 0x12040000),
    ],
)
def test_px4_custom_mode_matches_px4_encoding(name: str, value: int) -> None:
    assert custom_mode(Stack.PX4, name) == value
    assert mode_name(Stack.PX4, value) == name


@pytest.mark.parametrize(
    ("name", "number"),
    [
        ("STABILIZE", 0),
        ("ALT_HOLD", 2),
        ("AUTO", 3),
        ("GUIDED", 4),
        ("LOITER", 5),
        ("RTL", 6),
        ("LAND", 9),
        ("POSHOLD", 16),
        ("BRAKE", 17),
        ("THROW", 18),
        ("SMART_RTL", 21),
        ("AUTO_RTL", 27),
        ("TURTLE", 28),
    ],
)
def test_arducopter_mode_numbers(name: str, number: int) -> None:
    assert custom_mode(Stack.ARDUPILOT, name) == number
    assert mode_name(Stack.ARDUPILOT, number) == name


@pytest.mark.parametrize("stack", list(Stack))
def test_every_mode_round_trips_through_do_set_mode(stack: Stack) -> None:
    for name in mode_names(stack):
        p = set_mode_params(stack, name)
        assert custom_mode_from_set_mode(stack, p[0], p[1], p[2]) == custom_mode(stack, name)


def test_do_set_mode_params_per_stack() -> None:
    assert set_mode_params(Stack.PX4, "AUTO.LOITER")[:3] == (1.0, 4.0, 3.0)
    assert set_mode_params(Stack.ARDUPILOT, "LAND")[:3] == (1.0, 9.0, 0.0)


def test_do_set_mode_rejects_missing_flag_and_unknown_modes() -> None:
    with pytest.raises(ValueError, match="CUSTOM_MODE"):
        custom_mode_from_set_mode(Stack.PX4, 0, 4, 3)
    with pytest.raises(ValueError):
        custom_mode_from_set_mode(Stack.ARDUPILOT, 1, 8, 0)  # 8 is unused in ArduCopter
    with pytest.raises(ValueError):
        custom_mode_from_set_mode(Stack.PX4, 1, 4, 0)  # AUTO without a sub mode


def test_unknown_custom_mode_is_named_by_its_numbers() -> None:
    assert mode_name(Stack.ARDUPILOT, 99) == "UNKNOWN(99)"
    assert mode_name(Stack.ARDUPILOT, 8) == "UNKNOWN(8)"  # retired number
    assert mode_name(Stack.PX4, 0x000B0000) == "UNKNOWN(main=11,sub=0)"
    assert mode_name(Stack.PX4, 0x13040000) == "UNKNOWN(main=4,sub=19)"
    assert mode_name(Stack.PX4, 0x00040001) == "UNKNOWN(0x00040001)"  # low bits set
    with pytest.raises(KeyError):
        custom_mode(Stack.PX4, "LOITER")


def test_intents_pick_the_stack_specific_modes() -> None:
    assert intent_mode(Stack.PX4, ModeIntent.HOLD) == "AUTO.LOITER"
    assert intent_mode(Stack.PX4, ModeIntent.LAND) == "AUTO.LAND"
    assert intent_mode(Stack.PX4, ModeIntent.RETURN_TO_LAUNCH) == "AUTO.RTL"
    # ArduCopter's LOITER follows the throttle stick (down without a radio): BRAKE holds
    assert intent_mode(Stack.ARDUPILOT, ModeIntent.HOLD) == "BRAKE"
    assert hold_modes(Stack.ARDUPILOT) == ("BRAKE", "GUIDED")
    assert "LOITER" not in hold_modes(Stack.ARDUPILOT)
    assert hold_modes(Stack.PX4) == ("AUTO.LOITER",)
    assert intent_mode(Stack.ARDUPILOT, ModeIntent.LAND) == "LAND"
    assert intent_mode(Stack.ARDUPILOT, ModeIntent.RETURN_TO_LAUNCH) == "RTL"


def test_manual_modes() -> None:
    assert is_manual_mode(Stack.PX4, "POSCTL")
    assert is_manual_mode(Stack.PX4, "manual")
    assert not is_manual_mode(Stack.PX4, "AUTO.LOITER")
    assert is_manual_mode(Stack.ARDUPILOT, "STABILIZE")
    assert is_manual_mode(Stack.ARDUPILOT, "POSHOLD")
    # The autonomous intents are never pilot modes, or the safety routine would skip itself.
    for stack, intent in itertools.product(Stack, ModeIntent):
        assert not is_manual_mode(stack, intent_mode(stack, intent))


def test_heartbeat_autopilot_values() -> None:
    assert heartbeat_autopilot(Stack.PX4) == 12
    assert heartbeat_autopilot(Stack.ARDUPILOT) == 3
    assert stack_from_heartbeat(12) is Stack.PX4
    assert stack_from_heartbeat(3) is Stack.ARDUPILOT
    assert stack_from_heartbeat(8) is None


def test_state_names() -> None:
    assert mav_state_name(5) == "CRITICAL"
    assert mav_state_name(8) == "FLIGHT_TERMINATION"
    assert mav_state_name(42) == "UNKNOWN(42)"
    assert [api_landed_state(v) for v in range(5)] == [
        "Undefined",
        "OnGround",
        "InAir",
        "Takeoff",
        "Landing",
    ]
    assert api_landed_state(9) == "Undefined"
    assert int(MavLandedState.ON_GROUND) == 1


def test_sensor_bits_and_severity_follow_the_reference_table() -> None:
    assert int(SensorBit.GYRO) == 0x1 and int(SensorBit.AHRS) == 0x200000
    assert int(SensorBit.PREARM_CHECK) == 0x10000000
    assert int(SensorBit.PROPULSION) == 0x40000000
    for critical in (SensorBit.GYRO, SensorBit.ACCEL, SensorBit.AHRS):
        assert sensor_severity(critical) is SensorSeverity.CRITICAL
    for warn in (SensorBit.MAG, SensorBit.GPS, SensorBit.ABSOLUTE_PRESSURE, SensorBit.GYRO2):
        assert sensor_severity(warn) is SensorSeverity.WARN
    for ignored in (SensorBit.PREARM_CHECK, SensorBit.RC_RECEIVER, SensorBit.LOGGING):
        assert sensor_severity(ignored) is SensorSeverity.IGNORE
    assert sensor_from_name("gyro") is SensorBit.GYRO
    with pytest.raises(KeyError):
        sensor_from_name("flux")


def test_classify_sensors_counts_only_enabled_unhealthy_bits() -> None:
    enabled = SensorBit.GYRO | SensorBit.GPS | SensorBit.RC_RECEIVER
    health = SensorBit.MAG  # everything enabled is unhealthy; MAG is not enabled
    report = classify_sensors(int(enabled), int(health))
    assert report.critical == (SensorBit.GYRO,)
    assert report.warn == (SensorBit.GPS,)
    assert report.ignored == (SensorBit.RC_RECEIVER,)
    assert report.unhealthy == (SensorBit.GYRO, SensorBit.GPS)
    assert classify_sensors(int(enabled), int(enabled)).unhealthy == ()


@pytest.mark.parametrize("stack", list(Stack))
def test_a_healthy_stack_reports_nothing_that_counts(stack: Stack) -> None:
    enabled = stack_sensors(stack)
    health = enabled & ~stack_normally_unhealthy(stack)
    assert classify_sensors(int(enabled), int(health)).unhealthy == ()


def test_sitl_ports_follow_px4_and_ardupilot_conventions() -> None:
    px4 = sitl_endpoint(0, 1, Stack.PX4)
    assert (px4.instance, px4.sysid, px4.agent_port, px4.autopilot_port) == (1, 2, 14541, 14581)
    assert px4.connection == "udp://127.0.0.1:14541"
    ardu = sitl_endpoint(1, 0, Stack.ARDUPILOT)
    assert (ardu.instance, ardu.sysid, ardu.autopilot_port) == (4, 5, 5800)


@given(
    a=st.tuples(st.integers(0, 9), st.integers(0, 3), st.sampled_from(list(Stack))),
    b=st.tuples(st.integers(0, 9), st.integers(0, 3), st.sampled_from(list(Stack))),
)
def test_two_distinct_sitl_autopilots_never_collide(
    a: tuple[int, int, Stack], b: tuple[int, int, Stack]
) -> None:
    if a[:2] == b[:2]:
        return
    ea, eb = sitl_endpoint(*a), sitl_endpoint(*b)
    assert ea.sysid != eb.sysid
    ports_a = {ea.agent_port, ea.autopilot_port}
    ports_b = {eb.agent_port, eb.autopilot_port}
    assert not ports_a & ports_b


def test_sitl_rejects_instances_that_would_collide() -> None:
    with pytest.raises(ValueError):
        sitl_instance(0, 4)
    with pytest.raises(ValueError):
        sitl_endpoint(10, 0, Stack.PX4)  # instance 40: 14580 is instance 0's local port


@pytest.mark.parametrize(
    ("url", "device", "baud"),
    [
        ("udp://127.0.0.1:14541", "udpin:127.0.0.1:14541", 57600),
        ("udpin://127.0.0.1:14541", "udpin:127.0.0.1:14541", 57600),
        ("udp://:14541", "udpin:0.0.0.0:14541", 57600),
        ("udpout://10.0.0.2:14550", "udpout:10.0.0.2:14550", 57600),
        ("tcp://127.0.0.1:5760", "tcp:127.0.0.1:5760", 57600),
        ("serial:///dev/ttyUSB0:921600", "/dev/ttyUSB0", 921600),
        ("serial:///dev/pts/3", "/dev/pts/3", 57600),
    ],
)
def test_connection_urls_map_to_pymavlink(url: str, device: str, baud: int) -> None:
    got = pymavlink_device(url)
    assert (got.device, got.baud) == (device, baud)


@pytest.mark.parametrize("url", ["127.0.0.1:14541", "http://x:1", "udp://127.0.0.1"])
def test_bad_connection_urls_are_rejected(url: str) -> None:
    with pytest.raises(ValueError):
        pymavlink_device(url)


def test_agent_identity_constants() -> None:
    assert AGENT_COMPONENT_ID == 191
    assert FORCE_DISARM_MAGIC == 21196
