"""A ``roost sandbox up`` subprocess, as a user starts it, for the end-to-end tests.

:func:`running_sandbox` starts the real CLI (control plane, operator, agents, simulated
autopilots, the dashboard) in a directory of the test's own and stops it with
``roost sandbox down`` afterwards, whatever happened; :class:`RunningSandbox` plays the
user in a second terminal (``roost`` commands, kubectl).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from roost_cli.sandbox import state as sandbox_state
from roost_cli.sandbox.director import vehicle_ready

BIN = Path(sys.executable).parent
UP_TIMEOUT_S = 240.0


@dataclass
class RunningSandbox:
    """A `roost sandbox up` subprocess and how to talk to what it started."""

    directory: Path
    process: subprocess.Popen[str]
    output: Path

    def roost(self, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        env = {**os.environ, "COLUMNS": "220", sandbox_state.DIR_ENV: str(self.directory)}
        env.pop("KUBECONFIG", None)
        return subprocess.run(
            [str(BIN / "roost"), *args],
            capture_output=True,
            text=True,
            timeout=120,
            check=check,
            env=env,
        )

    def kubectl(self, *args: str) -> str:
        recorded = sandbox_state.load(self.directory)
        assert recorded is not None and recorded.kubeconfig is not None
        return subprocess.run(
            [str(BIN / "kubectl"), "--kubeconfig", recorded.kubeconfig, *args],
            capture_output=True,
            text=True,
            timeout=60,
            check=True,
        ).stdout

    def get(self, kind: str, name: str, namespace: str | None = None) -> dict[str, Any]:
        scope = ["-n", namespace] if namespace else []
        obj: dict[str, Any] = json.loads(self.kubectl("get", kind, name, *scope, "-o", "json"))
        return obj

    def log(self) -> str:
        return self.output.read_text(errors="replace")

    def ready_vehicles(self) -> set[str]:
        """Names of the Vehicles whose ``Ready`` condition is True now (none while the API
        server is too busy to answer: a loaded machine is no failure)."""
        try:
            listed = json.loads(self.kubectl("get", "vehicles", "-o", "json"))
        except (subprocess.CalledProcessError, subprocess.TimeoutExpired):
            return set()
        return {v["metadata"]["name"] for v in listed["items"] if vehicle_ready(v)}

    def failovers(self) -> dict[str, list[dict[str, Any]]]:
        """Each vehicle's failovers as its agent logged them (``{"event": "Failover"…}``).

        A record has ``onsetToSwitchMs``: the agent's own onset-to-switch time.
        """
        found: dict[str, list[dict[str, Any]]] = {}
        for log in sorted((self.directory / "logs").glob(f"{AGENT_LOG_PREFIX}*.log")):
            vehicle = log.stem.removeprefix(AGENT_LOG_PREFIX)
            for line in log.read_text(errors="replace").splitlines():
                if line.startswith('{"event": "Failover"'):
                    with contextlib.suppress(ValueError):
                        found.setdefault(vehicle, []).append(json.loads(line))
        return found


AGENT_LOG_PREFIX = "roost-agent-"


def recorded_processes(directory: Path) -> dict[int, float]:
    """pid → start time of every process the sandbox recorded, itself included."""
    recorded = sandbox_state.load(directory)
    assert recorded is not None
    found = {recorded.pid: recorded.create_time}
    found |= {p["pid"]: p["create_time"] for p in recorded.processes if p["pid"]}
    plane = json.loads((recorded.cluster_dir / "state.json").read_text())
    found |= {p["pid"]: p["create_time"] for p in plane["processes"] if p["pid"]}
    return found


def still_running(identities: dict[int, float]) -> list[int]:
    """The pids of ``identities`` (pid → start time) that are still the same process."""
    return [pid for pid, started in identities.items() if sandbox_state.process_alive(pid, started)]


def await_step(
    what: str, check: Callable[[], bool], sandbox: RunningSandbox, timeout_s: float
) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        if sandbox.process.poll() is not None:
            pytest.fail(f"roost sandbox up exited while waiting for {what}:\n{sandbox.log()}")
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s:.0f} s waiting for {what}:\n{sandbox.log()}")
        time.sleep(0.5)


def await_running(sandbox: RunningSandbox) -> sandbox_state.SandboxState:
    """Wait until ``roost sandbox up`` says it is running; its recorded state."""

    def up() -> bool:
        recorded = sandbox_state.load(sandbox.directory)
        return recorded is not None and recorded.phase == sandbox_state.Phase.RUNNING

    await_step("the sandbox to be running", up, sandbox, UP_TIMEOUT_S)
    recorded = sandbox_state.load(sandbox.directory)
    assert recorded is not None
    return recorded


@contextlib.contextmanager
def running_sandbox(tmp_path: Path, args: Sequence[str]) -> Iterator[RunningSandbox]:
    """``roost sandbox up ARGS`` in ``tmp_path``; stopped (and waited for) on exit."""
    directory = tmp_path / "sandbox"
    output = tmp_path / "sandbox-up.log"
    with output.open("w") as out:
        process = subprocess.Popen(
            [str(BIN / "roost"), "--sandbox-dir", str(directory), "sandbox", "up", *args],
            stdout=out,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, "COLUMNS": "200"},
        )
    running = RunningSandbox(directory, process, output)
    try:
        yield running
    finally:
        if process.poll() is None:
            with contextlib.suppress(subprocess.SubprocessError):
                running.roost("sandbox", "down", check=False)
        if process.poll() is None:
            process.send_signal(signal.SIGKILL)
        process.wait(timeout=30)
