"""A vehicle's WiFi drop on real harness nodes (the run ``tests/e2e_node/test_partition.py``
checks), measured.

- ``partition.pod_restarts``: container restarts, across the cut, of every pod on the
  vehicle node (the chart's agent, the vicon component pod, a Mission's onboard pod).
- ``partition.pods_replaced``: those pods gone or replaced by another (another UID).
- ``partition.status_catchup_s``: from the link back up to the RedundantAutopilot's
  status showing the failover the agent made during the cut.
- ``reboot.node_restart_to_report_s``: right after, the vehicle node loses power mid
  safety routine and boots again: from containerd and the kubelet starting to the
  agent's first report (informational).

The cut lasts :data:`~tests.support.partition.BENCH_CUT_S` (45 s) on a control plane with a
20 s node-monitor grace period and a 5 s eviction window, so it outlasts both; a bare
pod on the same node is evicted in it, which the run waits for. Needs root (namespaces,
cgroups) and the image tools; elsewhere the module reports why and returns no figures.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from bench.core import Figure
from roost_localcluster.nodenet import missing_prerequisites
from tests.support import partition
from tests.support.images import missing_tools

COMMAND = "python -m bench partition"


def figures(run: partition.PartitionRun) -> list[Figure]:
    window = (
        f"a {run.cut_s:.0f} s cut (grace period {partition.GRACE_S} s, eviction window "
        f"{partition.EVICTION_S} s; a pod without Roost's tolerations was evicted in it)"
    )
    pods = f"{len(run.before)} pods: {', '.join(sorted(run.before))}"
    return [
        Figure(
            "partition.pod_restarts",
            float(run.pod_restarts),
            "count",
            "== 0",
            COMMAND,
            note=f"container restarts over {window}; {pods}",
        ),
        Figure(
            "partition.pods_replaced",
            float(run.pods_replaced),
            "count",
            "== 0",
            COMMAND,
            note=f"pods gone or with another UID after {window}",
        ),
        Figure(
            "partition.status_catchup_s",
            run.catchup_s,
            "s",
            "<= 10",
            COMMAND,
            note="link back up to the RedundantAutopilot status showing the failover the "
            f"agent made during the cut (lastFailover.time {run.last_failover.get('time')}, "
            f"silenced at {run.silenced_at:%H:%M:%S}, link back at {run.restored_at:%H:%M:%S})",
        ),
    ]


def run() -> list[Figure]:
    reasons = missing_prerequisites() + [f"no {tool}" for tool in missing_tools()]
    if reasons:
        print(f"bench partition: skipped ({'; '.join(reasons)})", file=sys.stderr)
        return []
    with (
        tempfile.TemporaryDirectory(prefix="bench-partition-") as tmp,
        partition.flying_fleet(Path(tmp)) as fleet,
    ):
        measured = partition.cut_and_restore(fleet, cut_s=partition.BENCH_CUT_S)
        partition.stop_workloads(fleet)  # the Mission's Job pod does not reboot
        rebooted = partition.power_cycle(fleet)
    return [*figures(measured), reboot_figure(rebooted)]


def reboot_figure(run: partition.RebootRun) -> Figure:
    return Figure(
        "reboot.node_restart_to_report_s",
        run.restart_to_report_s,
        "s",
        "informational",
        COMMAND,
        note="the vehicle node powered off mid safety routine (every process killed, "
        "containerd/runc runtime state gone) and started again: containerd + kubelet "
        "start to the agent's first report (same pod, new containers; it resumed the "
        f"routine from {run.routine_before} on {run.active_after}, no switch back)",
    )
