"""The sandbox's mission programs as ``roost sandbox up --mission sync-paths`` starts them:
real simulator processes (the sandbox's own ``sims.start``), the monitor and followers as
separate processes over real UDP, and a lag fault sent through the simulators' control
sockets once the monitor starts the vehicles. The control plane is left out (the
programs do not use it); short trajectories (two 6 s legs of 9 m) keep the flight to
about 20 s."""

from __future__ import annotations

import json
import threading
from pathlib import Path
from typing import Any

import pytest

from roost_cli.sandbox import missionrun, plan, sims
from roost_cli.sandbox.missionrun import Lag, LagInjector
from roost_cli.sandbox.processes import Launcher
from roost_localcluster.processes import ManagedProcess
from roost_sim.control import request
from tests.support.waiting import wait_until

# serial: transits compared with the plan to half a second
pytestmark = [pytest.mark.slow, pytest.mark.serial]

LEG_S = 6.0
TRAJECTORY = "time_s,north_m,east_m,down_m\n0,{n},0,-5\n6,{n},9,-5\n12,{n},0,-5\n"


def _wait_for(what: str, check: Any, procs: list[ManagedProcess], timeout_s: float) -> Any:
    """Wait for ``check``; on a timeout the error carries every program's log tail."""
    return wait_until(
        what,
        check,
        timeout_s,
        poll_s=0.1,
        explain=lambda: "logs:\n" + "\n".join(f"--- {p.name}\n{p.log_tail()}" for p in procs),
    )


def test_a_lagging_vehicle_is_waited_for_and_transits_stay_planned(tmp_path: Path) -> None:
    launcher = Launcher(tmp_path / "logs", lambda: None)
    fleet = plan.plan_fleet(2)  # drone-1 PX4, drone-2 ArduPilot
    trajectories = tmp_path / "trajectories"
    trajectories.mkdir()
    for index, vehicle in enumerate(fleet):
        (trajectories / f"{vehicle.name}.csv").write_text(TRAJECTORY.format(n=index * 6))
    try:
        running = sims.start(launcher, fleet, tmp_path)
        names = [vehicle.name for vehicle in running]
        connections = {  # straight to the primaries: no agents (and no hubs) here
            vehicle.name: missionrun.pymavlink_url(
                next(a.connection for a in vehicle.autopilots if a.name == p.primary.name)
            )
            for vehicle, p in zip(running, fleet, strict=True)
        }
        output = tmp_path / "out"
        monitor = missionrun.monitor_program(missionrun.SYNC_PATHS, names, output)
        monitor_proc = launcher.start(monitor.name, list(monitor.argv), monitor.env)
        address = _wait_for(
            "the monitor's listening line",
            lambda: missionrun.listening_address(monitor_proc.log.read_text()),
            launcher.processes,
            60,
        )
        for program in missionrun.follower_programs(
            missionrun.SYNC_PATHS, connections, address, trajectories=trajectories
        ):
            launcher.start(program.name, list(program.argv), program.env)
        controls = {v.name: Path(v.autopilots[0].control) for v in running}
        stop = threading.Event()

        def send(vehicle: str, message: dict[str, object]) -> None:
            assert request(controls[vehicle], dict(message)).get("ok")

        injector = LagInjector(
            (Lag("drone-1", 0.0, LEG_S + 2.0, 15.0),),  # 0.75 m/s on leg 1 (1.5 planned)
            send,
            stop,
            lambda: missionrun.started(monitor_proc.log.read_text()),
        )
        injector.start()
        _wait_for("the results", (output / "results.json").is_file, launcher.processes, 180)
        stop.set()
        injector.join(timeout=30)
        assert injector.failed == []
        assert [m["op"] for _, _, m in injector.sent] == ["fault", "clear"]
        results: dict[str, Any] = json.loads((output / "results.json").read_text())
        assert sorted(results) == names
        records = {name: results[name]["records"] for name in names}
        delay = records["drone-1"][0]["delay_s"]
        assert delay > 1.0  # the lag made drone-1 late at task 1
        assert records["drone-2"][0]["wait_s"] == pytest.approx(
            delay - records["drone-2"][0]["delay_s"], abs=0.3
        )  # drone-2 waited for it
        for name in names:
            assert [r["task"] for r in records[name]] == [1, 2]
            for record in records[name]:
                assert record["transit_s"] == pytest.approx(LEG_S, abs=0.5)
        assert (output / "table.md").read_text().startswith("| task |")
    finally:
        launcher.stop_all()
