"""Starting the sandbox's own programs (operator, agents, simulators) and stopping them.

Each is a :class:`roost_localcluster.processes.ManagedProcess`: its own session, a log file in
``<dir>/logs``, remembered by pid and start time, tied to ``roost sandbox up`` by the
parent-death signal (so even a SIGKILLed sandbox leaves nothing behind), and stopped by
signalling its own process group only. Nothing is ever looked up or killed by name:
other people run the same programs on this machine.
"""

from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Callable, Mapping
from pathlib import Path

from roost_cli.errors import CliError
from roost_localcluster.processes import ManagedProcess

STOP_GRACE_S = 5.0


def console_script(name: str) -> str:
    """Path of one of Roost's console scripts, installed next to this Python."""
    found = shutil.which(name, path=str(Path(sys.executable).parent)) or shutil.which(name)
    if found is None:
        raise CliError(f"`{name}` is not installed: run `make setup` (or `pip install -e .`)")
    return found


class Launcher:
    """Starts processes, remembers them, and reports each start to ``on_change``."""

    def __init__(self, logs_dir: Path, on_change: Callable[[], None]) -> None:
        self.logs_dir = logs_dir
        self.on_change = on_change
        self.processes: list[ManagedProcess] = []

    def start(self, name: str, argv: list[str], env: Mapping[str, str]) -> ManagedProcess:
        """Launch ``argv`` with ``env`` added to this environment; its output goes to a log."""
        proc = ManagedProcess(name, argv, self.logs_dir / f"{name}.log")
        proc.launch({**os.environ, **env}, die_with_parent=True)
        self.processes.append(proc)
        self.on_change()
        return proc

    def dead(self) -> list[ManagedProcess]:
        """Processes that have exited although nobody stopped them."""
        return [proc for proc in self.processes if not proc.alive()]

    def stop(self, proc: ManagedProcess) -> None:
        """Stop one process (SIGTERM, then SIGKILL after the grace) and forget it."""
        proc.stop(grace_s=STOP_GRACE_S)
        self.processes.remove(proc)
        self.on_change()

    def stop_all(self) -> list[int]:
        """Stop every process, newest first; returns the pids stopped.

        All are asked to stop before any is waited for: 25 vehicles are 50 processes,
        and one grace period after another would outlast ``roost sandbox down``'s patience.
        """
        pids = [proc.pid for proc in self.processes if proc.pid is not None]
        for proc in reversed(self.processes):
            proc.terminate()
        for proc in reversed(self.processes):
            proc.stop(grace_s=STOP_GRACE_S)
        self.processes.clear()
        self.on_change()
        return pids

    def states(self) -> list[dict[str, object]]:
        return [proc.to_state() for proc in self.processes]
