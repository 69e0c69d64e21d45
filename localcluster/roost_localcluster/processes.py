"""Start and stop exactly our own processes.

Other engineers run the same programs (etcd, kube-apiserver, ...) on this machine at the same
time, so nothing here ever looks a process up by name. Each component is started in its own
session (so its process group id is its pid) and is remembered by pid *and* start time; a
stop signals that group only when the pid still belongs to the process we started, escalates
SIGTERM to SIGKILL, and waits until it is gone.

``die_with_parent`` asks Linux (``PR_SET_PDEATHSIG``) to SIGKILL the child when the
thread that started it exits. Pytest sessions use it, so even a SIGKILLed test run leaves no
control plane behind; ``roost-cluster up`` does not, because its whole point is to outlive
the command. SIGKILL rather than SIGTERM: this is the emergency path, the data is thrown
away, and a gracefully stopping API server whose etcd vanished at the same moment takes
over ten seconds to give up.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import subprocess
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil

_PR_SET_PDEATHSIG = 1
STOP_GRACE_S = 10.0


def _set_parent_death_signal() -> None:  # runs in the child between fork and exec
    ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)


@dataclass
class ManagedProcess:
    """One started program: its command line, log file and identity (pid + start time)."""

    name: str
    argv: list[str]
    log: Path
    pid: int | None = None
    create_time: float | None = None
    returncode: int | None = None  # how the last run ended (negative: killed by a signal)
    _popen: subprocess.Popen[bytes] | None = field(default=None, repr=False, compare=False)

    def launch(self, env: Mapping[str, str] | None = None, die_with_parent: bool = False) -> None:
        """Start the program, appending its stdout and stderr to :attr:`log`."""
        self.log.parent.mkdir(parents=True, exist_ok=True)
        with self.log.open("ab") as log:
            log.write(f"\n==> {time.strftime('%H:%M:%S')} {' '.join(self.argv)}\n".encode())
            log.flush()
            self._popen = subprocess.Popen(
                self.argv,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                env=dict(env) if env is not None else None,
                start_new_session=True,
                preexec_fn=_set_parent_death_signal if die_with_parent else None,  # noqa: PLW1509
            )
        self.pid = self._popen.pid
        try:
            self.create_time = psutil.Process(self.pid).create_time()
        except psutil.NoSuchProcess:
            self.create_time = None

    def _process(self) -> psutil.Process | None:
        """The running process if ``pid`` is still ours (same start time, not a zombie)."""
        if self.pid is None:
            return None
        try:
            proc = psutil.Process(self.pid)
            if self.create_time is not None and abs(proc.create_time() - self.create_time) > 0.01:
                return None
            if proc.status() == psutil.STATUS_ZOMBIE:
                return None
        except psutil.NoSuchProcess:
            return None
        return proc

    def alive(self) -> bool:
        if self._popen is not None and self._popen.poll() is not None:
            return False
        return self._process() is not None

    def rss_bytes(self) -> int:
        proc = self._process()
        if proc is None:
            return 0
        with contextlib.suppress(psutil.NoSuchProcess):
            return int(proc.memory_info().rss)
        return 0

    def terminate(self) -> None:
        """SIGTERM the process group and return at once (:meth:`stop` waits for the end).

        Stopping many processes, terminate them all first: each then shuts down while the
        others do, instead of one grace period after another.
        """
        if self._process() is not None:
            self._signal_group(signal.SIGTERM)

    def stop(self, grace_s: float = STOP_GRACE_S) -> None:
        """SIGTERM the process group, SIGKILL it after ``grace_s``, and wait for the end.

        :attr:`returncode` is how it ended. psutil's wait reaps the child itself, after
        which ``Popen.wait`` can only answer 0, so psutil's code is kept when it has one.
        """
        self.returncode = None
        proc = self._process()
        if proc is not None:
            self._signal_group(signal.SIGTERM)
            gone, alive = psutil.wait_procs([proc], timeout=grace_s)
            if alive:
                self._signal_group(signal.SIGKILL)
                killed, _ = psutil.wait_procs(alive, timeout=grace_s)
                gone += killed
            codes = [p.returncode for p in gone if getattr(p, "returncode", None) is not None]
            if codes:
                self.returncode = int(codes[0])
        if self._popen is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                code = self._popen.wait(timeout=grace_s)
                if self.returncode is None:
                    self.returncode = code
        self._popen = None
        self.pid = None
        self.create_time = None

    def crash(self) -> None:
        """SIGKILL the process group at once (no shutdown handlers, like a power loss)."""
        if self._process() is not None:
            self._signal_group(signal.SIGKILL)
        self.stop()

    def _signal_group(self, sig: signal.Signals) -> None:
        assert self.pid is not None
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.pid, sig)

    def to_state(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "argv": self.argv,
            "log": str(self.log),
            "pid": self.pid,
            "create_time": self.create_time,
        }

    @classmethod
    def from_state(cls, state: Mapping[str, Any]) -> ManagedProcess:
        return cls(
            name=state["name"],
            argv=list(state["argv"]),
            log=Path(state["log"]),
            pid=state["pid"],
            create_time=state["create_time"],
        )

    def log_tail(self, lines: int = 30) -> str:
        try:
            return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:])
        except FileNotFoundError:
            return "(no log)"
