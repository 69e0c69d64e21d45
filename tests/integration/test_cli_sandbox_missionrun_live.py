"""``roost sandbox up --mission`` with real parts: the real monitor reports the port it
bound, and the lag injector's thread injects and clears lag on schedule.

Which programs run with which environment is in ``tests/unit/test_cli_sandbox_missionrun.py``.
"""

from __future__ import annotations

import subprocess
import threading
import time
from pathlib import Path

from roost_cli.sandbox import missionrun
from roost_cli.sandbox.missionrun import Lag, LagInjector

NAMES = ["drone-1", "drone-2", "drone-3"]


def test_the_real_monitor_reports_the_port_it_bound(tmp_path: Path) -> None:
    program = missionrun.monitor_program(missionrun.SYNC_PATHS, NAMES, tmp_path / "out")
    proc = subprocess.Popen(
        list(program.argv),
        env={**program.env, "PATH": "/usr/bin:/bin"},
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert proc.stdout is not None
        address = missionrun.listening_address(proc.stdout.readline())
        assert address is not None
        host, _, port = address.rpartition(":")
        assert host == "127.0.0.1" and int(port) > 0
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_lag_injector_injects_then_clears_and_survives_a_gone_vehicle() -> None:
    got: list[tuple[str, dict[str, object]]] = []

    def send(vehicle: str, message: dict[str, object]) -> None:
        if vehicle == "gone":
            raise RuntimeError("its simulator is not there")
        got.append((vehicle, message))

    stop = threading.Event()
    schedule = (Lag("gone", 0.0, 0.01, 50.0), Lag("drone-1", 0.02, 0.05, 25.0))
    injector = LagInjector(schedule, send, stop)
    injector.start()
    deadline = time.monotonic() + 30
    while len(got) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    injector.join(timeout=30)
    assert injector.failed == [("gone", "its simulator is not there")] * 2
    assert got == [
        ("drone-1", {"op": "fault", "kind": "lag", "value": 25.0}),
        ("drone-1", {"op": "clear", "kind": "lag"}),
    ]


def test_lag_injector_stops_when_told() -> None:
    stop = threading.Event()
    injector = LagInjector((Lag("drone-1", 3600.0, 1.0, 50.0),), lambda *_: None, stop)
    injector.start()
    stop.set()
    injector.join(timeout=30)
    assert not injector.is_alive() and injector.sent == []


def test_lag_clock_starts_when_the_monitor_starts_the_vehicles() -> None:
    assert not missionrun.started("drone-1 joined\n")
    assert missionrun.started("x syncpaths.monitor: starting 3 vehicles in 2 s\n")
    log = {"text": ""}
    got: list[str] = []
    stop = threading.Event()
    injector = LagInjector(
        (Lag("drone-1", 0.0, 3600.0, 50.0),),
        lambda vehicle, _message: got.append(vehicle),
        stop,
        lambda: missionrun.started(log["text"]),
    )
    injector.start()
    assert not stop.wait(3 * LagInjector.POLL_S)  # nothing happens for 3 polls: not started
    assert got == []
    log["text"] = "starting 3 vehicles in 2 s"
    deadline = time.monotonic() + 30
    while not got and time.monotonic() < deadline:
        time.sleep(0.01)
    stop.set()
    injector.join(timeout=30)
    assert got == ["drone-1"]
