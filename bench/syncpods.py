"""The paper's experiment from the mission's own pods on real nodes (Table I, in a cluster).

The sync-paths example's image (one index, amd64 and arm64) and its ``mission.yaml``, on
real harness nodes (:mod:`tests.support.realmission`, the steps
``tests/e2e_node/test_sync_paths_real.py`` tests): the chart's operator and the monitor
pod on a ground node, one follower pod per vehicle node flying two simulated autopilots
through the agent's hub, the sandbox's ``lag`` schedule slowing drone-1 on legs 1 and 4,
drone-2 on leg 2 and drone-3 on leg 3. Three vehicles on nodes of this machine's
architecture. Writes the run's Table I and paths to
``bench/sync-results/real-pods/`` and:

- ``sync.real_pods_max_transit_error_s``: the largest |corrected transit - planned
  transit| over every vehicle and task, from the monitor pod's results (target <= 0.5);
- ``sync.real_pods_flight_s``: from ``kubectl apply`` of the Mission to the monitor pod
  finished (informational: five 20 s legs, the delays, take-off and landing, and the
  pods' start on the nodes).

Not on the emulated arm64 node: tried (the third vehicle's node arm64 under
qemu-user-static, its follower pod privileged for the seccomp reason in
docs/real-node.md), the pod started and ran the image's arm64 half, but its arm command
through the emulated agent's hub got no answer within the follower's 3 s, twice (Job
retries), so the monitor never started the legs. Measured since (docs/real-node.md): the
emulated hub answers a native client on that node in milliseconds, every time; an arm64
client under emulation reading the hub's full stream misses about a third of its answers
(its receive buffer overflows: the kernel drops them). Emulation speed on the follower's
side, not the hub. ``RealMission(arches=(..., "arm64"))`` is that run.

Needs root (namespaces, cgroups); elsewhere it reports why and returns no figures.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from bench.core import Figure
from roost_localcluster import binaries
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane
from roost_localcluster.nodenet import missing_prerequisites
from roost_localcluster.realnode import RealNodes
from tests.support.images import missing_tools
from tests.support.realmission import RealMission

COMMAND = "python -m bench syncpods"
OUTPUT = Path(__file__).parent / "sync-results" / "real-pods"


def run() -> list[Figure]:
    from syncpaths.table import max_transit_error, table, write_results  # noqa: PLC0415

    reasons = missing_prerequisites() + [f"no {tool}" for tool in missing_tools()]
    if reasons:
        print(f"bench syncpods: skipped ({'; '.join(reasons)})", file=sys.stderr)
        return []
    arches = (binaries.HOST_ARCH,) * 3
    with (
        tempfile.TemporaryDirectory(prefix="bench-syncpods-") as tmp,
        ControlPlane(Path(tmp) / "control-plane") as plane,
        RealNodes(cluster := Cluster.of(plane), Path(tmp) / "nodes") as pool,
    ):
        mission = RealMission(cluster, pool, Path(tmp) / "mission", arches=arches)
        try:
            mission.start()
            flight = mission.fly()
        finally:
            mission.stop()
    write_results(flight.results, OUTPUT)
    (OUTPUT / "results.json").unlink()  # the flown paths are in the plot; keep the repo small
    print(table(flight.results))
    records = [r for result in flight.results.values() for r in result.get("records", [])]
    transits = [r["transit_s"] for r in records]
    return [
        Figure(
            "sync.real_pods_max_transit_error_s",
            round(max_transit_error(flight.results), 3),
            "s",
            "<= 0.5",
            COMMAND,
            f"{len(records)} transits of 20 s planned, from the monitor pod's results: "
            f"follower pods on {len(arches)} real {arches[0]} vehicle nodes (the emulated arm64 "
            "node was tried: its follower got no command answer through the emulated hub, see "
            "bench/syncpods.py), monitor pod on the ground node; corrected transits "
            f"{min(transits):.2f}-{max(transits):.2f} s, "
            f"largest delay absorbed {max(r['delay_s'] for r in records):.2f} s "
            "(bench/sync-results/real-pods/table.md)",
        ),
        Figure(
            "sync.real_pods_flight_s",
            round(flight.flight_s, 1),
            "s",
            "informational",
            COMMAND,
            "kubectl apply of mission.yaml to the monitor pod finished: pods started on the "
            "nodes, take-off, five 20 s legs with the delays, landing",
        ),
    ]
