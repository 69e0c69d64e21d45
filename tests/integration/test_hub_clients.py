"""Real MAVLink clients through the agent's hub: MAVSDK's native library and MAVProxy.

Neither shares code with Roost: they connect to the vehicle endpoint the agent serves,
see one vehicle (the hub's sysid), read telemetry, arm, take off and land; the simulated
autopilots behind the agent (real UDP MAVLink) and their standby follow. The bridge is
simulated (no GPIO hardware here).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

import pytest
from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.action import Action
from mavsdk.plugins.offboard import Offboard, PositionNedYaw
from mavsdk.plugins.telemetry import Telemetry

from roost_agent.hub_policy import UNSIGNED
from roost_api.autopilot import HubEndpoint, HubSigning
from roost_mavlink.signing import passphrase_key
from roost_sim import FaultKind, SimConfig
from tests.support.hubclient import VEHICLE_SYSID, HubVehicle, hub_vehicle, repeating
from tests.support.waiting import wait_until

pytestmark = pytest.mark.slow

BIN = Path(sys.executable).parent


def eventually(what: str, check: Callable[[], bool], timeout: float = 15.0) -> None:
    wait_until(what, check, timeout, 0.1)


def airborne(v: HubVehicle) -> bool:
    return all(s.snapshot().landed_state == "InAir" for s in v.sims)


def on_ground(v: HubVehicle) -> bool:
    return all(s.snapshot().landed_state == "OnGround" for s in v.sims)


def mavsdk_on(v: HubVehicle) -> tuple[Mavsdk, Telemetry, Action, Offboard]:
    hub = v.agent.hub
    assert hub is not None
    host, port = hub.udp_address
    mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    assert int(mavsdk.add_any_connection(f"udpout://{host}:{port}")) == 0
    system = mavsdk.first_autopilot(10.0)
    assert system is not None and system.get_system_id() == VEHICLE_SYSID
    return mavsdk, Telemetry(system), Action(system), Offboard(system)


def test_mavsdk_flies_the_vehicle_through_the_hub() -> None:
    with hub_vehicle(["px4", "px4"]) as v:
        mavsdk, telemetry, action, _ = mavsdk_on(v)
        try:
            eventually("armable", lambda: telemetry.health().is_armable)
            eventually("home known", lambda: telemetry.health().is_home_position_ok)
            assert not math.isnan(telemetry.position().latitude_deg)
            action.arm()
            action.takeoff()
            eventually("both autopilots in the air", lambda: airborne(v))
            eventually("MAVSDK sees the vehicle in the air", telemetry.in_air)
            action.land()
            eventually("both autopilots landed", lambda: on_ground(v), 30)
            eventually("MAVSDK sees it landed", lambda: not telemetry.in_air())
        finally:
            mavsdk.destroy()


# serial: T_off and a failover judged in real time
@pytest.mark.serial
def test_mavsdk_offboard_stream_continues_to_the_new_autopilot_after_a_failover() -> None:
    with hub_vehicle(["px4", "px4"]) as v:
        mavsdk, telemetry, action, offboard = mavsdk_on(v)
        try:
            eventually("armable", lambda: telemetry.health().is_armable)
            action.arm()
            action.takeoff()
            eventually("both autopilots in the air", lambda: airborne(v))
            eventually("both above 2 m", lambda: all(s.snapshot().altitude_m > 2 for s in v.sims))
            time.sleep(1.2)  # not a wait for a condition: T_off, a standby's required OK time
            setpoint = PositionNedYaw(0.0, 0.0, -5.0, 0.0)
            offboard.set_position_ned(setpoint)
            # MAVSDK resends the last setpoint itself; the controller keeps it fresh
            with repeating(lambda: offboard.set_position_ned(setpoint), 0.1):
                hub = v.agent.hub
                assert hub is not None
                v.sim("fc1").inject(FaultKind.SILENCE)
                wait_until("switched to fc2", lambda: v.agent.active == "fc2", 10, 0.02)
                routed = hub.counters.from_clients
                received = v.sim("fc2").setpoints_received
                eventually(
                    "MAVSDK's setpoints reach fc2",
                    lambda: (
                        v.sim("fc2").setpoints_received > received + 10
                        and hub.counters.from_clients > routed + 20
                    ),
                )
                systems = mavsdk.get_systems()  # still one vehicle: no new system appeared
                assert [s.get_system_id() for s in systems] == [VEHICLE_SYSID]
                eventually("MAVSDK still gets telemetry", telemetry.in_air)
        finally:
            mavsdk.destroy()


class MavProxy:
    """A MAVProxy process on ``address`` (udpout), driven through its console."""

    def __init__(self, address: tuple[str, int], state_dir: Path, sysid: int) -> None:
        host, port = address
        state_dir.mkdir(parents=True, exist_ok=True)
        self.proc = subprocess.Popen(
            [
                str(BIN / "mavproxy.py"),
                f"--master=udpout:{host}:{port}",
                f"--target-system={VEHICLE_SYSID}",
                f"--source-system={sysid}",
                f"--state-basedir={state_dir}",
                "--default-modules=mode,arm,cmdlong,signing",
                "--nowait",
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=state_dir,
            env={**os.environ, "HOME": str(state_dir)},  # no ~/.mavproxy of the user's
        )
        self.output: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.output.append(line)

    def say(self, line: str) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def detected(self) -> list[str]:
        return [line for line in self.output if "Detected vehicle" in line]

    def close(self) -> None:
        with suppress(OSError):
            self.say("exit")
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=5)


@contextmanager
def mavproxy(address: tuple[str, int], state_dir: Path, sysid: int = 254) -> Iterator[MavProxy]:
    proxy = MavProxy(address, state_dir, sysid)
    try:
        yield proxy
    finally:
        proxy.close()


def fly_with_mavproxy(v: HubVehicle, proxy: MavProxy) -> None:
    """GUIDED, arm, take off 5 m and land, through MAVProxy's console."""
    eventually(
        "MAVProxy sees one vehicle, the hub's sysid",
        lambda: any(f"Detected vehicle {VEHICLE_SYSID}:1" in line for line in proxy.detected()),
    )
    proxy.say("mode GUIDED")
    eventually("GUIDED on both", lambda: all(s.snapshot().mode == "GUIDED" for s in v.sims))
    proxy.say("arm throttle")
    eventually("armed on both", lambda: all(s.snapshot().armed for s in v.sims))
    proxy.say("takeoff 5")
    eventually("both autopilots in the air", lambda: airborne(v))
    proxy.say("mode LAND")
    eventually("both autopilots landed", lambda: on_ground(v), 40)
    assert len(proxy.detected()) == 1, proxy.detected()  # one identity all along


def test_mavproxy_arms_takes_off_and_lands_through_the_hub(tmp_path: Path) -> None:
    with hub_vehicle(["ardupilot", "ardupilot"], config=SimConfig.fast(preset_streams=True)) as v:
        hub = v.agent.hub
        assert hub is not None
        with mavproxy(hub.udp_address, tmp_path) as proxy:
            fly_with_mavproxy(v, proxy)


PASSPHRASE = "correct-horse-battery-staple-roost"
UNSIGNED_MAVPROXY_SYSID = 249


def test_signed_mavproxy_flies_a_signed_vehicle_and_an_unsigned_one_gets_nothing(
    tmp_path: Path,
) -> None:
    """MAVProxy's ``signing key PASSPHRASE`` uses SHA-256 of the passphrase as the key,
    which is what ``roost keys create`` stores for the vehicle."""
    key = passphrase_key(PASSPHRASE)
    gcs = HubEndpoint(name="gcs", address="127.0.0.1:0", signing=HubSigning.REQUIRED)
    config = SimConfig.fast(preset_streams=True)
    with hub_vehicle(["ardupilot", "ardupilot"], config=config, endpoints=[gcs], key=key) as v:
        hub = v.agent.hub
        assert hub is not None
        address = hub.endpoint_address("gcs")
        drops = next(e for e in hub.endpoints if e.name == "gcs").drops
        with (
            mavproxy(address, tmp_path / "intruder", UNSIGNED_MAVPROXY_SYSID) as intruder,
            mavproxy(address, tmp_path / "pilot") as pilot,
        ):
            intruder.say("arm throttle")
            intruder.say("mode GUIDED")
            eventually("the intruder's frames are dropped", lambda: drops.by_reason[UNSIGNED] > 0)
            pilot.say(f"signing key {PASSPHRASE}")
            fly_with_mavproxy(v, pilot)
            intruder.say("arm throttle")
            assert intruder.detected() == []  # it never even saw the vehicle
        reached = [c for s in v.sims for c in s.commands if c.source[0] == UNSIGNED_MAVPROXY_SYSID]
        assert reached == []
        assert hub.endpoint_status()[1].signed
