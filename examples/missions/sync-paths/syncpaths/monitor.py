"""The offboard program: the central synchronisation monitor.

It learns the vehicles from their ``hello`` messages, starts the mission (a common start
time a couple of seconds ahead) once ``SYNC_VEHICLES`` of them are at their start
points, forwards every reported delay to every vehicle (``pause``), keeps the member
list (a vehicle that says ``leave`` or is silent for ``silent_after_s`` is dropped, and
the others stop waiting for it), and when every vehicle is done or gone writes the
results: ``table.md`` (the paper's Table I layout), ``results.json`` and ``paths.svg``
into ``SYNC_OUTPUT`` (default ``./sync-results``), and the same results to stdout, Table I
then one JSON line ``{"results": ...}``: a finished pod keeps nothing but its log, so
that is where a cluster's run is read back from (``kubectl logs``; :func:`results_from_log`).
Listens on ``SYNC_LISTEN`` (default ``0.0.0.0:7700`` in a pod behind a Service; the
sandbox uses ``127.0.0.1``).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

from syncpaths.channel import Channel, Message, parse_address
from syncpaths.sync import Membership
from syncpaths.table import table, write_results

log = logging.getLogger("syncpaths.monitor")
START_DELAY_S = 2.0
BROADCAST_S = 0.5


class Monitor:
    """The monitor's state machine over one :class:`Channel`."""

    def __init__(self, channel: Channel, expected: int, *, silent_after_s: float = 3.0) -> None:
        self.channel = channel
        self.expected = expected
        self.membership = Membership(silent_after_s=silent_after_s)
        self.addresses: dict[str, tuple[str, int]] = {}
        self.ready: set[str] = set()
        self.start_at: float | None = None
        self.delays: dict[int, dict[str, float]] = {}
        self.results: dict[str, dict[str, Any]] = {}
        self._last_broadcast = 0.0

    def broadcast(self, message: Message) -> None:
        for vehicle in self.membership.members:
            self.channel.send(message, self.addresses[vehicle])

    def handle(self, message: Message, sender: tuple[str, int], now: float) -> None:
        vehicle = str(message.get("vehicle", ""))
        if not vehicle or vehicle in self.results:
            return
        kind = message["type"]
        if kind in ("leave", "done"):
            self.results[vehicle] = message
            if self.membership.leave(vehicle):
                log.info("%s %s", vehicle, "is done" if kind == "done" else "left the mission")
                self.broadcast({"type": "members", "vehicles": self.membership.members})
            return
        self.addresses[vehicle] = sender
        if self.membership.heard(vehicle, now):
            log.info("%s joined", vehicle)
        if kind == "hello" and message.get("ready"):
            self.ready.add(vehicle)
        elif kind == "delay":
            task, delay = int(message["task"]), float(message["delay"])
            if vehicle not in self.delays.setdefault(task, {}):
                log.info("%s: delay %.1f s at task %d", vehicle, delay, task)
            self.delays[task][vehicle] = delay
            self.broadcast({"type": "pause", "vehicle": vehicle, "task": task, "delay": delay})

    def tick(self, now: float) -> None:
        gone = self.membership.expire(now)
        for vehicle in gone:
            log.info("%s fell silent: nobody waits for it any more", vehicle)
            self.results.setdefault(vehicle, {"type": "silent", "records": [], "path": []})
        if (
            self.start_at is None
            and len(self.ready & set(self.membership.members)) >= self.expected
        ):
            self.start_at = time.time() + START_DELAY_S
            log.info("starting %d vehicles in %.0f s", self.expected, START_DELAY_S)
        if gone or now - self._last_broadcast >= BROADCAST_S:
            self.broadcast({"type": "members", "vehicles": self.membership.members})
            if self.start_at is not None:
                self.broadcast({"type": "start", "at": self.start_at})
            self._last_broadcast = now

    @property
    def finished(self) -> bool:
        return self.start_at is not None and not self.membership.members and bool(self.results)

    def run(self, stop: threading.Event, period_s: float = 0.02) -> dict[str, dict[str, Any]]:
        while not stop.is_set() and not self.finished:
            now = time.monotonic()
            for message, sender in self.channel.receive():
                self.handle(message, sender, now)
            self.tick(now)
            time.sleep(period_s)
        return self.results


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    env = os.environ
    expected = int(
        env.get("SYNC_VEHICLES") or len(env.get("ROOST_MISSION_VEHICLES", "x").split(","))
    )
    channel = Channel(parse_address(env.get("SYNC_LISTEN", "0.0.0.0:7700"), 7700))
    host, port = channel.address
    print(json.dumps({"listening": f"{host}:{port}"}), flush=True)  # when the port was 0
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    try:
        results = Monitor(channel, expected).run(stop)
    finally:
        channel.close()
    output = Path(env.get("SYNC_OUTPUT", "sync-results"))
    write_results(results, output)
    print(table(results), flush=True)
    print(json.dumps({RESULTS_KEY: results}), flush=True)
    print(json.dumps({"vehicles": sorted(results), "output": str(output)}))
    return 0


RESULTS_KEY = "results"


def results_from_log(text: str) -> dict[str, dict[str, Any]] | None:
    """The results a monitor printed to its log (``{"results": ...}``), once it has."""
    for line in reversed(text.splitlines()):
        if not line.startswith("{"):
            continue
        try:
            said = json.loads(line)
        except ValueError:
            continue
        if isinstance(said, dict) and isinstance(said.get(RESULTS_KEY), dict):
            found: dict[str, dict[str, Any]] = said[RESULTS_KEY]
            return found
    return None


if __name__ == "__main__":
    raise SystemExit(main())
