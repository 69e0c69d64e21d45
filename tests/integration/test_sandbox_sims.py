"""The sandbox's simulators bind their own ports and report them; nothing races for a port.

The sandbox once picked agent ports by binding and closing sockets before starting the
simulators, whose own ephemeral sockets could then take one of them (an agent logging
"Address already in use" forever). Now each simulator binds a free port itself and the
RedundantAutopilot is written from what it reports. Here real ``roost-sim`` processes
are started exactly as ``roost sandbox up`` starts them, and a real MAVLink client
talks to the reported ports the way the agent's ``udpout://`` link does; two vehicles
share one process, as the sandbox groups them.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import psutil
import pytest
from pymavlink import mavutil

from roost_api import shapes
from roost_api.autopilot import RedundantAutopilotSpec
from roost_cli.sandbox import plan, sims, state
from roost_cli.sandbox.processes import Launcher

HEARTBEAT_TIMEOUT_S = 15.0


@pytest.fixture
def started(tmp_path: Path) -> Iterator[tuple[Launcher, list[state.SandboxVehicle]]]:
    launcher = Launcher(tmp_path / "logs", lambda: None)
    try:
        fleet = plan.plan_fleet(3)
        recorded = [
            v
            for group in sims.process_groups(fleet, 2)
            for v in sims.start(launcher, group, tmp_path)
        ]
        yield launcher, recorded
    finally:
        launcher.stop_all()


def test_each_simulator_holds_the_port_it_reports_and_answers_there(
    started: tuple[Launcher, list[state.SandboxVehicle]],
) -> None:
    launcher, recorded = started
    ports: list[int] = []
    processes = {}  # vehicle name -> the ports its simulator process holds
    for proc in launcher.processes:  # two processes: drone-1; drone-2 with drone-3
        assert proc.pid is not None
        held = {c.laddr.port for c in psutil.Process(proc.pid).net_connections(kind="udp")}
        first, _, last = proc.name.removeprefix("roost-sim-").partition("..")
        processes.update({name: held for name in {first, last or first}})
    assert sorted(processes) == ["drone-1", "drone-2", "drone-3"]
    for vehicle in recorded:
        held = processes[vehicle.name]
        for autopilot in vehicle.autopilots:
            match = re.fullmatch(r"udpout://127\.0\.0\.1:(\d+)", autopilot.connection)
            assert match, autopilot.connection
            port = int(match.group(1))
            assert port in held, f"{autopilot.name} reports {port}, its process holds {held}"
            ports.append(port)
    assert len(set(ports)) == len(ports)

    for vehicle in recorded:
        for autopilot in vehicle.autopilots:
            host_port = autopilot.connection.removeprefix("udpout://")
            link = mavutil.mavlink_connection(
                f"udpout:{host_port}", source_system=autopilot.sysid, source_component=191
            )
            try:
                link.mav.heartbeat_send(18, 8, 0, 0, 0)  # the agent speaks first, as it does
                beat = link.recv_match(type="HEARTBEAT", blocking=True, timeout=HEARTBEAT_TIMEOUT_S)
                while beat is not None and beat.get_srcSystem() != autopilot.sysid:
                    beat = link.recv_match(
                        type="HEARTBEAT", blocking=True, timeout=HEARTBEAT_TIMEOUT_S
                    )
                assert beat is not None, f"no heartbeat from {vehicle.name}/{autopilot.name}"
            finally:
                link.close()


def test_the_redundant_autopilot_is_written_from_the_reported_ports(
    started: tuple[Launcher, list[state.SandboxVehicle]],
) -> None:
    _, recorded = started
    for vehicle, running in zip(plan.plan_fleet(3), recorded, strict=True):
        connections = {a.name: a.connection for a in running.autopilots}
        manifest = plan.autopilot_manifest(vehicle, connections)
        spec = RedundantAutopilotSpec.model_validate(manifest["spec"])
        assert [a.connection for a in spec.autopilots] == list(connections.values())
        for autopilot in spec.autopilots:
            assert re.search(shapes.NETWORK_CONNECTION, autopilot.connection)
