"""The agent as the vehicle's MAVLink hub, against simulated autopilots over real UDP.

A ground-station client (tests.support.hubclient: its own UDP socket, real MAVLink 2)
connects to the endpoint the agent serves and flies the vehicle through it, while the
simulated autopilots run behind the agent's links and a simulated bridge (the only
stand-in: no GPIO hardware here). What a client must see: one vehicle identity before and
after a failover, its commands and setpoint stream reaching whichever autopilot is
active, nothing from a standby, and standbys kept in step (or reported out of step).
"""

from __future__ import annotations

import math
import socket
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

import psutil
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from roost_api.autopilot import (
    AutopilotCommand,
    CommandAction,
)
from roost_api.meta import HealthLevel
from roost_mavlink import (
    MAV_CMD_DO_SET_MODE,
    MavResult,
    set_mode_params,
)
from roost_sim import (
    FaultKind,
    SimulatedAutopilot,
)
from tests.support.agent import run_agent_once
from tests.support.hubclient import (
    VEHICLE_SYSID,
    HubVehicle,
    fly_setpoint_circle,
    hub_vehicle,
    repeating,
    source_system,
)
from tests.support.waiting import wait_until

pytestmark = pytest.mark.slow

POLL_S = 0.02
MAV_CMD_COMPONENT_ARM_DISARM = 400
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_NAV_LAND = 21


def take_off_through_hub(v: HubVehicle) -> None:
    """Arm and take off with commands the client addresses to the vehicle."""
    assert v.client.command(VEHICLE_SYSID, MAV_CMD_COMPONENT_ARM_DISARM, 1) == MavResult.ACCEPTED
    result = v.client.command(VEHICLE_SYSID, MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, math.nan)
    assert result == MavResult.ACCEPTED


def airborne(sim: SimulatedAutopilot) -> None:
    sim.wait_until(lambda s: s.landed_state == "InAir" and s.altitude_m > 2.0, timeout=15)


def ready_to_switch(v: HubVehicle) -> None:
    """Taken off through the hub, every autopilot OK for T_off: a switch is allowed."""
    take_off_through_hub(v)
    for sim in v.sims:
        airborne(sim)
    wait_until("every autopilot OK", lambda: all_ok(v), 10, POLL_S)
    time.sleep(1.2)  # not a wait for a condition: T_off before a switch is allowed


def condition_is(
    v: HubVehicle, name: str, status: str, reason: str | None = None
) -> Callable[[], bool]:
    def check() -> bool:
        cond = v.in_step(name)
        return cond is not None and cond.status == status and reason in (None, cond.reason)

    return check


def set_mode(v: HubVehicle, mode: str) -> int:
    params = set_mode_params(v.sims[0].stack, mode)
    return v.client.command(VEHICLE_SYSID, MAV_CMD_DO_SET_MODE, *params)


def all_ok(v: HubVehicle) -> bool:
    a = v.agent.assessments()
    return all(s.name in a and a[s.name].level == HealthLevel.OK for s in v.sims)


def test_client_flies_the_vehicle_through_the_hub_and_the_standby_follows() -> None:
    with hub_vehicle(["px4", "px4"]) as v:
        take_off_through_hub(v)
        for sim in v.sims:  # the standby got the mirrored arm and takeoff
            airborne(sim)
        wait_until("fc2 in step", condition_is(v, "fc2", "True", "InStep"), 10, POLL_S)
        assert v.in_step("fc1") is not None and v.in_step("fc1").reason == "Active"  # type: ignore[union-attr]
        assert set_mode(v, "AUTO.LOITER") == MavResult.ACCEPTED
        for sim in v.sims:
            sim.wait_until(lambda s: s.mode == "AUTO.LOITER", timeout=5)
        assert v.client.command(VEHICLE_SYSID, MAV_CMD_NAV_LAND) == MavResult.ACCEPTED
        for sim in v.sims:
            sim.wait_until(lambda s: s.landed_state == "OnGround", timeout=20)
        # one identity: everything the client ever got came from the vehicle's sysid
        senders = {r.sysid for r in v.client.messages()}
        assert senders == {VEHICLE_SYSID}, senders
        kinds = {r.kind for r in v.client.messages()}
        assert {"HEARTBEAT", "GLOBAL_POSITION_INT", "COMMAND_ACK"} <= kinds


# serial: a failover after T_off, judged in real time
@pytest.mark.serial
def test_failover_keeps_the_client_connected_and_its_setpoint_stream_moves() -> None:
    with hub_vehicle(["px4", "px4"]) as v:
        take_off_through_hub(v)
        for sim in v.sims:
            airborne(sim)
        wait_until("every autopilot OK", lambda: all_ok(v), 10, POLL_S)
        wait_until("fc2 in step", condition_is(v, "fc2", "True"), 10, POLL_S)
        time.sleep(1.2)  # not a wait for a condition: T_off, a standby's required OK time
        with repeating(lambda: v.client.setpoint(VEHICLE_SYSID, 0.0, 0.0, -5.0), 0.05):
            hub = v.agent.hub
            assert hub is not None
            standby_before = v.in_step("fc2")
            v.sim("fc1").inject(FaultKind.SILENCE)
            wait_until("switched to fc2", lambda: v.agent.active == "fc2", 10, POLL_S)
            assert hub.active == "fc2"
            assert (v.sim("fc1").driving, v.sim("fc2").driving) == (False, True)  # the bridge
            switched = time.monotonic()
            # the client keeps its connection: the vehicle answers it from fc2
            v.client.wait_for(lambda r: r.kind == "HEARTBEAT", 5, switched)
            routed = hub.counters.from_clients
            wait_until(
                "setpoints reach fc2 through the hub",
                lambda: hub.counters.from_clients > routed + 10,
                5,
                POLL_S,
            )
            record = v.agent.status().last_failover
            assert record is not None and record.standby_in_step is True, (
                f"{record}; fc2 before the silence: {standby_before}"
            )
            assert set_mode(v, "AUTO.LOITER") == MavResult.ACCEPTED  # answered by fc2
        assert {r.sysid for r in v.client.messages()} == {VEHICLE_SYSID}


# serial: switches after T_off; heartbeats counted per second
@pytest.mark.serial
def test_after_a_switch_nothing_from_the_old_active_reaches_the_client() -> None:
    with hub_vehicle(["px4", "px4"]) as v:
        ready_to_switch(v)
        switch(v, "fc2", 1)
        hub = v.agent.hub
        assert hub is not None
        before = hub.counters.forwarded.get("fc1", 0)
        link = v.agent.links["fc1"]
        accepted = link.counters.accepted
        start = time.monotonic()
        wait_until(
            "fc1 keeps talking to the agent",
            lambda: link.counters.accepted > accepted + 100,
            5,
            POLL_S,
        )
        assert hub.counters.forwarded.get("fc1", 0) == before  # none of it went to clients
        beats = v.client.messages("HEARTBEAT", start)
        elapsed = time.monotonic() - start
        assert len(beats) <= math.ceil(elapsed) + 1, (len(beats), elapsed)  # one source, 1 Hz


def switch(v: HubVehicle, target: str, n: int) -> None:
    command = AutopilotCommand(
        id=f"switch-{n}", action=CommandAction.SWITCH, target=target, issued_at=datetime.now(UTC)
    )
    assert v.agent.submit(command).result(timeout=5).result == "Executed"


# serial: 22 switches, each allowed only after T_off
@pytest.mark.serial
def test_switching_back_and_forth_leaks_no_threads_sockets_or_clients() -> None:
    with hub_vehicle(["px4", "px4"]) as v:
        ready_to_switch(v)
        hub = v.agent.hub
        assert hub is not None
        me = psutil.Process()
        switch(v, "fc2", 0)
        switch(v, "fc1", 1)
        threads, fds, clients = threading.active_count(), me.num_fds(), hub.clients()
        for n in range(2, 22):
            switch(v, "fc2" if n % 2 == 0 else "fc1", n)
            v.client.wait_for(lambda r: r.kind == "ATTITUDE", 5, time.monotonic())
        assert hub.counters.switches == 22
        assert (threading.active_count(), me.num_fds(), hub.clients()) == (threads, fds, clients)


def test_unmirrored_standby_drifts_out_of_step_and_a_dead_active_still_fails_over() -> None:
    with hub_vehicle(["px4", "px4"], mirror=False) as v:
        for sim in v.sims:
            sim.fly()
        for sim in v.sims:
            airborne(sim)
        wait_until("every autopilot OK", lambda: all_ok(v), 10, POLL_S)
        wait_until("fc2 in step", condition_is(v, "fc2", "True"), 15, POLL_S)
        assert set_mode(v, "AUTO.RTL") == MavResult.ACCEPTED  # fc1 only: no mirroring
        wait_until("fc2 out of step", condition_is(v, "fc2", "False", "ModeDiffers"), 10, POLL_S)
        v.sim("fc1").inject(FaultKind.SILENCE)
        wait_until("switched to fc2", lambda: v.agent.active == "fc2", 10, POLL_S)
        record = v.agent.status().last_failover
        assert record is not None and record.standby_in_step is False


def test_standby_rejecting_a_mirrored_mode_is_out_of_step() -> None:
    with hub_vehicle(["px4", "px4"]) as v:
        take_off_through_hub(v)
        for sim in v.sims:
            airborne(sim)
        wait_until("fc2 in step", condition_is(v, "fc2", "True"), 15, POLL_S)
        v.sim("fc2").inject(FaultKind.SENSOR, "gps")  # position modes refused from now
        assert set_mode(v, "POSCTL") == MavResult.ACCEPTED  # the active accepts
        wait_until(
            "fc2 rejected the mirrored mode",
            condition_is(v, "fc2", "False", "RejectedMirroredCommand"),
            10,
            POLL_S,
        )
        cond = v.in_step("fc2")
        assert cond is not None and "DO_SET_MODE" in cond.message


def test_silent_standby_is_out_of_step() -> None:
    with hub_vehicle(["ardupilot", "ardupilot"]) as v:
        for sim in v.sims:
            sim.fly()
        for sim in v.sims:
            airborne(sim)
        wait_until("fc2 in step", condition_is(v, "fc2", "True"), 15, POLL_S)
        v.sim("fc2").inject(FaultKind.SILENCE)
        wait_until("fc2 silent", condition_is(v, "fc2", "False", "Silent"), 10, POLL_S)
        # the ArduPilot standby was told it is one (STANDBY aux function high), the active not
        aux = [c for c in v.sim("fc2").commands if c.command == 218]
        assert aux and aux[0].params[:2] == (76.0, 2.0) and aux[0].result == 0, aux
        assert v.sim("fc2").snapshot().standby_aux is True
        assert v.sim("fc1").snapshot().standby_aux is False
        assert (v.sim("fc1").driving, v.sim("fc2").driving) == (True, False)


def test_a_tcp_ground_station_gets_the_vehicle_and_commands_it() -> None:
    with hub_vehicle(["px4", "px4"], tcp=True) as v:
        hub = v.agent.hub
        assert hub is not None and hub.tcp_address is not None
        parser = mavlink.MAVLink(None)
        gcs = mavlink.MAVLink(None, 254, 190)
        with socket.create_connection(hub.tcp_address, timeout=5) as sock:
            sock.sendall(gcs.heartbeat_encode(6, 8, 0, 0, 0).pack(gcs))
            sock.sendall(
                gcs.command_long_encode(VEHICLE_SYSID, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(gcs)
            )
            seen: set[str] = set()
            ack = None
            deadline = time.monotonic() + 10
            while (ack is None or "HEARTBEAT" not in seen) and time.monotonic() < deadline:
                for msg in parser.parse_buffer(sock.recv(65535)) or []:
                    assert source_system(msg) == VEHICLE_SYSID
                    seen.add(msg.get_type())
                    if msg.get_type() == "COMMAND_ACK" and msg.command == 400:
                        ack = msg
        assert ack is not None and ack.result == MavResult.ACCEPTED, seen
        assert "HEARTBEAT" in seen
        for sim in v.sims:  # armed through TCP, mirrored to the standby
            sim.wait_until(lambda s: s.armed, timeout=5)


def test_an_agent_whose_hub_endpoint_is_taken_refuses_in_one_line(tmp_path: Path) -> None:
    blocker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    blocker.bind(("127.0.0.1", 0))
    port = blocker.getsockname()[1]
    try:
        done = run_agent_once(tmp_path, {"udp": f"127.0.0.1:{port}"})
    finally:
        blocker.close()
    assert done.returncode == 2
    refusals = [line for line in done.stderr.splitlines() if line.startswith("roost-agent: ")]
    assert len(refusals) == 1 and "MAVLink endpoint" in refusals[0], done.stderr
    assert "Traceback" not in done.stderr


# serial: positions compared to a metre while flying a 20 Hz setpoint stream
@pytest.mark.serial
@pytest.mark.parametrize("mirror", [True, False], ids=["mirrored", "unmirrored"])
def test_a_mirrored_standby_flies_the_clients_path_and_an_unmirrored_one_stays_behind(
    mirror: bool,
) -> None:
    with hub_vehicle(["px4", "px4"], mirror=mirror) as v:
        separations = fly_setpoint_circle(v, 12.0)
        if mirror:
            assert max(separations) < 1.0, separations
            wait_until("fc2 in step", condition_is(v, "fc2", "True", "InStep"), 15, POLL_S)
        else:
            assert separations[-1] > 10.0, separations  # 24 m along the circle, fc2 hovers
            wait_until(
                "fc2 out of step",
                lambda: (
                    condition_is(v, "fc2", "False", "PositionDiffers")()
                    or condition_is(v, "fc2", "False", "ModeDiffers")()
                ),
                5,
                POLL_S,
            )


# serial: a failover mid-circle, where the vehicle is judged to metres
@pytest.mark.serial
def test_a_failover_under_a_setpoint_stream_continues_from_where_the_vehicle_was() -> None:
    """The client's circle goes on through the hub to fc2, which was flying the same path
    (mirrored): the vehicle does not jump at the switch; the safety routine then holds it
    on its track."""
    with hub_vehicle(["px4", "px4"]) as v:
        seen: dict[str, tuple[float, float, float]] = {}

        def fail_midway(flown_s: float) -> None:
            if flown_s >= 6.0 and "fc1" not in seen:
                at = v.sim("fc1").snapshot()
                seen["fc1"] = (at.north_m, at.east_m, at.altitude_m)
                v.sim("fc1").inject(FaultKind.SILENCE)

        fly_setpoint_circle(v, 10.0, on_sample=fail_midway)
        wait_until("switched to fc2", lambda: v.agent.active == "fc2", 5, POLL_S)
        record = v.agent.status().last_failover
        assert record is not None and record.standby_in_step is True
        held = v.sim("fc2").wait_until(lambda s: s.speed_mps == 0.0, timeout=15)
        # 4 s of circle after the fault at 2 m/s, then braking: on the circle, near the switch
        assert math.dist(seen["fc1"], (held.north_m, held.east_m, held.altitude_m)) < 12.0
        assert abs(math.hypot(held.north_m, held.east_m - 20.0) - 20.0) < 1.5  # on the circle
