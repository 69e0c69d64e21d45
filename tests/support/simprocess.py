"""Simulated autopilots in a process of their own, at real-time priority: stand-ins for
flight controllers that the companion computer's load cannot stall.

Why: a real autopilot is a separate microcontroller; however busy the companion computer
is, its stream keeps its rhythm. Simulated autopilots that share a process (and its
interpreter lock) or just the CPU with a busy host stall with it, and their stalls look
to the agent exactly like an autopilot going silent. A benchmark that starves the host to
measure the AGENT must not starve what stands for the autopilots. So ``roost-sim run``
(the same program and control sockets the sandbox uses) is started under ``SCHED_RR``:
every thread of it runs ahead of any normal-priority process (the agent, busy loops,
the bench itself), while the kernel's real-time throttling (95 % of each second) keeps a
runaway from taking the machine. The agent stays at normal priority, so it is still
starved by whatever competes with it.

:class:`SimProcess` starts such a process for one vehicle and hands out
:class:`RemoteSim` handles with the calls the benchmarks make of an in-process
:class:`roost_sim.SimulatedAutopilot` (``name``, ``inject``, ``clear``), and
:meth:`SimProcess.specs` for the agent's spec.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol

from roost_api.autopilot import AutopilotSpec
from roost_api.meta import Stack
from roost_mavlink import AUTOPILOT_COMPONENT_ID
from roost_sim.control import request
from roost_sim.faults import FaultKind
from roost_sim.vehicle import autopilot_specs
from tests.support.flight import AIRBORNE_M, BOOT_TIMEOUT_S, TAKEOFF_TIMEOUT_S

REALTIME_PRIORITY = 10
"""SCHED_RR priority of the simulator process (1..99; anything above normal processes)."""
_LAUNCH = (
    "import os, sys; "
    "os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(int(sys.argv[1]))); "
    "from roost_sim.main import main; sys.exit(main(sys.argv[2:]))"
)


class FaultTarget(Protocol):
    """What a benchmark does to an autopilot: an in-process sim or a :class:`RemoteSim`."""

    @property
    def name(self) -> str: ...

    def inject(self, kind: FaultKind, value: Any = None) -> None: ...

    def clear(self, kind: FaultKind | None = None) -> None: ...


@dataclass(frozen=True)
class RemoteSim:
    """One autopilot of a :class:`SimProcess`, reached through its control socket."""

    name: str
    stack: Stack
    sysid: int
    connection: str
    control: Path
    component_id: int = AUTOPILOT_COMPONENT_ID  # what roost-sim runs them with

    def _ask(self, message: dict[str, Any], timeout: float = 10.0) -> dict[str, Any]:
        answer = request(self.control, message, timeout)
        if not answer.get("ok"):
            raise RuntimeError(f"{self.name}: {message['op']} refused: {answer.get('error')}")
        state: dict[str, Any] = answer["state"]
        return state

    def inject(self, kind: FaultKind, value: Any = None) -> None:
        self._ask({"op": "fault", "kind": kind.value, "value": value})

    def clear(self, kind: FaultKind | None = None) -> None:
        self._ask({"op": "clear", "kind": kind.value if kind else None})

    def status(self) -> dict[str, Any]:
        return self._ask({"op": "status"})

    def fly(self) -> None:
        """Arm and take off once started (as :func:`tests.support.flight.take_off`)."""
        self._ask({"op": "fly", "timeout": BOOT_TIMEOUT_S}, BOOT_TIMEOUT_S + 5)


class SimProcess:
    """``roost-sim run --vehicle <stacks> --fast-boot`` under SCHED_RR, stopped by pid."""

    def __init__(self, stacks: Sequence[str]) -> None:
        self._dir = tempfile.TemporaryDirectory(prefix="roost-simprocess-")
        argv = [
            sys.executable, "-c", _LAUNCH, str(REALTIME_PRIORITY),
            "--state-dir", self._dir.name, "run", "--vehicle", ",".join(stacks), "--fast-boot",
        ]  # fmt: skip
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, text=True)
        self.sims: list[RemoteSim] = []
        try:
            assert self.proc.stdout is not None
            for _ in stacks:
                line = self.proc.stdout.readline()
                if not line:
                    raise RuntimeError(f"roost-sim exited ({self.proc.wait()}) before starting")
                d = json.loads(line)
                self.sims.append(
                    RemoteSim(
                        d["name"],
                        Stack(d["stack"]),
                        d["sysid"],
                        d["connection"],
                        Path(d["control"]),
                    )
                )
        except BaseException:
            self.stop()
            raise

    @property
    def policy(self) -> str:
        """The process's scheduling policy as the kernel reports it (for figure notes)."""
        policy = os.sched_getscheduler(self.proc.pid)
        priority = os.sched_getparam(self.proc.pid).sched_priority
        names = {os.SCHED_RR: "SCHED_RR", os.SCHED_FIFO: "SCHED_FIFO", os.SCHED_OTHER: "normal"}
        return f"{names.get(policy, str(policy))} priority {priority}"

    def specs(self) -> list[AutopilotSpec]:
        """``AutopilotSpec`` entries: bridge channel = position in the list."""
        return autopilot_specs(self.sims)

    def take_off(self) -> None:
        """Every autopilot armed and airborne (above :data:`AIRBORNE_M`)."""
        for sim in self.sims:
            sim.fly()
        deadline = time.monotonic() + TAKEOFF_TIMEOUT_S
        for sim in self.sims:
            while not _airborne(sim.status()):
                if time.monotonic() > deadline:
                    raise TimeoutError(f"{sim.name} not airborne: {sim.status()}")
                time.sleep(0.1)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._dir.cleanup()

    def __enter__(self) -> SimProcess:
        return self

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()


def _airborne(state: dict[str, Any]) -> bool:
    return state.get("landed_state") == "InAir" and float(state.get("altitude_m", 0)) > AIRBORNE_M
