"""The simulated autopilot on real sockets and a real pseudo-terminal.

Clients here are real MAVLink implementations: pymavlink (the agent's library) and, in
the slow tests, MAVSDK's native library, which was written against real PX4/ArduPilot
and shares no code with the simulator. Rates are measured and checked loosely (the
machine is shared); speed figures belong to the benchmarks.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.action import Action
from mavsdk.plugins.telemetry import Telemetry

from roost_api.autopilot import RedundantAutopilotSpec
from roost_api.meta import Stack
from roost_mavlink import (
    FORCE_DISARM_MAGIC,
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MAV_CMD_NAV_TAKEOFF,
    MAV_CMD_REQUEST_MESSAGE,
    MAV_CMD_SET_MESSAGE_INTERVAL,
    MavResult,
    heartbeat_autopilot,
    intent_mode,
    mode_name,
    pymavlink_device,
    set_mode_params,
)
from roost_mavlink.modes import ModeIntent
from roost_mavlink.status import MAV_AUTOPILOT_INVALID, MavState, SensorBit
from roost_sim import (
    FaultKind,
    SimConfig,
    SimulatedAutopilot,
    autopilot_specs,
    free_udp_port,
    message_id,
    start_vehicle_sims,
    stop_sims,
)
from roost_sim.main import build_parser, build_sims, vehicle_entries
from roost_sim.main import main as sim_cli
from tests.support.waiting import wait_until

os.environ.setdefault("MAVLINK20", "1")  # before mavutil is imported: the sims speak MAVLink 2
from pymavlink import mavutil

if getattr(mavutil.mavlink, "WIRE_PROTOCOL_VERSION", "2.0") != "2.0":
    mavutil.set_dialect(mavutil.current_dialect)  # mavutil was imported before the env was set

NAN = math.nan
STACKS = list(Stack)
FAST = SimConfig.fast()
BOOTING = {Stack.PX4: MavState.UNINIT, Stack.ARDUPILOT: MavState.BOOT}
# What a ground station asks ArduPilot for (it streams nothing else unasked).
GCS_RATES = {
    "ATTITUDE": 50.0,
    "GLOBAL_POSITION_INT": 10.0,
    "SYS_STATUS": 5.0,
    "EXTENDED_SYS_STATE": 5.0,
    "SYSTEM_TIME": 1.0,
}
# PX4's onboard link, unasked.
PX4_RATES = {
    "HEARTBEAT": 1.0,
    "ATTITUDE": 100.0,
    "GLOBAL_POSITION_INT": 50.0,
    "HIGHRES_IMU": 50.0,
    "SYS_STATUS": 5.0,
    "EXTENDED_SYS_STATE": 5.0,
    "SYSTEM_TIME": 1.0,
}


class Client:
    """A pymavlink connection that records every message, the way a GCS would."""

    def __init__(self, device: str, baud: int = 57600) -> None:
        self.conn = mavutil.mavlink_connection(
            device, baud=baud, source_system=245, source_component=190
        )

    def close(self) -> None:
        self.conn.close()

    def collect(self, seconds: float) -> list[tuple[float, Any]]:
        """(arrival monotonic time, message) for everything valid that arrives."""
        out: list[tuple[float, Any]] = []
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            msg = self.conn.recv_match(blocking=True, timeout=min(left, 0.1))
            if msg is not None and msg.get_type() != "BAD_DATA":
                out.append((time.monotonic(), msg))
        return out

    def drain(self) -> None:
        """Discard what is already queued in the socket (older than the next event)."""
        while self.conn.recv_match(blocking=False) is not None:
            pass

    def wait_for(self, kind: str, cond: Callable[[Any], bool], timeout: float = 5.0) -> Any:
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            msg = self.conn.recv_match(type=kind, blocking=True, timeout=min(left, 0.2))
            if msg is not None and cond(msg):
                return msg
        raise AssertionError(f"no {kind} matching the condition within {timeout}s")

    def command(self, sysid: int, command: int, *params: float, timeout: float = 2.0) -> int:
        """Send COMMAND_LONG and return the COMMAND_ACK result for it.

        Drains first: at PX4's ~400 datagrams/s a socket nobody read for ~0.6 s is full
        and would drop the ACK (a real ground station reads continuously).
        """
        self.drain()
        padded = [*params, *([0.0] * (7 - len(params)))]
        self.conn.mav.command_long_send(sysid, 1, command, 0, *padded)
        ack = self.wait_for("COMMAND_ACK", lambda m: m.command == command, timeout)
        return int(ack.result)

    def command_unanswered(self, sysid: int, command: int, wait: float = 1.0) -> bool:
        self.conn.mav.command_long_send(sysid, 1, command, 0, 0, 0, 0, 0, 0, 0, 0)
        try:
            self.wait_for("COMMAND_ACK", lambda m: m.command == command, wait)
        except AssertionError:
            return True
        return False


@pytest.fixture
def udp_sim(request: pytest.FixtureRequest) -> Iterator[tuple[SimulatedAutopilot, Client]]:
    """A sim streaming to a listening client, like the agent's ``udp://`` links."""
    stack = getattr(request, "param", Stack.PX4)
    port = free_udp_port()
    client = Client(pymavlink_device(f"udp://127.0.0.1:{port}").device)
    sim = SimulatedAutopilot.udp(stack, 7, target_port=port, config=FAST).start()
    try:
        # Booted (STANDBY): from here on commands behave as on a ready autopilot.
        client.wait_for("HEARTBEAT", lambda m: m.system_status == MavState.STANDBY)
        sim.wait_ready()
        if stack is Stack.ARDUPILOT:
            request_streams(client, sim.sysid)
        yield sim, client
    finally:
        sim.stop()
        client.close()


def request_streams(client: Client, sysid: int, rates: dict[str, float] | None = None) -> None:
    """SET_MESSAGE_INTERVAL for each stream, as a ground station does on ArduPilot."""
    for name, hz in (rates or GCS_RATES).items():
        interval = MAV_CMD_SET_MESSAGE_INTERVAL
        assert client.command(sysid, interval, message_id(name), 1e6 / hz) == MavResult.ACCEPTED


def by_type(messages: list[tuple[float, Any]], sysid: int | None = None) -> Counter[str]:
    return Counter(m.get_type() for _, m in messages if sysid is None or m.get_srcSystem() == sysid)


def fly(client: Client, stack: Stack, sysid: int) -> None:
    if stack is Stack.ARDUPILOT:
        guided = set_mode_params(stack, "GUIDED")
        assert client.command(sysid, MAV_CMD_DO_SET_MODE, *guided) == MavResult.ACCEPTED
    assert client.command(sysid, MAV_CMD_COMPONENT_ARM_DISARM, 1) == MavResult.ACCEPTED
    takeoff = (0, 0, 0, NAN, NAN, NAN, NAN if stack is Stack.PX4 else 2.5)
    assert client.command(sysid, MAV_CMD_NAV_TAKEOFF, *takeoff) == MavResult.ACCEPTED


# ---- streams and identity -------------------------------------------------------------


@pytest.mark.parametrize("udp_sim", STACKS, indirect=True)
def test_streams_arrive_at_roughly_their_rates(
    udp_sim: tuple[SimulatedAutopilot, Client],
) -> None:
    sim, client = udp_sim
    seconds = 3.0
    counts = by_type(client.collect(seconds), sim.sysid)
    rates = {kind: n / seconds for kind, n in counts.items()}
    expected = PX4_RATES if sim.stack is Stack.PX4 else {"HEARTBEAT": 1.0, **GCS_RATES}
    # Loose bounds: the 2-core machine is shared; calibration is test_sim_calibration's.
    for kind, hz in expected.items():
        assert 0.5 * hz <= rates.get(kind, 0.0) <= 1.6 * hz + 0.5, kind


@pytest.mark.parametrize("udp_sim", STACKS, indirect=True)
def test_heartbeat_and_sys_status_follow_the_stack(
    udp_sim: tuple[SimulatedAutopilot, Client],
) -> None:
    sim, client = udp_sim
    hb = client.wait_for("HEARTBEAT", lambda m: m.system_status == MavState.STANDBY)
    assert hb.autopilot == heartbeat_autopilot(sim.stack)
    assert hb.type == mavutil.mavlink.MAV_TYPE_QUADROTOR
    assert mode_name(sim.stack, hb.custom_mode) == sim.snapshot().mode
    status = client.wait_for("SYS_STATUS", lambda m: True)
    assert status.onboard_control_sensors_enabled & SensorBit.GYRO
    assert status.onboard_control_sensors_health & SensorBit.GYRO
    rc_healthy = bool(status.onboard_control_sensors_health & SensorBit.RC_RECEIVER)
    assert rc_healthy is (sim.stack is Stack.ARDUPILOT)  # PX4 SITL has no RC


def test_a_client_that_talks_first_is_answered_and_streamed_to() -> None:
    with SimulatedAutopilot.udp(Stack.PX4, 3, config=FAST) as sim:  # no target: udpout:// clients
        assert sim.connection.startswith("udpout://127.0.0.1:")
        client = Client(pymavlink_device(sim.connection).device)
        try:
            client.conn.mav.heartbeat_send(6, MAV_AUTOPILOT_INVALID, 0, 0, 0)
            client.wait_for("HEARTBEAT", lambda m: m.system_status == MavState.STANDBY)
            sim.wait_ready()
            assert client.command(3, MAV_CMD_COMPONENT_ARM_DISARM, 1) == MavResult.ACCEPTED
        finally:
            client.close()


def test_serial_pseudo_terminal_link() -> None:
    with SimulatedAutopilot.pty(Stack.ARDUPILOT, 4, config=FAST) as sim:
        assert sim.connection == f"serial://{sim.device}:57600"
        device = pymavlink_device(sim.connection)
        client = Client(device.device, device.baud)
        try:
            request_streams(client, 4)
            counts = by_type(client.collect(1.5), 4)
            assert counts["HEARTBEAT"] >= 1 and counts["ATTITUDE"] >= 30
            sim.wait_ready()
            fly(client, Stack.ARDUPILOT, 4)
            sim.wait_until(lambda s: s.landed_state == "InAir", timeout=5)
            assert client.command(4, MAV_CMD_NAV_LAND) == MavResult.ACCEPTED
            sim.wait_until(lambda s: not s.armed, timeout=8)
        finally:
            client.close()


# ---- commands -------------------------------------------------------------------------


@pytest.mark.parametrize("udp_sim", STACKS, indirect=True)
def test_arm_takeoff_hold_land_over_the_wire(udp_sim: tuple[SimulatedAutopilot, Client]) -> None:
    sim, client = udp_sim
    stack = sim.stack
    fly(client, stack, sim.sysid)
    client.wait_for("EXTENDED_SYS_STATE", lambda m: m.landed_state == 2, timeout=5)  # in air
    position = client.wait_for("GLOBAL_POSITION_INT", lambda m: m.relative_alt > 2000)
    assert position.relative_alt == pytest.approx(2500, abs=100)
    hold = intent_mode(stack, ModeIntent.HOLD)
    params = set_mode_params(stack, hold)
    assert client.command(sim.sysid, MAV_CMD_DO_SET_MODE, *params) == MavResult.ACCEPTED
    client.wait_for("HEARTBEAT", lambda m: mode_name(stack, m.custom_mode) == hold)
    assert client.command(sim.sysid, MAV_CMD_NAV_LAND) == MavResult.ACCEPTED
    client.wait_for("EXTENDED_SYS_STATE", lambda m: m.landed_state == 4)  # landing
    client.wait_for("EXTENDED_SYS_STATE", lambda m: m.landed_state == 1, timeout=6)
    client.wait_for(
        "HEARTBEAT", lambda m: not m.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    )
    modes = [change.mode for change in sim.mode_history]
    assert modes[-2:] == [hold, intent_mode(stack, ModeIntent.LAND)]
    names = [c.name for c in sim.commands]
    assert names[-2:] == ["MAV_CMD_DO_SET_MODE", "MAV_CMD_NAV_LAND"]
    assert sim.commands[-1].source == (245, 190)


@pytest.mark.parametrize("udp_sim", STACKS, indirect=True)
def test_refusals_use_each_stacks_result_codes(udp_sim: tuple[SimulatedAutopilot, Client]) -> None:
    sim, client = udp_sim
    refused = MavResult.TEMPORARILY_REJECTED if sim.stack is Stack.PX4 else MavResult.FAILED
    sim.inject(FaultKind.SENSOR, "gyro")
    assert client.command(sim.sysid, MAV_CMD_COMPONENT_ARM_DISARM, 1) == refused
    sim.clear()
    fly(client, sim.stack, sim.sysid)
    sim.wait_until(lambda s: s.landed_state == "InAir")
    assert client.command(sim.sysid, MAV_CMD_COMPONENT_ARM_DISARM, 0) == refused
    sim.inject(FaultKind.SENSOR, "gps")
    assert client.command(sim.sysid, MAV_CMD_NAV_RETURN_TO_LAUNCH) == refused
    force = (0, FORCE_DISARM_MAGIC)
    assert client.command(sim.sysid, MAV_CMD_COMPONENT_ARM_DISARM, *force) == MavResult.ACCEPTED
    sim.wait_until(lambda s: s.landed_state == "OnGround" and not s.armed)
    assert client.command(sim.sysid, 31000) == MavResult.UNSUPPORTED  # a user command


@pytest.mark.parametrize("udp_sim", [Stack.PX4], indirect=True)
def test_message_interval_and_request_message(udp_sim: tuple[SimulatedAutopilot, Client]) -> None:
    sim, client = udp_sim
    attitude = message_id("ATTITUDE")
    assert client.command(sim.sysid, MAV_CMD_SET_MESSAGE_INTERVAL, attitude, 1e5) == 0
    counts = by_type(client.collect(2.0), sim.sysid)
    assert 10 <= counts["ATTITUDE"] <= 30  # 10 Hz now
    assert client.command(sim.sysid, MAV_CMD_SET_MESSAGE_INTERVAL, attitude, -1) == 0
    time.sleep(0.1)  # frames already on the way; then nothing arrives for 1 s
    assert by_type(client.collect(1.0), sim.sysid)["ATTITUDE"] == 0
    heartbeat = message_id("HEARTBEAT")
    assert client.command(sim.sysid, MAV_CMD_SET_MESSAGE_INTERVAL, heartbeat, 1e5) == 2
    version = message_id("AUTOPILOT_VERSION")
    assert client.command(sim.sysid, MAV_CMD_REQUEST_MESSAGE, version) == 0
    reply = client.wait_for("AUTOPILOT_VERSION", lambda m: m.get_srcSystem() == sim.sysid)
    assert reply.capabilities & mavutil.mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert client.command(sim.sysid, MAV_CMD_REQUEST_MESSAGE, 9999) == MavResult.DENIED


def test_commands_for_another_system_are_ignored(
    udp_sim: tuple[SimulatedAutopilot, Client],
) -> None:
    sim, client = udp_sim
    assert client.command_unanswered(sim.sysid + 1, MAV_CMD_COMPONENT_ARM_DISARM)
    assert not sim.snapshot().armed and sim.commands == []


# ---- faults, each seen on the wire ----------------------------------------------------


def test_fault_silence(udp_sim: tuple[SimulatedAutopilot, Client]) -> None:
    sim, client = udp_sim
    sim.inject(FaultKind.SILENCE)
    time.sleep(0.05)  # frames already on the way; then nothing arrives for 1 s
    client.drain()
    assert by_type(client.collect(1.0), sim.sysid) == Counter()
    assert client.command_unanswered(sim.sysid, MAV_CMD_COMPONENT_ARM_DISARM, wait=0.5)
    sim.clear(FaultKind.SILENCE)
    assert by_type(client.collect(0.5), sim.sysid)["ATTITUDE"] > 5


def test_fault_freeze_repeats_values(udp_sim: tuple[SimulatedAutopilot, Client]) -> None:
    sim, client = udp_sim
    sim.inject(FaultKind.FREEZE)
    time.sleep(0.05)  # frames sent before the freeze are drained, not counted
    client.drain()
    received = client.collect(1.0)
    attitudes = [m for _, m in received if m.get_type() == "ATTITUDE"]
    assert len(attitudes) > 25  # the stream keeps its rate...
    values = {(m.time_boot_ms, m.roll, m.pitch, m.yaw) for m in attitudes}
    assert len(values) == 1  # ...but every sample is the same
    times = {m.time_boot_ms for _, m in received if m.get_type() == "SYSTEM_TIME"}
    assert len(times) <= 1
    assert client.command_unanswered(sim.sysid, MAV_CMD_COMPONENT_ARM_DISARM, wait=0.5)
    sim.clear(FaultKind.FREEZE)
    after = [m for _, m in client.collect(0.5) if m.get_type() == "ATTITUDE"]
    assert len({m.time_boot_ms for m in after}) > 5


def test_fault_sensor_bit(udp_sim: tuple[SimulatedAutopilot, Client]) -> None:
    sim, client = udp_sim
    sim.inject(FaultKind.SENSOR, "gyro")
    status = client.wait_for(
        "SYS_STATUS", lambda m: not m.onboard_control_sensors_health & SensorBit.GYRO
    )
    assert status.onboard_control_sensors_enabled & SensorBit.GYRO
    assert status.onboard_control_sensors_present & SensorBit.GYRO
    sim.clear()
    client.wait_for("SYS_STATUS", lambda m: m.onboard_control_sensors_health & SensorBit.GYRO)


@pytest.mark.parametrize("state", ["CRITICAL", "EMERGENCY"])
def test_fault_mav_state(udp_sim: tuple[SimulatedAutopilot, Client], state: str) -> None:
    sim, client = udp_sim
    sim.inject(FaultKind.STATE, state)
    client.wait_for("HEARTBEAT", lambda m: m.system_status == MavState[state], timeout=3)
    sim.clear(FaultKind.STATE)
    client.wait_for("HEARTBEAT", lambda m: m.system_status == MavState.STANDBY, timeout=3)


@pytest.mark.parametrize("udp_sim", STACKS, indirect=True)
def test_fault_reboot_in_flight(udp_sim: tuple[SimulatedAutopilot, Client]) -> None:
    sim, client = udp_sim
    fly(client, sim.stack, sim.sysid)
    sim.wait_until(lambda s: s.landed_state == "InAir")
    before = client.wait_for("ATTITUDE", lambda m: True).time_boot_ms
    sim.inject(FaultKind.REBOOT, 0.3)
    booting = BOOTING[sim.stack]
    boot = client.wait_for("HEARTBEAT", lambda m: m.system_status == booting, timeout=3)
    assert not boot.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    if sim.stack is Stack.ARDUPILOT:
        request_streams(client, sim.sysid)  # a reboot forgets every stream request
    after = client.wait_for("ATTITUDE", lambda m: True).time_boot_ms
    assert after < before and after < 1000  # time_boot_ms went backwards
    client.wait_for("HEARTBEAT", lambda m: m.system_status == MavState.STANDBY, timeout=3)


def test_fault_garbage_is_seen_and_valid_frames_still_arrive(
    udp_sim: tuple[SimulatedAutopilot, Client],
) -> None:
    sim, client = udp_sim
    errors_before = client.conn.mav.total_receive_errors
    sim.inject(FaultKind.GARBAGE, 4000)
    counts = by_type(client.collect(1.0), sim.sysid)
    assert client.conn.mav.total_receive_errors > errors_before
    assert counts["ATTITUDE"] > 10


def test_fault_packet_loss(udp_sim: tuple[SimulatedAutopilot, Client]) -> None:
    sim, client = udp_sim
    baseline = by_type(client.collect(1.0), sim.sysid)["ATTITUDE"]
    sim.inject(FaultKind.LOSS, 60)
    lossy = by_type(client.collect(1.0), sim.sysid)["ATTITUDE"]
    assert 0 < lossy < 0.75 * baseline


def test_fault_jitter_delays_frames_in_order(udp_sim: tuple[SimulatedAutopilot, Client]) -> None:
    sim, client = udp_sim

    def lateness(seconds: float) -> list[float]:
        samples = [(t, m) for t, m in client.collect(seconds) if m.get_type() == "ATTITUDE"]
        # Arrival time minus the autopilot's own timestamp: constant on a perfect link.
        return [t - m.time_boot_ms / 1000.0 for t, m in samples]

    base = lateness(1.0)
    sim.inject(FaultKind.JITTER, 200)
    time.sleep(0.3)  # frames sent before the fault drain first; a measurement window, not a wait
    jittery = lateness(1.5)
    # The unimpaired spread is read between the 10th and 90th percentiles: a loaded
    # machine stalls the odd frame for 100 ms, which says nothing about the link.
    deciles = statistics.quantiles(base, n=10)
    assert max(jittery) - min(jittery) > 0.1 > deciles[-1] - deciles[0]
    in_order = [m.time_boot_ms for _, m in client.collect(0.5) if m.get_type() == "ATTITUDE"]
    assert in_order == sorted(in_order)


def test_fault_spoofed_sysid_and_component(udp_sim: tuple[SimulatedAutopilot, Client]) -> None:
    sim, client = udp_sim
    sim.inject(FaultKind.SPOOF, 42)
    received = [m for _, m in client.collect(1.0) if m.get_type() == "HEARTBEAT"]
    foreign = [m for m in received if m.get_srcSystem() == 42]
    gimbal = [m for m in received if m.get_srcSystem() == sim.sysid and m.get_srcComponent() != 1]
    assert foreign and foreign[0].system_status == MavState.EMERGENCY
    assert gimbal and gimbal[0].autopilot == MAV_AUTOPILOT_INVALID
    own = [m for m in received if m.get_srcSystem() == sim.sysid and m.get_srcComponent() == 1]
    assert all(m.system_status == MavState.STANDBY for m in own)


# ---- each stack's link conventions ----------------------------------------------------


def test_ardupilot_streams_only_what_is_requested_and_forgets_it_on_reboot() -> None:
    port = free_udp_port()
    client = Client(pymavlink_device(f"udp://127.0.0.1:{port}").device)
    try:
        with SimulatedAutopilot.udp(Stack.ARDUPILOT, 5, target_port=port, config=FAST) as sim:
            unasked = set(by_type(client.collect(1.0), 5))
            assert "HEARTBEAT" in unasked
            assert unasked <= {"HEARTBEAT", "TIMESYNC", "GPS_GLOBAL_ORIGIN", "HOME_POSITION"}
            extra1 = mavutil.mavlink.MAV_DATA_STREAM_EXTRA1
            client.conn.mav.request_data_stream_send(5, 1, extra1, 20, 1)
            counts = by_type(client.collect(1.0), 5)
            assert 10 <= counts["ATTITUDE"] <= 30 and counts["SYS_STATUS"] == 0
            client.conn.mav.request_data_stream_send(5, 1, extra1, 0, 0)
            time.sleep(0.1)
            client.drain()
            assert by_type(client.collect(0.5), 5)["ATTITUDE"] == 0
            request_streams(client, 5, {"ATTITUDE": 20.0})
            sim.inject(FaultKind.REBOOT, 0.0)
            client.wait_for("HEARTBEAT", lambda m: m.system_status == MavState.BOOT)
            time.sleep(0.1)
            client.drain()
            assert by_type(client.collect(0.5), 5)["ATTITUDE"] == 0
    finally:
        client.close()


@pytest.mark.parametrize("udp_sim", STACKS, indirect=True)
def test_a_mode_change_is_heard_at_once_on_ardupilot_and_at_the_next_second_on_px4(
    udp_sim: tuple[SimulatedAutopilot, Client],
) -> None:
    sim, client = udp_sim
    mode = "ALT_HOLD" if sim.stack is Stack.ARDUPILOT else "AUTO.LAND"
    last_beat = client.wait_for("HEARTBEAT", lambda m: True)
    assert last_beat is not None
    beat_at = time.monotonic()
    params = set_mode_params(sim.stack, mode)
    assert client.command(sim.sysid, MAV_CMD_DO_SET_MODE, *params) == MavResult.ACCEPTED
    changed_at = time.monotonic()
    client.wait_for("HEARTBEAT", lambda m: mode_name(sim.stack, m.custom_mode) == mode)
    seen_at = time.monotonic()
    if sim.stack is Stack.ARDUPILOT:
        assert seen_at - changed_at < 0.3
    else:
        assert seen_at - beat_at > 0.8  # the regular 1 Hz heartbeat, not an extra one


@pytest.mark.parametrize("udp_sim", [Stack.PX4], indirect=True)
def test_px4_refuses_a_heartbeat_interval_and_ignores_data_stream_requests(
    udp_sim: tuple[SimulatedAutopilot, Client],
) -> None:
    sim, client = udp_sim
    heartbeat = message_id("HEARTBEAT")
    result = client.command(sim.sysid, MAV_CMD_SET_MESSAGE_INTERVAL, heartbeat, 1e5)
    assert result == MavResult.DENIED
    client.conn.mav.request_data_stream_send(sim.sysid, 1, 0, 1, 0)  # "stop everything"
    time.sleep(0.2)
    counts = by_type(client.collect(1.0), sim.sysid)
    assert counts["HEARTBEAT"] <= 2 and counts["ATTITUDE"] > 50


def test_ardupilot_texts_only_after_hearing_the_link_and_refuses_to_arm_until_gps() -> None:
    port = free_udp_port()
    client = Client(pymavlink_device(f"udp://127.0.0.1:{port}").device)
    try:
        with SimulatedAutopilot.udp(Stack.ARDUPILOT, 6, target_port=port) as sim:  # real timing
            client.wait_for("HEARTBEAT", lambda m: m.system_status == MavState.STANDBY)
            assert by_type(client.collect(0.5), 6)["STATUSTEXT"] == 0  # never heard anyone
            refused = client.command(6, MAV_CMD_COMPONENT_ARM_DISARM, 1)
            assert refused == MavResult.FAILED
            text = client.wait_for("STATUSTEXT", lambda m: m.text.startswith("Arm:"))
            assert text.text == "Arm: AHRS: waiting for home" and text.severity == 2
            assert not sim.snapshot().ready
    finally:
        client.close()


def test_ardupilot_routes_other_systems_traffic_onto_the_link_and_px4_does_not() -> None:
    ports = {stack: free_udp_port() for stack in STACKS}
    clients = {s: Client(pymavlink_device(f"udp://127.0.0.1:{p}").device) for s, p in ports.items()}
    config = SimConfig.fast(gcs_heartbeat=True)
    sims = [
        SimulatedAutopilot.udp(stack, 1, target_port=ports[stack], config=config).start()
        for stack in STACKS
    ]
    companion = mavutil.mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    text = companion.statustext_encode(4, b"companion: low disk", 0, 0).pack(companion)
    try:
        for sim in sims:
            sim.route(text)
        seen = {s: clients[s].collect(1.5) for s in STACKS}
    finally:
        stop_sims(sims)
        for client in clients.values():
            client.close()
    ardupilot = [m for _, m in seen[Stack.ARDUPILOT]]
    gcs = [m for m in ardupilot if m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 255]
    assert gcs and gcs[0].type == mavutil.mavlink.MAV_TYPE_GCS
    assert any(m.get_type() == "STATUSTEXT" and m.get_srcComponent() == 191 for m in ardupilot)
    px4 = [m for _, m in seen[Stack.PX4]]
    assert not [m for m in px4 if m.get_srcSystem() == 255 or m.get_srcComponent() == 191]


def altitudes_mm(client: Client, seconds: float) -> list[int]:
    """GLOBAL_POSITION_INT relative altitudes (mm) received over ``seconds``."""
    frames = client.collect(seconds)
    return [m.relative_alt for _, m in frames if m.get_type() == "GLOBAL_POSITION_INT"]


def set_ardupilot_mode(client: Client, sim: SimulatedAutopilot, mode: str) -> None:
    params = set_mode_params(Stack.ARDUPILOT, mode)
    assert client.command(sim.sysid, MAV_CMD_DO_SET_MODE, *params) == MavResult.ACCEPTED


def _airborne_ardupilot(client: Client, sim: SimulatedAutopilot, altitude: float) -> None:
    set_ardupilot_mode(client, sim, "GUIDED")
    assert client.command(sim.sysid, MAV_CMD_COMPONENT_ARM_DISARM, 1) == MavResult.ACCEPTED
    takeoff = (0, 0, 0, NAN, NAN, NAN, altitude)
    assert client.command(sim.sysid, MAV_CMD_NAV_TAKEOFF, *takeoff) == MavResult.ACCEPTED
    sim.wait_until(lambda s: s.altitude_m >= altitude - 0.01, timeout=10)
    assert sim.snapshot().mode == "GUIDED"  # it stays in GUIDED after the takeoff


@pytest.mark.parametrize("udp_sim", [Stack.ARDUPILOT], indirect=True)
def test_ardupilot_loiter_without_rc_flies_into_the_ground(
    udp_sim: tuple[SimulatedAutopilot, Client],
) -> None:
    """The recorded crash: LOITER with no pilot follows a low stick down at ~2.5 m/s."""
    sim, client = udp_sim
    _airborne_ardupilot(client, sim, 5.0)
    set_ardupilot_mode(client, sim, "LOITER")
    descending = client.wait_for("GLOBAL_POSITION_INT", lambda m: m.vz > 200, timeout=3)
    assert descending.relative_alt > 1000
    hit = client.wait_for("STATUSTEXT", lambda m: m.text.startswith("SIM Hit ground"), timeout=5)
    assert 2.3 <= float(hit.text.split()[-2]) <= 2.6
    assert sim.touchdowns[-1].mode == "LOITER" and sim.snapshot().armed


@pytest.mark.parametrize("udp_sim", [Stack.ARDUPILOT], indirect=True)
def test_ardupilot_brake_holds_and_a_centred_rc_stick_holds_loiter(
    udp_sim: tuple[SimulatedAutopilot, Client],
) -> None:
    sim, client = udp_sim
    _airborne_ardupilot(client, sim, 4.0)
    set_ardupilot_mode(client, sim, "BRAKE")
    altitudes = altitudes_mm(client, 1.5)
    assert max(altitudes) - min(altitudes) < 50  # millimetres
    centre = [65535, 65535, 1500, *([65535] * 5)]
    client.conn.mav.rc_channels_override_send(sim.sysid, 1, *centre)
    set_ardupilot_mode(client, sim, "LOITER")
    altitudes = altitudes_mm(client, 1.5)
    assert max(altitudes) - min(altitudes) < 50 and not sim.touchdowns


# ---- helpers for the agent and benchmarks, and the CLI ---------------------------------


def test_start_vehicle_sims_gives_unique_ids_ports_and_valid_specs() -> None:
    sims = start_vehicle_sims([Stack.PX4, Stack.ARDUPILOT, Stack.PX4])
    try:
        assert [s.name for s in sims] == ["fc1", "fc2", "fc3"]
        assert len({s.sysid for s in sims}) == 3
        assert len({s.connection for s in sims}) == 3
        specs = autopilot_specs(sims)
        RedundantAutopilotSpec(vehicle_name="v1", autopilots=specs, primary="fc1")
        for sim in sims:  # each one streams to its own agent port
            client = Client(pymavlink_device(sim.connection).device)
            try:
                hb = client.wait_for("HEARTBEAT", lambda m: True)
                assert hb.get_srcSystem() == sim.sysid
                assert hb.autopilot == heartbeat_autopilot(sim.stack)
            finally:
                client.close()
    finally:
        stop_sims(sims)


def test_vehicle_sims_with_heartbeats_only() -> None:
    quiet = {message_id(name): 0.0 for name in PX4_RATES if name != "HEARTBEAT"}
    quiet |= {message_id(name): 0.0 for name in ("ATTITUDE_QUATERNION", "LOCAL_POSITION_NED")}
    sims = start_vehicle_sims([Stack.PX4], rates=quiet, config=FAST)
    client = Client(pymavlink_device(sims[0].connection).device)
    try:
        counts = by_type(client.collect(1.5), sims[0].sysid)
        assert counts["HEARTBEAT"] >= 1
        assert not set(counts) & {*PX4_RATES, "ATTITUDE_QUATERNION"} - {"HEARTBEAT"}
    finally:
        client.close()
        stop_sims(sims)


def test_cli_run_fault_status_clear(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``roost-sim run`` in its own process; fault/status/clear through the CLI entry point
    in this one (same code as the console script, without paying interpreter start-up)."""
    monkeypatch.setenv("ROOST_SIM_STATE_DIR", str(tmp_path))
    port = free_udp_port()
    client = Client(pymavlink_device(f"udp://127.0.0.1:{port}").device)
    run = [sys.executable, "-m", "roost_sim.main", "run", "--stack", "ardupilot"]
    proc = subprocess.Popen(
        [*run, "--sysid", "9", "--name", "fcx", "--udp-out", f"127.0.0.1:{port}"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        started = json.loads(proc.stdout.readline())
        assert started["connection"] == f"udp://127.0.0.1:{port}" and started["sysid"] == 9
        client.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() == 9)

        def cli(*args: str) -> tuple[int, dict[str, Any]]:
            code = sim_cli(list(args))
            out = capsys.readouterr().out
            return code, json.loads(out) if out.strip() else {}

        assert cli("fault", "fcx", "state", "--value", "EMERGENCY")[0] == 0
        client.wait_for("HEARTBEAT", lambda m: m.system_status == MavState.EMERGENCY)
        code, answer = cli("status", "fcx")
        assert code == 0 and answer["state"]["faults"] == {"state": "EMERGENCY"}
        assert answer["state"]["stack"] == "ardupilot"
        assert cli("clear", "all")[0] == 0
        client.wait_for("HEARTBEAT", lambda m: m.system_status == MavState.STANDBY)
        assert cli("fault", "fcx", "state", "--value", "PANIC")[0] == 1
        assert cli("status", "nobody")[0] == 2
        # Refused requests are answered and leave the autopilot and its socket working.
        code, answer = cli("fly", "fcx", "--wait", "0.2")  # still waiting for GPS
        assert code == 1 and "starting up" in answer["error"]
        code, answer = cli("fault", "fcx", "jitter", "--value", "inf")
        assert code == 1 and "out of range" in answer["error"]
        assert cli("fault", "fcx", "jitter", "--value", "20")[0] == 0
        assert cli("clear", "fcx", "jitter")[0] == 0
        code, answer = cli("status", "fcx")
        assert code == 0 and answer["state"]["faults"] == {}
        client.drain()
        client.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() == 9)
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        client.close()
    assert proc.returncode == 0
    assert not list(tmp_path.glob("*.sock"))  # the control socket is removed on exit


def test_cli_config_file_starts_several_autopilots(tmp_path: Path) -> None:
    port = free_udp_port()
    config = tmp_path / "sims.yaml"
    config.write_text(
        "autopilots:\n"
        f"  - {{name: a, stack: px4, sysid: 11, udp_out: '127.0.0.1:{port}'}}\n"
        "  - {name: b, stack: ardupilot, sysid: 12, pty: true}\n"
    )
    hosted = build_sims(build_parser().parse_args(["run", "--config", str(config)]))
    sims = [h.sim for h in hosted]
    try:
        assert [h.target for h in hosted] == ["a", "b"]
        assert [(s.name, s.stack, s.sysid) for s in sims] == [
            ("a", Stack.PX4, 11),
            ("b", Stack.ARDUPILOT, 12),
        ]
        assert sims[0].connection == f"udp://127.0.0.1:{port}"
        assert sims[1].connection.startswith("serial:///dev/")
    finally:
        stop_sims(sims)
    clash = tmp_path / "clash.yaml"
    clash.write_text("autopilots: [{name: a, sysid: 1, pty: true}, {name: a, sysid: 2}]\n")
    with pytest.raises(SystemExit):
        build_sims(build_parser().parse_args(["run", "--config", str(clash)]))


FLEET_CONFIG = """
fast_boot: true
home_lat_deg: 47.0
vehicles:
  - name: v1
    home_lon_deg: 8.0
    autopilots:
      - {name: px4-a, stack: px4, sysid: 1, udp_out: '127.0.0.1:PORT1'}
      - {name: px4-b, stack: px4, sysid: 2}
  - name: v2
    home_lon_deg: 8.001
    battery: per-autopilot
    boot_s: 7.5
    autopilots:
      - {name: px4-a, stack: px4, sysid: 1}
      - {name: px4-b, stack: px4, sysid: 2}
"""


def test_one_config_hosts_several_vehicles_each_with_its_home_battery_and_sockets(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A ``vehicles`` file: autopilot names repeat across vehicles and are reached as
    ``vehicle/autopilot``; a vehicle's autopilots share its battery (unless it says
    otherwise), its home and its own options; a fault reaches one autopilot only."""
    port = free_udp_port()
    config = tmp_path / "fleet.yaml"
    config.write_text(FLEET_CONFIG.replace("PORT1", str(port)))
    states = tmp_path / "state"
    client = Client(pymavlink_device(f"udp://127.0.0.1:{port}").device)
    run = [sys.executable, "-m", "roost_sim.main", "--state-dir", str(states), "run"]
    proc = subprocess.Popen([*run, "--config", str(config)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        lines = [json.loads(proc.stdout.readline()) for _ in range(4)]
        assert [(line["vehicle"], line["name"]) for line in lines] == [
            ("v1", "px4-a"), ("v1", "px4-b"), ("v2", "px4-a"), ("v2", "px4-b"),
        ]  # fmt: skip
        assert lines[0]["connection"] == f"udp://127.0.0.1:{port}"
        assert lines[2]["control"] == str(states / "v2" / "px4-a.sock")
        client.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() == 1)

        def cli(*args: str) -> tuple[int, str]:
            code = sim_cli(["--state-dir", str(states), *args])
            return code, capsys.readouterr().out

        code, listed = cli("list")
        assert listed.split() == ["v1/px4-a", "v1/px4-b", "v2/px4-a", "v2/px4-b"]
        assert cli("fault", "v1/px4-a", "battery")[0] == 0  # v1 shares one pack
        assert cli("fault", "v2/px4-a", "battery")[0] == 0  # v2 has one per autopilot
        assert cli("fault", "v2/px4-b", "silence")[0] == 0
        faults = {}
        for target in ("v1/px4-a", "v1/px4-b", "v2/px4-a", "v2/px4-b"):
            code, out = cli("status", target)
            assert code == 0
            faults[target] = json.loads(out)["state"]["faults"]
        assert faults == {
            "v1/px4-a": {"battery": "True"},
            "v1/px4-b": {"battery": "True"},
            "v2/px4-a": {"battery": "True"},
            "v2/px4-b": {"silence": "True"},
        }
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        client.close()
    assert proc.returncode == 0
    assert not list(states.rglob("*.sock"))


def test_autopilots_sharing_a_process_are_named_by_vehicle_in_logs_and_errors(
    tmp_path: Path,
) -> None:
    """Autopilot names repeat across the vehicles of one process: what it logs and
    raises names ``vehicle/autopilot``."""
    config = tmp_path / "fleet.yaml"
    config.write_text(FLEET_CONFIG.replace("PORT1", str(free_udp_port())))
    hosted = build_sims(build_parser().parse_args(["run", "--config", str(config)]))
    sims = [h.sim for h in hosted]
    try:
        assert [s.label for s in sims] == ["v1/px4-a", "v1/px4-b", "v2/px4-a", "v2/px4-b"]
        assert [s.name for s in sims] == ["px4-a", "px4-b", "px4-a", "px4-b"]
        with pytest.raises(TimeoutError, match=r"^v2/px4-b: condition not met"):
            sims[3].wait_until(lambda state: False, timeout=0.05)
    finally:
        stop_sims(sims)


def test_vehicle_entries_apply_the_files_keys_then_each_vehicles_own() -> None:
    document = yaml.safe_load(FLEET_CONFIG)
    v1, v2 = vehicle_entries(document, {"preset_streams": True})
    assert (v1.name, v1.battery, v2.battery) == ("v1", "shared", "per-autopilot")
    assert v1.options["home_lat_deg"] == v2.options["home_lat_deg"] == 47.0
    assert (v1.options["home_lon_deg"], v2.options["home_lon_deg"]) == (8.0, 8.001)
    assert v1.options["preset_streams"] and v2.options["fast_boot"]
    assert "boot_s" not in v1.options and v2.options["boot_s"] == 7.5
    assert v2.target("px4-a") == "v2/px4-a"
    [flat] = vehicle_entries({"autopilots": [{"name": "fc1"}]}, {}, "per-autopilot")
    assert (flat.name, flat.battery, flat.target("fc1")) == (None, "per-autopilot", "fc1")
    for bad in (
        {"vehicles": [{"name": "v1"}, {"name": "v1"}]},
        {"vehicles": [{"autopilots": []}]},
        {"vehicles": [{"name": "a/b"}]},
        {"vehicles": [{"name": "v1", "battery": "none"}]},
    ):
        with pytest.raises(SystemExit):
            vehicle_entries(bad, {})


# ---- an independent MAVLink implementation --------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("stack", STACKS)
def test_mavsdk_connects_reads_telemetry_arms_takes_off_and_lands(stack: Stack) -> None:
    port = free_udp_port()
    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    # MAVSDK does not request ArduPilot's streams (SYS_STATUS for its health); with the
    # real firmware one sets the SRn_* stream-rate parameters, which preset_streams is.
    config = SimConfig.fast(preset_streams=stack is Stack.ARDUPILOT)
    sim = SimulatedAutopilot.udp(stack, 1, target_port=port, config=config).start()
    try:
        assert int(mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")) == 0
        system = mavsdk.first_autopilot(10.0)
        assert system is not None and system.get_system_id() == 1
        telemetry, action = Telemetry(system), Action(system)

        def eventually(check: Callable[[], bool]) -> None:
            wait_until("MAVSDK to see the expected state", check, 10.0, 0.1)

        # MAVSDK reads "armable" from SYS_STATUS PREARM_CHECK: false while the sim boots.
        eventually(lambda: telemetry.health().is_armable)
        eventually(lambda: telemetry.health().is_home_position_ok)
        position = telemetry.position()
        assert position.latitude_deg == pytest.approx(sim.config.home_lat_deg, abs=1e-6)
        assert telemetry.health().is_global_position_ok
        action.arm()
        action.takeoff()
        eventually(lambda: telemetry.in_air() and telemetry.position().relative_altitude_m > 1.5)
        assert sim.snapshot().armed
        action.land()
        eventually(lambda: not telemetry.in_air() and not telemetry.armed())
        snap = sim.snapshot()
        assert snap.landed_state == "OnGround" and not snap.armed
        names = [c.name for c in sim.commands if c.result == MavResult.ACCEPTED]
        for expected in ("MAV_CMD_COMPONENT_ARM_DISARM", "MAV_CMD_NAV_TAKEOFF", "MAV_CMD_NAV_LAND"):
            assert expected in names
    finally:
        mavsdk.destroy()
        sim.stop()


@pytest.mark.slow
def test_mavsdk_over_the_serial_pseudo_terminal() -> None:
    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    with SimulatedAutopilot.pty(Stack.PX4, 2, config=FAST) as sim:
        try:
            assert int(mavsdk.add_any_connection(f"serial://{sim.device}:57600")) == 0
            system = mavsdk.first_autopilot(10.0)
            assert system is not None and system.get_system_id() == 2
            telemetry = Telemetry(system)
            wait_until(
                "a position over the serial link",
                lambda: not math.isnan(telemetry.position().latitude_deg),
                10.0,
                0.1,
            )
        finally:
            mavsdk.destroy()
