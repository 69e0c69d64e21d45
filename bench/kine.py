"""The control plane on kine over SQLite (K3s's datastore) beside the etcd figures.

- ``controlplane.kine_start_to_ready_s``: median of three starts with the binaries cached,
  from nothing (fresh certificates, empty SQLite database) to usable, as
  ``controlplane.warm_start_to_ready_s`` measures it on etcd.
- ``controlplane.kine_rss_mb_10_nodes``: summed resident memory of kine, kube-apiserver,
  kube-controller-manager, kube-scheduler and kwok with 10 Ready fake vehicle nodes each
  running one DaemonSet pod, as ``controlplane.rss_mb_10_nodes`` on etcd.
"""

from __future__ import annotations

from bench.controlplane import memory_10_nodes, warm_start
from bench.core import Figure
from roost_localcluster import binaries
from roost_localcluster.controlplane import Settings

COMMAND = "python -m bench kine"
KINE = Settings(datastore="kine")


def run() -> list[Figure]:
    binaries.ensure_built(KINE.start_order)
    start = warm_start("controlplane.kine_start_to_ready_s", KINE, COMMAND)
    rss = memory_10_nodes(KINE)
    note = "kine+apiserver+controller-manager+scheduler+kwok, one DaemonSet pod per node"
    return [
        start,
        Figure("controlplane.kine_rss_mb_10_nodes", rss, "MiB", "informational", COMMAND, note),
    ]
