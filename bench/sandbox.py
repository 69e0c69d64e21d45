"""The largest sandbox on this machine: ``roost sandbox up --vehicles 25``, what it costs.

The real command, headless and without the dashboard, in a directory of its own, with its
scripted fault at the default time (``--fault-after`` 15 s): control plane, operator, 25
agents and three ``roost-sim`` processes (8, 8 and 9 vehicles of two autopilots).

- ``sandbox.up_25_s``: from starting the command until every Vehicle has been ``Ready``
  (the scripted fault may come first, and the faulted vehicle is no longer redundant
  after it: each Vehicle counts once it has been Ready).
- ``sandbox.failover_25_onset_to_switch_ms``: the scripted silence's onset to the bridge
  switch, as the faulted vehicle's agent reports it (``onsetToSwitchMs``), to be read
  beside ``failover.silent_onset_to_switch_default_p99_ms``.
- ``sandbox.cpu_pct_25``: CPU of every process of the sandbox (user + system, % of one
  core) over ``QUIET_S`` of flight once the failover story has ended (``SETTLE_S``
  later), by program in the note.
- ``sandbox.rss_mb_25``: resident memory of all those processes at the end of that
  window, by program in the note.

The machine's 1-min load average goes in every note: these figures share two cores with
whatever else runs.
"""

from __future__ import annotations

import collections
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import psutil

from bench.core import Figure
from roost_cli.sandbox import plan
from roost_cli.sandbox import state as sandbox_state
from tests.support.sandbox import RunningSandbox, running_sandbox
from tests.support.waiting import wait_until

COMMAND = "python -m bench sandbox"
VEHICLES = plan.MAX_VEHICLES
FAULT_VEHICLE = "drone-1"
UP_TIMEOUT_S = 900.0
STORY_TIMEOUT_S = 300.0
STORY_END = "safety routine on"
"""The script's last line about the failover (:mod:`roost_cli.sandbox.director`)."""
SETTLE_S = 10.0
QUIET_S = 30.0


@dataclass(frozen=True)
class Usage:
    """CPU seconds and resident MB of one program's processes."""

    processes: int
    cpu_s: float
    rss_mb: float


def program(proc: psutil.Process) -> str:
    """A process's program: the Roost console script it runs, else its executable."""
    argv = proc.cmdline()
    for arg in argv[:2]:
        name = Path(arg).name
        if name.startswith("roost"):
            return name
    return str(proc.name())


def usage(root: psutil.Process) -> dict[str, Usage]:
    """CPU and RSS of ``root`` and all its descendants, by program."""
    counts: dict[str, int] = collections.Counter()
    cpu: dict[str, float] = collections.defaultdict(float)
    rss: dict[str, float] = collections.defaultdict(float)
    for proc in [root, *root.children(recursive=True)]:
        try:
            name = program(proc)
            times = proc.cpu_times()
            resident = proc.memory_info().rss
        except psutil.Error:
            continue
        counts[name] += 1
        cpu[name] += times.user + times.system
        rss[name] += resident / 1e6
    return {name: Usage(counts[name], cpu[name], rss[name]) for name in counts}


def breakdown(parts: dict[str, float], unit: str) -> str:
    """``name N unit`` parts, largest first."""
    ordered = sorted(parts.items(), key=lambda item: -item[1])
    return ", ".join(f"{name} {value:.0f} {unit}" for name, value in ordered)


def load_1min() -> float:
    return os.getloadavg()[0]


def run() -> list[Figure]:
    with tempfile.TemporaryDirectory(prefix="roost-bench-sandbox-") as tmp:
        args = ["--vehicles", str(VEHICLES), "--no-live", "--no-dashboard"]
        started = time.monotonic()
        with running_sandbox(Path(tmp), args) as sandbox:
            return measure(sandbox, started)


def measure(sandbox: RunningSandbox, started: float) -> list[Figure]:
    names = {vehicle.name for vehicle in plan.plan_fleet(VEHICLES)}
    seen_ready: set[str] = set()

    def all_seen_ready() -> bool:
        if sandbox.process.poll() is not None:
            raise RuntimeError(f"roost sandbox up exited:\n{sandbox.log()}")
        recorded = sandbox_state.load(sandbox.directory)
        if recorded is not None and recorded.kubeconfig is not None:
            seen_ready.update(sandbox.ready_vehicles())
        return seen_ready >= names

    wait_until(f"all {VEHICLES} Vehicles Ready", all_seen_ready, UP_TIMEOUT_S, poll_s=1.0)
    up_s = time.monotonic() - started
    load_up = load_1min()
    wait_until("the failover story", lambda: STORY_END in sandbox.log(), STORY_TIMEOUT_S)
    failovers = sandbox.failovers()
    record = failovers[FAULT_VEHICLE][-1]
    others = sorted(set(failovers) - {FAULT_VEHICLE})
    load_failover = load_1min()

    time.sleep(SETTLE_S)
    root = psutil.Process(sandbox.process.pid)
    before = usage(root)
    load_start = load_1min()
    time.sleep(QUIET_S)
    after = usage(root)
    load_end = load_1min()
    cpu_pct = {
        name: (after[name].cpu_s - before[name].cpu_s) / QUIET_S * 100
        for name in after
        if name in before
    }
    rss = {name: u.rss_mb for name, u in after.items()}
    counts = ", ".join(f"{u.processes} {name}" for name, u in sorted(after.items()))
    setup = (
        f"roost sandbox up --vehicles {VEHICLES} --no-live --no-dashboard (fault after the "
        f"default 15 s); processes: {counts}"
    )
    onset_ms = float(record["onsetToSwitchMs"])
    return [
        Figure(
            "sandbox.up_25_s",
            round(up_s, 1),
            "s",
            "",
            COMMAND,
            f"command start to every Vehicle seen Ready; {setup}; 1-min load {load_up:.1f}",
        ),
        Figure(
            "sandbox.failover_25_onset_to_switch_ms",
            round(onset_ms, 1),
            "ms",
            "<= 235",
            COMMAND,
            f"scripted silence on {FAULT_VEHICLE}/{record['failover']['from']}: "
            f"{record['failover']['reason']}, onset to switch as its agent reports it; "
            f"failovers on other vehicles: {', '.join(others) or 'none'}; "
            f"1-min load {load_failover:.1f}",
        ),
        Figure(
            "sandbox.cpu_pct_25",
            round(sum(cpu_pct.values()), 1),
            "%",
            "",
            COMMAND,
            f"% of one core over {QUIET_S:.0f} s of flight {SETTLE_S:.0f} s after the failover "
            f"story ended (24 flying, {FAULT_VEHICLE} landed): {breakdown(cpu_pct, '%')}; "
            f"1-min load {load_start:.1f} at the start, {load_end:.1f} at the end",
        ),
        Figure(
            "sandbox.rss_mb_25",
            round(sum(rss.values())),
            "MB",
            "",
            COMMAND,
            f"sum of RSS of every sandbox process: {breakdown(rss, 'MB')}; {setup}; "
            f"1-min load {load_end:.1f}",
        ),
    ]
