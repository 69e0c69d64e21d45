"""The onboard program: take off, fly the timed trajectory in sync with the others, land.

States: ``TakingOff`` -> ``ToStart`` (fly to the first task, say ``ready``) ->
``Following`` (the :class:`~syncpaths.sync.Follower` schedule, from the monitor's start
time) -> ``Landing`` -> ``Done``; ``Aborted`` on SIGTERM/SIGINT (the operator stops the
workload on an abort or when ``onFailover: AbortVehicle`` takes the vehicle out): it
tells the monitor it leaves and stops sending setpoints, and Roost's agent lands the
vehicle. Configuration from the environment (the Mission's pod template sets it; Roost
adds ``ROOST_MISSION_VEHICLES`` and ``ROOST_MISSION_VEHICLE_INDEX``):

- ``SYNC_VEHICLE`` (default: this vehicle's name from Roost's variables),
- ``SYNC_TRAJECTORY`` (a CSV file; default ``trajectories/<vehicle>.csv`` beside the
  package, or ``SYNC_TRAJECTORY_DIR``),
- ``SYNC_MONITOR`` (``host:port`` of the monitor, default ``127.0.0.1:7700``),
- ``MAVLINK_URL`` (default ``udpout:127.0.0.1:14550``, the Roost agent's hub).
"""

from __future__ import annotations

import logging
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from syncpaths.channel import Channel, bind_towards, parse_address
from syncpaths.sync import Follower, Phase
from syncpaths.trajectory import Point, Task, load
from syncpaths.vehicle import MavlinkVehicle, Vehicle

log = logging.getLogger("syncpaths.follower")
DEFAULT_MONITOR = "127.0.0.1:7700"
PERIOD_S = 0.05  # 20 Hz setpoints
HELLO_S = 0.5
PATH_SAMPLE_S = 0.5


def fly(
    name: str,
    tasks: Sequence[Task],
    vehicle: Vehicle,
    monitor: tuple[str, int],
    stop: threading.Event,
    *,
    on_state: Callable[[Follower], None] | None = None,
) -> dict[str, Any]:
    """Fly the mission; returns the result sent to the monitor (records and path)."""
    channel = Channel(bind_towards(monitor))
    path: list[tuple[float, ...]] = []
    follower: Follower | None = None
    state = "TakingOff"
    delays: dict[int, dict[str, float]] = {}
    members: list[str] = [name]
    reported: dict[int, float] = {}
    start_at: float | None = None
    last_hello = last_sample = 0.0

    def say(message: Mapping[str, Any]) -> None:
        channel.send({**message, "vehicle": name}, monitor)

    try:
        vehicle.take_off(-tasks[0].point[2])
        vehicle.fly_setpoints(tasks[0].point)
        state = "ToStart"
        while not stop.is_set():
            now = time.monotonic()
            for message, _ in channel.receive():
                kind = message.get("type")
                if kind == "start" and start_at is None:
                    start_at = now + float(message["at"]) - time.time()
                    follower = Follower(name, tasks, start=start_at)
                    state = "Following"
                elif kind == "members":
                    members = [str(v) for v in message["vehicles"]]
                elif kind == "pause":
                    task = int(message["task"])
                    delays.setdefault(task, {})[str(message["vehicle"])] = float(message["delay"])
                    if message["vehicle"] == name:
                        reported.pop(task, None)  # confirmed
            position = vehicle.position()
            if state == "ToStart":
                vehicle.send_setpoint(tasks[0].point)
            elif follower is not None:
                vehicle.send_setpoint(follower.setpoint(now))
                delay = follower.step(now, position)
                if delay is not None:  # say it now; repeated with the hellos until confirmed
                    reported[follower.task] = delay
                    say({"type": "delay", "task": follower.task, "delay": delay})
                task = follower.task
                follower.try_depart(now, delays.get(task, {}), members)
                if position is not None and now - last_sample >= PATH_SAMPLE_S:
                    path.append((round(now - follower.start, 2), *(round(v, 2) for v in position)))
                    last_sample = now
                if on_state is not None:
                    on_state(follower)
                if follower.phase is Phase.DONE:
                    break
            if now - last_hello >= HELLO_S:
                ready = state == "ToStart" and _near(position, tasks[0].point)
                say({"type": "hello", "ready": ready or state == "Following"})
                for task, delay in reported.items():  # repeated until confirmed
                    say({"type": "delay", "task": task, "delay": delay})
                last_hello = now
            time.sleep(PERIOD_S)
        result = {
            "type": "done" if follower is not None and follower.phase is Phase.DONE else "leave",
            "records": [asdict(r) for r in follower.records] if follower else [],
            "path": path,
            "plan": [[t.time_s, *t.point] for t in tasks],
        }
        for _ in range(3):  # datagrams: say it more than once
            say(result)
        if result["type"] == "done":
            vehicle.land()
        return result
    finally:
        channel.close()


def _near(position: Point | None, point: Point, radius_m: float = 0.5) -> bool:
    return position is not None and math.dist(position, point) <= radius_m


def _vehicle_name(env: Mapping[str, str]) -> str:
    if env.get("SYNC_VEHICLE"):
        return env["SYNC_VEHICLE"]
    vehicles = env.get("ROOST_MISSION_VEHICLES", "").split(",")
    index = int(env.get("ROOST_MISSION_VEHICLE_INDEX", "0"))
    return vehicles[index]


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    env = os.environ
    name = _vehicle_name(env)
    directory = Path(env.get("SYNC_TRAJECTORY_DIR", Path(__file__).parent.parent / "trajectories"))
    tasks = load(Path(env.get("SYNC_TRAJECTORY", directory / f"{name}.csv")))
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    url = env.get("MAVLINK_URL", "udpout:127.0.0.1:14550")
    log.info("%s: flying through %s, monitor %s", name, url, env.get("SYNC_MONITOR"))
    vehicle = MavlinkVehicle(url)
    try:
        vehicle.wait_connected()
        result = fly(
            name,
            tasks,
            vehicle,
            parse_address(env.get("SYNC_MONITOR", DEFAULT_MONITOR), 7700),
            stop,
        )
    finally:
        vehicle.close()
    log.info("%s: %s after %d tasks", name, result["type"], len(result["records"]))
    return 0 if result["type"] == "done" else 1


if __name__ == "__main__":
    raise SystemExit(main())
