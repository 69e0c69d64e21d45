"""The sandbox's state file: what is running, so other ``roost`` commands can find it.

``roost sandbox up`` writes ``<dir>/state.json`` as soon as it starts anything and keeps
it current. It records

- the ``roost sandbox up`` process itself (pid and start time),
- every process it started (operator, agents, simulated autopilots) by pid and start time,
  the control plane's own processes being recorded by the harness in ``<dir>/cluster``,
- the kubeconfig, and each vehicle's simulated autopilots with the connection URL each
  reported (the port it bound itself) and their control sockets,

so ``roost status`` finds the cluster, ``roost fault`` finds a simulator's control port,
and ``roost sandbox down`` (another terminal) stops exactly those processes. Pids alone
are not identities (they are reused), hence the start times, compared by the harness's
:class:`~roost_localcluster.processes.ManagedProcess`.
"""

from __future__ import annotations

import contextlib
import os
from enum import StrEnum
from pathlib import Path
from typing import Any

import psutil
from pydantic import BaseModel, Field

STATE_FILE = "state.json"
DEFAULT_DIR = Path(".sandbox")
DIR_ENV = "ROOST_SANDBOX_DIR"


class Phase(StrEnum):
    """Where ``roost sandbox up`` is."""

    STARTING = "Starting"
    RUNNING = "Running"
    STOPPING = "Stopping"


class SimulatedAutopilot(BaseModel):
    """One simulated autopilot process and how to reach it."""

    name: str
    stack: str
    sysid: int
    connection: str
    """``AutopilotSpec.connection`` the simulator reported for the port it bound itself."""
    bridge_channel: int
    control: str
    """The simulator's control socket (faults, take-off); see :mod:`roost_sim.control`."""


class SandboxVehicle(BaseModel):
    """One simulated vehicle of the sandbox."""

    name: str
    node: str
    stack: str
    autopilots: list[SimulatedAutopilot]
    hub: str | None = None
    """``HOST:PORT`` of the agent's MAVLink hub: connect a client (MAVProxy, a mission) here."""
    telemetry: str | None = None
    """The agent's telemetry stream (``ws://127.0.0.1:P/``), once it announced it."""


class SandboxState(BaseModel):
    """The contents of ``state.json``."""

    pid: int
    create_time: float
    phase: Phase = Phase.STARTING
    directory: str
    kubeconfig: str | None = None
    server: str | None = None
    processes: list[dict[str, Any]] = Field(default_factory=list)
    """``ManagedProcess.to_state()`` of each process the sandbox started itself."""
    vehicles: list[SandboxVehicle] = Field(default_factory=list)
    dashboard: str | None = None
    """The URL ``roost dashboard`` serves the sandbox on, once it announced it."""

    @property
    def cluster_dir(self) -> Path:
        return Path(self.directory) / "cluster"

    def vehicle(self, name: str) -> SandboxVehicle | None:
        return next((v for v in self.vehicles if v.name == name), None)


def sandbox_dir(explicit: Path | None = None) -> Path:
    """``--dir``, else ``$ROOST_SANDBOX_DIR``, else ``./.sandbox``; always absolute."""
    chosen = explicit or Path(os.environ.get(DIR_ENV) or DEFAULT_DIR)
    return chosen.resolve()


def load(directory: Path) -> SandboxState | None:
    """The recorded state, or None when no sandbox was ever started in ``directory``."""
    path = directory / STATE_FILE
    try:
        return SandboxState.model_validate_json(path.read_text())
    except FileNotFoundError:
        return None


def save(state: SandboxState) -> None:
    """Write atomically, so a reader never sees half a file."""
    directory = Path(state.directory)
    directory.mkdir(parents=True, exist_ok=True)
    tmp = directory / f".{STATE_FILE}.tmp"
    tmp.write_text(state.model_dump_json(indent=2) + "\n")
    tmp.replace(directory / STATE_FILE)


def remove(directory: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        (directory / STATE_FILE).unlink()


def process_alive(pid: int, create_time: float) -> bool:
    """True when ``pid`` is still the process that started at ``create_time``."""
    try:
        proc = psutil.Process(pid)
        same = abs(float(proc.create_time()) - create_time) < 0.01
        return same and bool(proc.status() != psutil.STATUS_ZOMBIE)
    except psutil.NoSuchProcess:
        return False


def running(directory: Path) -> SandboxState | None:
    """The state of a sandbox whose ``roost sandbox up`` is still alive, else None."""
    state = load(directory)
    if state is None or not process_alive(state.pid, state.create_time):
        return None
    return state
