"""Running a mission's own programs in the sandbox: the ``sync-paths`` reference mission.

The sandbox applies the mission's own manifest (``mission.yaml``: the Mission and the
monitor's Service), so the operator claims, preflights and follows the vehicles as it
would in a cluster. On KWOK nodes no container runs, so the sandbox plays the pods
itself: one onboard follower per vehicle and one offboard monitor, as local processes
with the environment the Mission's pods would get. The followers reach the monitor over
UDP on 127.0.0.1 (in a cluster the same address is a Service) and their vehicle at its
agent's MAVLink hub, as on a real vehicle: a failover moves the hub's route, never the
follower's connection. When the operator takes a vehicle out of the Mission (an abort,
or ``onFailover: AbortVehicle``) it would stop that vehicle's pod; the sandbox stops the
follower (:func:`vehicles_out`), which tells the monitor it leaves, so the others do not
wait for it. ``lag`` faults on a time schedule slow chosen vehicles on chosen legs, so
the monitor has delays like the paper's Table I to absorb; the schedule follows the legs
of the trajectories flown (the mission's own, or another directory of them: a shorter
flight for tests).

Pure except :class:`LagInjector`, so the processes, manifests and schedule are
unit-tested without a cluster.
"""

from __future__ import annotations

import csv
import json
import sys
import threading
import time
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from roost_api.mission import MissionVehiclePhase

SYNC_PATHS = "sync-paths"
MISSIONS = (SYNC_PATHS,)
REPO_ROOT = Path(__file__).resolve().parents[3]
EXAMPLE_DIR = REPO_ROOT / "examples" / "missions" / SYNC_PATHS
START_DELAY_S = 2.0
"""The monitor starts the vehicles this long after it says so (``syncpaths.monitor``)."""
LAG_OVERRUN_S = 4.0
"""A lag lasts this much past its leg's planned arrival: the slowed vehicle arrives late
(at a quarter of PX4's 5 m/s a 30 m leg planned for 20 s takes about 24 s), and earlier
delays shift a leg later than its planned time, which the schedule counts in (a few
seconds: on 6 s legs without this margin a fourth leg's lag would end before most of the
leg was flown). The next leg is flown at speed once it ends."""
STARTING_MARK = "starting "
"""What the monitor logs when every vehicle is ready: the legs' clock starts."""


@dataclass(frozen=True)
class Program:
    """One mission process: its name, command line and environment."""

    name: str
    argv: tuple[str, ...]
    env: Mapping[str, str]


@dataclass(frozen=True)
class Lag:
    """Slow ``vehicle`` to ``percent`` of its speed from ``start_s`` for ``duration_s``."""

    vehicle: str
    start_s: float
    duration_s: float
    percent: float


# (vehicle, leg) -> percent of the normal speed on that leg: delays of 1.5 to 6 s
LAG_LEGS: dict[tuple[str, int], float] = {
    ("drone-1", 1): 23.0,
    ("drone-2", 2): 26.0,
    ("drone-3", 3): 28.0,
    ("drone-1", 4): 25.0,
}


def task_times(path: Path) -> list[float]:
    """The planned times of a trajectory file's tasks: its first column, a header row
    skipped (the follower reads the whole file, ``syncpaths.trajectory``)."""
    times: list[float] = []
    with path.open(newline="") as f:
        for row in csv.reader(f):
            if not row or not row[0].strip():
                continue
            try:
                times.append(float(row[0]))
            except ValueError:
                if times:
                    raise ValueError(f"{path}: task time {row[0]!r} is not a number") from None
    return times


def lag_schedule(
    vehicles: tuple[str, ...], trajectories: Path = EXAMPLE_DIR / "trajectories"
) -> tuple[Lag, ...]:
    """Lags for the legs in :data:`LAG_LEGS` flown by ``vehicles``, by planned time.

    Times count from the monitor's start mark: leg k is planned from task k-1's time to
    task k's in the vehicle's trajectory (``<vehicle>.csv`` in ``trajectories``); the lag
    lasts the leg and :data:`LAG_OVERRUN_S` more (earlier delays shift later legs by a
    few seconds, which only moves where it bites). A leg the trajectory has not gets none.
    """
    lags = []
    for (vehicle, leg), percent in LAG_LEGS.items():
        if vehicle not in vehicles:
            continue
        times = task_times(trajectories / f"{vehicle}.csv")
        if leg < len(times):
            start, end = times[leg - 1], times[leg]
            lags.append(Lag(vehicle, START_DELAY_S + start, end - start + LAG_OVERRUN_S, percent))
    return tuple(sorted(lags, key=lambda lag: lag.start_s))


OUT_OF_MISSION = frozenset(
    {MissionVehiclePhase.ABORTING, MissionVehiclePhase.ABORTED, MissionVehiclePhase.FAILED}
)
"""Phases in which the operator has stopped (or is stopping) a vehicle's onboard pod."""


def pymavlink_url(connection: str) -> str:
    """``udpout://127.0.0.1:P`` (a simulator's report) as pymavlink spells it."""
    return connection.replace("://", ":", 1)


def hub_url(hub: str) -> str:
    """pymavlink's URL for a client of the agent's hub at ``HOST:PORT``."""
    return f"udpout:{hub}"


def mission_manifests(
    mission: str, count: int, runtime: Mapping[str, str], example_dir: Path = EXAMPLE_DIR
) -> list[dict[str, Any]]:
    """The mission's own ``mission.yaml`` for a sandbox of ``count`` vehicles.

    Changed only where the sandbox differs from a cluster: the Mission asks for ``count``
    vehicles, and its pod templates carry ``runtime`` (KWOK's annotations for how long
    the pods it plays run).
    """
    check(mission, [], example_dir)
    documents = [
        doc
        for doc in yaml.safe_load_all((example_dir / "mission.yaml").read_text())
        if doc is not None
    ]
    for doc in documents:
        if doc.get("kind") != "Mission":
            continue
        spec = doc["spec"]
        spec["vehicles"]["count"] = count
        for workload in ("onboard", "offboard"):
            if spec.get(workload) is not None:
                metadata = spec[workload].setdefault("metadata", {})
                metadata.setdefault("annotations", {}).update(runtime)
    return documents


def mission_ref(documents: list[dict[str, Any]]) -> tuple[str, str]:
    """(namespace, name) of the Mission among ``documents``."""
    for doc in documents:
        if doc.get("kind") == "Mission":
            meta = doc["metadata"]
            return str(meta.get("namespace", "default")), str(meta["name"])
    raise ValueError("the mission's manifest has no Mission")


def vehicles_out(mission: Mapping[str, Any]) -> set[str]:
    """Vehicles the Mission has taken out (their onboard pods stop), from its status."""
    status = mission.get("status") or {}
    return {
        str(entry["name"])
        for entry in status.get("vehicles") or []
        if entry.get("phase") in OUT_OF_MISSION
    }


LISTENING_KEY = "listening"
"""The monitor's first stdout line, ``{"listening": "HOST:PORT"}``: it binds port 0 itself."""


def check(
    mission: str,
    vehicles: Collection[str],
    example_dir: Path = EXAMPLE_DIR,
    trajectories: Path | None = None,
) -> Path:
    """The trajectory directory (``trajectories``, else the mission's own), or ValueError
    saying why the mission cannot run."""
    if mission not in MISSIONS:
        raise ValueError(f"unknown mission {mission!r}: one of {', '.join(MISSIONS)}")
    if trajectories is None:
        trajectories = example_dir / "trajectories"
    elif not trajectories.is_dir():
        raise ValueError(f"{trajectories} is not a directory of trajectories (<vehicle>.csv)")
    missing = [name for name in vehicles if not (trajectories / f"{name}.csv").is_file()]
    if missing:
        have = len(list(trajectories.glob("*.csv")))
        raise ValueError(
            f"{mission} has no trajectory for {', '.join(missing)} (in {trajectories}): "
            f"run it with at most {have} vehicles"
        )
    return trajectories


def _common(example_dir: Path, vehicles: Collection[str]) -> dict[str, str]:
    return {
        "PYTHONPATH": str(example_dir),
        "PYTHONUNBUFFERED": "1",
        "ROOST_MISSION_VEHICLES": ",".join(vehicles),
    }


def monitor_program(
    mission: str,
    vehicles: Collection[str],
    output: Path,
    example_dir: Path = EXAMPLE_DIR,
    trajectories: Path | None = None,
) -> Program:
    """The offboard monitor, on a port it chooses (see :data:`LISTENING_KEY`), for the
    followers of :func:`follower_programs` (the same ``trajectories``)."""
    check(mission, vehicles, example_dir, trajectories)
    return Program(
        "sync-monitor",
        (sys.executable, "-m", "syncpaths.monitor"),
        {
            **_common(example_dir, vehicles),
            "SYNC_LISTEN": "127.0.0.1:0",
            "SYNC_VEHICLES": str(len(vehicles)),
            "SYNC_OUTPUT": str(output),
        },
    )


def follower_programs(
    mission: str,
    connections: Mapping[str, str],
    monitor: str,
    example_dir: Path = EXAMPLE_DIR,
    trajectories: Path | None = None,
) -> tuple[Program, ...]:
    """One onboard follower per vehicle (name -> pymavlink URL of its vehicle: the agent's
    hub, see :func:`hub_url`); ``trajectories``: another directory of ``<vehicle>.csv``
    than the mission's own."""
    trajectories = check(mission, list(connections), example_dir, trajectories)
    return tuple(
        Program(
            f"sync-follower-{name}",
            (sys.executable, "-m", "syncpaths.follower"),
            {
                **_common(example_dir, list(connections)),
                "SYNC_VEHICLE": name,
                "SYNC_TRAJECTORY_DIR": str(trajectories),
                "SYNC_MONITOR": monitor,
                "MAVLINK_URL": connection,
            },
        )
        for name, connection in connections.items()
    )


def started(log_text: str) -> bool:
    """Whether the monitor has started the vehicles (its legs' clock runs)."""
    return any(STARTING_MARK in line for line in log_text.splitlines())


def listening_address(log_text: str) -> str | None:
    """The monitor's address from its log, once it has said it."""
    for line in log_text.splitlines():
        if LISTENING_KEY not in line:
            continue
        try:
            said = json.loads(line)
        except ValueError:
            continue
        if isinstance(said, dict) and isinstance(said.get(LISTENING_KEY), str):
            return str(said[LISTENING_KEY])
    return None


class LagInjector(threading.Thread):
    """Injects and clears the scheduled lags through ``send(vehicle, message)``, counting
    from when ``has_started()`` first says so (polled every :data:`POLL_S`)."""

    POLL_S = 0.2

    def __init__(
        self,
        schedule: tuple[Lag, ...],
        send: Callable[[str, dict[str, object]], None],
        stop: threading.Event,
        has_started: Callable[[], bool] = lambda: True,
    ) -> None:
        super().__init__(name="sandbox-lags", daemon=True)
        self.schedule = schedule
        self.send = send
        self.stop_event = stop
        self.has_started = has_started
        self.sent: list[tuple[float, str, dict[str, object]]] = []
        self.failed: list[tuple[str, str]] = []

    def run(self) -> None:
        while not self.has_started():
            if self.stop_event.wait(self.POLL_S):
                return
        start = time.monotonic()
        events = sorted(
            [
                (lag.start_s, lag.vehicle, {"op": "fault", "kind": "lag", "value": lag.percent})
                for lag in self.schedule
            ]
            + [
                (lag.start_s + lag.duration_s, lag.vehicle, {"op": "clear", "kind": "lag"})
                for lag in self.schedule
            ],
            key=lambda event: event[0],
        )
        for at, vehicle, message in events:
            if self.stop_event.wait(max(0.0, start + at - time.monotonic())):
                return
            try:
                self.send(vehicle, message)
            except Exception as error:  # a vehicle gone (failover, stop) is no error here
                self.failed.append((vehicle, str(error)))
                continue
            self.sent.append((time.monotonic() - start, vehicle, message))
