"""The developer's loop: how long ``make check`` (lint, types, unit tests) takes warm.

- ``dev.check_s``: wall time of one ``make check`` (ruff check, ruff format --check, mypy
  --strict, pytest tests/unit) with the virtualenv, mypy's and ruff's caches warm (a
  first run warms them when mypy's cache is missing). The note gives the CPU time the
  run used and the load average it started at, since on a shared machine the wall time
  follows the load.
"""

from __future__ import annotations

import os
import resource
import subprocess
import time

from bench.core import Figure
from roost_localcluster.binaries import REPO_ROOT

COMMAND = "python -m bench dev"


def make(target: str) -> tuple[float, float]:
    """One ``make TARGET``: (wall seconds, CPU seconds of its processes)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.monotonic()
    subprocess.run(["make", "--no-print-directory", target], cwd=REPO_ROOT, check=True)
    wall = time.monotonic() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def run() -> list[Figure]:
    if not (REPO_ROOT / ".mypy_cache").is_dir():
        make("check")
    load = os.getloadavg()[0]
    wall, cpu = make("check")
    note = (
        f"lint + types + unit, warm; {cpu:.0f} s CPU, load average {load:.1f} "
        f"on {os.cpu_count()} cores at the start"
    )
    return [Figure("dev.check_s", wall, "s", "<= 180", COMMAND, note)]
