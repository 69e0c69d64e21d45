"""The sync-paths reference mission flown against simulated autopilots, in one process.

Its real programs' code (``syncpaths.follower.fly`` and ``syncpaths.monitor.Monitor``)
runs on threads instead of in pods: each follower reaches its own simulated autopilot
over real UDP MAVLink through ``syncpaths.vehicle.MavlinkVehicle`` and the monitor over
real UDP datagrams. Delays are created as a lab would see them, with the simulator's
``lag`` fault (the vehicle flies slower than planned) on chosen vehicles and transits.
Used by ``python -m bench sync``; the real-node test shares its paths and log reader.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from roost_localcluster.binaries import REPO_ROOT
from roost_sim import FaultKind, SimConfig, SimulatedAutopilot, UdpLink

EXAMPLE = REPO_ROOT / "examples" / "missions" / "sync-paths"
if str(EXAMPLE) not in sys.path:
    sys.path.insert(0, str(EXAMPLE))

from syncpaths.channel import Channel  # noqa: E402
from syncpaths.follower import fly  # noqa: E402
from syncpaths.monitor import Monitor, results_from_log  # noqa: E402
from syncpaths.sync import Follower, Phase  # noqa: E402
from syncpaths.trajectory import Task, load  # noqa: E402
from syncpaths.vehicle import MavlinkVehicle  # noqa: E402

TRAJECTORIES = EXAMPLE / "trajectories"
SHORT_TRAJECTORIES = Path(__file__).parent / "sync_trajectories"
"""The tests' flights: the shipped trajectories' shape (three drones, five tasks, four
legs at 1.5 m/s) scaled down to 9 m squares flown in 6 s legs, 15 m apart; the injected
lags still make delays of one to two seconds (the sandbox's schedule follows these legs:
``roost_cli.sandbox.missionrun.lag_schedule``). About 24 s of legs instead of 80 s."""
__all__ = [
    "EXAMPLE",
    "SHORT_TRAJECTORIES",
    "SyncRun",
    "fly_mission",
    "paper_plans",
    "results_from_log",
]


@dataclass
class SyncRun:
    """What one run produced: the monitor's results per vehicle."""

    results: dict[str, dict[str, Any]]
    lags: dict[tuple[str, int], float] = field(default_factory=dict)

    def records(self) -> list[dict[str, Any]]:
        return [r for result in self.results.values() for r in result.get("records", [])]


def fly_mission(
    plans: Mapping[str, Sequence[Task]],
    *,
    stack: str = "px4",
    lags: Mapping[tuple[str, int], float] | None = None,
    leave_at_task: Mapping[str, int] | None = None,
    timeout_s: float = 300.0,
) -> SyncRun:
    """Fly ``plans`` (vehicle name -> tasks). ``lags``: (vehicle, task) -> percent of
    speed while flying to that task; ``leave_at_task``: a vehicle's workload is stopped
    when it starts towards that task (as when a failover takes it out of the mission)."""
    lags = dict(lags or {})
    leaving = dict(leave_at_task or {})
    names = list(plans)
    sims = [
        SimulatedAutopilot.udp(stack, i + 1, name=name, config=SimConfig.fast()).start()
        for i, name in enumerate(names)
    ]
    stops = {name: threading.Event() for name in names}
    monitor_stop = threading.Event()
    channel = Channel()
    monitor = Monitor(channel, expected=len(names))
    results: dict[str, dict[str, Any]] = {}
    errors: list[BaseException] = []

    def hook(sim: SimulatedAutopilot, name: str) -> Any:
        lagging: dict[str, int | None] = {"task": None}

        def on_state(follower: Follower) -> None:
            task = follower.task if follower.phase is Phase.APPROACHING else None
            if task is not None and leaving.get(name) == task:
                stops[name].set()
            if lagging["task"] == task:
                return
            if lagging["task"] is not None:
                sim.clear(FaultKind.LAG)
                lagging["task"] = None
            if task is not None and (name, task) in lags:
                sim.inject(FaultKind.LAG, lags[(name, task)])
                lagging["task"] = task

        return on_state

    def follower(sim: SimulatedAutopilot, name: str) -> None:
        assert isinstance(sim.link, UdpLink)
        host, port = sim.link.local_address
        vehicle = MavlinkVehicle(f"udpout:{host}:{port}")
        try:
            vehicle.wait_connected()
            fly(name, plans[name], vehicle, channel.address, stops[name], on_state=hook(sim, name))
        except BaseException as error:  # reported to the caller
            errors.append(error)
        finally:
            vehicle.close()

    def run_monitor() -> None:
        results.update(monitor.run(monitor_stop))

    threads = [threading.Thread(target=run_monitor, name="sync-monitor", daemon=True)]
    threads += [
        threading.Thread(target=follower, args=(sim, name), name=f"sync-{name}", daemon=True)
        for sim, name in zip(sims, names, strict=True)
    ]
    try:
        for thread in threads:
            thread.start()
        for thread in threads[1:]:
            thread.join(timeout_s)
        threads[0].join(10)
        if errors:
            raise errors[0]
        if threads[0].is_alive():
            raise TimeoutError(f"the monitor did not finish: members {monitor.membership.members}")
        return SyncRun(results, {k: v for k, v in lags.items()})
    finally:
        monitor_stop.set()
        for stop in stops.values():
            stop.set()
        for sim in sims:
            sim.stop()
        channel.close()


def paper_plans() -> dict[str, list[Task]]:
    """The shipped trajectories: three drones, 20 s transits."""
    return {path.stem: load(path) for path in sorted(TRAJECTORIES.glob("*.csv"))}
