"""The whole suite as CI runs it, warm: how long ``make test`` takes on this machine.

- ``dev.test_warm_s``: wall time of one ``make test`` (check, integration, e2e, the
  control-plane suites on kine) with the virtualenv and the control-plane, node, image
  and compiled-build caches under ``~/.cache/roost`` warm. CI's run adds what a cold cache
  costs on top.
- ``dev.integration_warm_s`` (``ROOST_BENCH_TIER=integration``): ``make integration``
  alone, for a shared machine too busy for a whole run to mean much.

The note gives the CPU time the run used and the load average it started at: the suite
is mostly waiting (sockets, timers, the control plane), so on a shared machine its wall
time follows the others' load. Not among ``make bench``'s modules (it is the test suite
itself, tens of minutes): ``python -m bench devtest``.
"""

from __future__ import annotations

import os

from bench.core import Figure
from bench.dev import make

COMMAND = "python -m bench devtest"
TIERS = {"test": ("dev.test_warm_s", "<= 1500"), "integration": ("dev.integration_warm_s", "")}


def run() -> list[Figure]:
    tier = os.environ.get("ROOST_BENCH_TIER", "test")
    if tier not in TIERS:
        raise SystemExit(f"ROOST_BENCH_TIER={tier!r}: one of {', '.join(TIERS)}")
    name, target = TIERS[tier]
    load = os.getloadavg()[0]
    wall, cpu = make(tier)
    note = (
        f"make {tier}, warm; {cpu:.0f} s CPU, load average {load:.1f} at the start "
        f"and {os.getloadavg()[0]:.1f} at the end on {os.cpu_count()} cores"
    )
    command = COMMAND if tier == "test" else f"ROOST_BENCH_TIER={tier} {COMMAND}"
    return [Figure(name, wall, "s", target, command, note)]
