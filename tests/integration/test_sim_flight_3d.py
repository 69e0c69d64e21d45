"""3D flight of a simulated autopilot driven by a MAVLink client over real UDP.

A ground-station client (:class:`tests.support.hubclient.HubClient`: its own socket, a
1 Hz heartbeat) streams position setpoints to one simulated autopilot, switches it into
the stack's setpoint mode with DO_SET_MODE, and reads where it flies from the
LOCAL_POSITION_NED and GLOBAL_POSITION_INT it streams back: the same path a mission's
onboard controller takes.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from roost_api.meta import Stack
from roost_mavlink import MAV_CMD_DO_SET_MODE, MAV_CMD_NAV_RETURN_TO_LAUNCH, set_mode_params
from roost_sim import FaultKind, SimConfig, SimulatedAutopilot, UdpLink
from roost_sim.kinematics import global_from_ned
from tests.support.flight import take_off
from tests.support.hubclient import HubClient, Received, repeating

pytestmark = pytest.mark.slow

SYSID = 1
LOCAL_POSITION_HZ = 20.0


@contextlib.contextmanager
def client_of(stack: Stack) -> Iterator[tuple[SimulatedAutopilot, HubClient]]:
    """One airborne sim streaming LOCAL_POSITION_NED, and a client it answers."""
    sim = SimulatedAutopilot.udp(stack, SYSID, name="fc1", config=SimConfig.fast()).start()
    try:
        assert isinstance(sim.link, UdpLink)
        host, port = sim.link.local_address
        with HubClient((host, port)) as client:
            sim.set_rate(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, LOCAL_POSITION_HZ)
            sim.set_rate(mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 10.0)
            take_off([sim])
            yield sim, client
    finally:
        sim.stop()


def near(
    north: float, east: float, down: float, tolerance: float = 0.3
) -> Callable[[Received], bool]:
    """A LOCAL_POSITION_NED within ``tolerance`` of the point."""

    def check(r: Received) -> bool:
        if r.kind != "LOCAL_POSITION_NED":
            return False
        m = r.msg
        return (
            abs(m.x - north) < tolerance
            and abs(m.y - east) < tolerance
            and abs(m.z - down) < tolerance
        )

    return check


def set_mode(client: HubClient, stack: Stack, mode: str) -> int:
    return client.command(SYSID, MAV_CMD_DO_SET_MODE, *set_mode_params(stack, mode))


def test_px4_offboard_flies_the_setpoint_stream_and_holds_when_it_stops() -> None:
    with client_of(Stack.PX4) as (sim, client):
        assert set_mode(client, Stack.PX4, "OFFBOARD") == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
        with repeating(lambda: client.setpoint(SYSID, 20.0, 10.0, -5.0), 0.05):
            client.setpoint(SYSID, 20.0, 10.0, -5.0)  # same socket: it arrives before the mode
            assert set_mode(client, Stack.PX4, "OFFBOARD") == mavlink.MAV_RESULT_ACCEPTED
            arrived = client.wait_for(near(20.0, 10.0, -5.0), 20)
        # the stream stopped: after COM_OF_LOSS_T PX4 holds (AUTO.LOITER) where it is
        sim.wait_until(lambda s: s.mode == "AUTO.LOITER", timeout=5)
        position = client.wait_for(
            lambda r: r.kind == "LOCAL_POSITION_NED" and r.at > arrived.at + 2.0, 10
        )
        assert abs(position.msg.x - 20.0) < 0.5 and abs(position.msg.y - 10.0) < 0.5


def test_ardupilot_guided_flies_a_global_setpoint_and_rtl_brings_it_home() -> None:
    with client_of(Stack.ARDUPILOT) as (sim, client):
        lat, lon = global_from_ned(-15.0, 25.0, sim.config.home_lat_deg, sim.config.home_lon_deg)
        client.mav.set_position_target_global_int_send(
            0, SYSID, 1, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0b0000_1111_1111_1000,
            round(lat * 1e7), round(lon * 1e7), 6.0, 0, 0, 0, 0, 0, 0, 0, 0,
        )  # fmt: skip
        arrived = client.wait_for(near(-15.0, 25.0, -6.0), 20)
        there = client.wait_for(lambda r: r.kind == "GLOBAL_POSITION_INT", 5, since=arrived.at)
        assert abs(there.msg.lat - lat * 1e7) < 50 and abs(there.msg.lon - lon * 1e7) < 50  # ~0.5 m
        assert abs(there.msg.relative_alt - 6000) < 300
        assert client.command(SYSID, MAV_CMD_NAV_RETURN_TO_LAUNCH) == mavlink.MAV_RESULT_ACCEPTED
        sim.wait_until(lambda s: s.landed_state == "OnGround", timeout=40)
        snapshot = sim.snapshot()
        assert abs(snapshot.north_m) < 0.6 and abs(snapshot.east_m) < 0.6


def test_the_lag_fault_slows_the_vehicle_until_cleared() -> None:
    with client_of(Stack.ARDUPILOT) as (sim, client):
        sim.inject(FaultKind.LAG, 40)
        assert sim.snapshot().faults == {"lag": "40.0"}
        client.setpoint(SYSID, 200.0, 0.0, -5.0)
        sim.wait_until(lambda s: s.speed_mps > 1.5, timeout=10)
        speeds = []
        sampled_until = time.monotonic() + 3.0
        while time.monotonic() < sampled_until:  # sampling a cruise, not waiting for it
            speeds.append(sim.snapshot().speed_mps)
            time.sleep(0.05)
        assert max(speeds) <= 0.4 * sim.config.max_speed_mps + 0.01
        sim.clear(FaultKind.LAG)
        sim.wait_until(lambda s: s.speed_mps > 0.4 * sim.config.max_speed_mps + 0.5, timeout=10)
