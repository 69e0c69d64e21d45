"""Roost's end-to-end run on KinD (``make e2e-kind``, tests/e2e/kind/run.sh).

- ``kind.node_image_build_cold_s``: a cold build of the node image
  (tests/e2e/kind/node-image/build.sh with nothing cached but Roost's Kubernetes builds):
  the last ``debian-root`` record (mmdebstrap, a cache stage of its own) plus the last
  ``after-root`` one (the kubeadm images, the containerd import, the commit and the cache
  archive) of its ``build-times.tsv``. Read, never triggered.
- ``kind.node_image_build_warm_s``: median of three runs of that script with the image
  present (what every ``make e2e-kind`` pays).
- ``kind.create_to_ready_s``: ``kind create cluster`` from kind-config.yaml (one control
  plane, three workers) until all four nodes are Ready, in one run of run.sh.
- ``kind.e2e_suite_s``: the tests of tests/e2e/kind/ in that run (simulators, the
  fleet, the agents' reports, a Mission, failover, ``helm uninstall``).

The last two come from ``.kind/timings.tsv`` written by the run this module starts; where
run.sh skips (no Docker, no podman as root) the module says why and returns only what
the records hold.
"""

from __future__ import annotations

import csv
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from bench.core import Figure

REPO = Path(__file__).resolve().parents[1]
BUILD = REPO / "tests" / "e2e" / "kind" / "node-image" / "build.sh"
RUN = REPO / "tests" / "e2e" / "kind" / "run.sh"
TIMINGS = REPO / ".kind" / "timings.tsv"
COMMAND = "python -m bench kind"


def _records(path: Path) -> dict[str, list[float]]:
    found: dict[str, list[float]] = {}
    if path.exists():
        with path.open() as f:
            for row in csv.reader(f, delimiter="\t"):
                if len(row) >= 2:
                    found.setdefault(row[0], []).append(float(row[1]))
    return found


def _cache_dir() -> Path:
    root = os.environ.get("ROOST_CACHE_DIR")
    if root:
        return Path(root)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "roost"


def cold_build() -> list[Figure]:
    """The cold node image build, from its build record (never triggered here)."""
    figures: list[Figure] = []
    image_record = _cache_dir() / "kind" / "node-image" / "build-times.tsv"
    records = _records(image_record)
    cold, root = records.get("after-root"), records.get("debian-root")
    if cold and root:
        figures.append(
            Figure(
                "kind.node_image_build_cold_s",
                root[-1] + cold[-1],
                "s",
                "informational",
                "tests/e2e/kind/node-image/build.sh (no node image cached)",
                note=f"Debian root by mmdebstrap {root[-1]:.0f} s (a cache stage of its own) + "
                f"kubeadm's images, containerd import, commit and cache archive {cold[-1]:.0f} s; "
                "kubeadm and kubectl were built before (a one-off Go build of about 9 min here); "
                "2 cores shared with other builds",
            )
        )
    return figures


def run() -> list[Figure]:
    done = subprocess.run([str(RUN)], cwd=REPO, capture_output=True, text=True, check=False)
    tail = "\n".join(done.stdout.splitlines()[-3:])
    if done.returncode != 0 or "SKIPPED" in done.stdout:
        print(
            f"bench kind: run.sh did not complete (exit {done.returncode}):\n{tail}\n"
            f"{done.stderr[-2000:]}",
            file=sys.stderr,
        )
    figures = cold_build()
    warm = []
    for _ in range(3):
        t0 = time.monotonic()
        if subprocess.run([str(BUILD)], capture_output=True, check=False).returncode != 0:
            break
        warm.append(time.monotonic() - t0)
    if len(warm) == 3:
        figures.append(
            Figure(
                "kind.node_image_build_warm_s",
                statistics.median(warm),
                "s",
                "<= 5",
                "tests/e2e/kind/node-image/build.sh (image present)",
                note=f"median of {[round(w, 2) for w in warm]}",
            )
        )
    timings = _records(TIMINGS) if done.returncode == 0 else {}
    if "create_to_ready_s" in timings:
        figures.append(
            Figure(
                "kind.create_to_ready_s",
                timings["create_to_ready_s"][-1],
                "s",
                "<= 180",
                COMMAND,
                note="kind create cluster (podman, Roost's node image) until the 4 nodes "
                "of kind-config.yaml are Ready",
            )
        )
    if "e2e_suite_s" in timings:
        figures.append(
            Figure(
                "kind.e2e_suite_s",
                timings["e2e_suite_s"][-1],
                "s",
                "informational",
                COMMAND,
                note="pytest tests/e2e/kind on the running cluster with the chart installed",
            )
        )
    return figures
