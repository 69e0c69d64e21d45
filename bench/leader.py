"""Leader election figures, on the local control plane with two ``roost-operator``
replicas (``--leader-election``): ``operator.leader_takeover_s`` and
``operator.double_actions_on_takeover``.

The leader is killed (SIGKILL) in the middle of a 100-Vehicle rollout, at the first claim
of a two-vehicle Mission that is starting (:mod:`tests.support.takeover`). The takeover is the time
from the kill until the standby holds the Lease (polled every 50 ms); the standby waits
for one whole lease (8 s) without a renewal on its own clock, then looks every second.
Double actions are the objects the actions make (component Pods, claim Leases, the
Mission's Jobs) that were made twice or removed though they should stay, status
transitions made twice (a Vehicle's ``Ready``, the Mission's phase and its Events) and
fence commands sent twice.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from bench.core import Figure
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane, Settings
from tests.support.takeover import kill_the_leader

COMMAND = "python -m bench leader"


def run() -> list[Figure]:
    with (
        tempfile.TemporaryDirectory(prefix="bench-leader-") as tmp,
        ControlPlane(Path(tmp), settings=Settings()) as plane,
    ):
        cluster = Cluster.of(plane)
        cluster.install_crds()
        result = kill_the_leader(cluster, Path(tmp), fleet=100)
    note = (
        f"killed at {result.at_kill}; after: {result.pods} pods, {result.claims} claims, "
        f"{result.jobs} Jobs, {result.fences} fence writes"
    )
    return [
        Figure(
            "operator.leader_takeover_s",
            round(result.takeover_s, 1),
            "s",
            "<= 15",
            COMMAND,
            "SIGKILL of the leader to the standby holding the Lease; " + note,
        ),
        Figure(
            "operator.double_actions_on_takeover",
            len(result.doubles),
            "actions",
            "== 0",
            COMMAND,
            "; ".join(result.doubles) or note,
        ),
    ]
