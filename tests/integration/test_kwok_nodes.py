"""kwok's nodes reporting their status like kubelets with leases (``roost_localcluster.kwoknodes``).

A real control plane and kwok with the Node stages: a new node turns Ready with what the
scheduler and the node lifecycle controller read (conditions, addresses, ``Running``),
its status is rewritten only every report period (here 3 s, a kubelet's is 5 min), and
its Lease is renewed by kwok in between. Nothing here is timed: the test waits for the
second report and looks at what changed.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from roost_localcluster import nodes
from roost_localcluster.cluster import Cluster
from roost_localcluster.controlplane import ControlPlane, Settings
from tests.support.waiting import wait_until

REPORT_S = 3.0


def _node(cluster: Cluster, name: str) -> Any:
    return json.loads(cluster.kubectl("get", "node", name, "-o", "json").stdout)


def _heartbeat(node: Any) -> str:
    ready = next(c for c in node["status"]["conditions"] if c["type"] == "Ready")
    return str(ready["lastHeartbeatTime"])


def test_a_node_turns_ready_and_reports_again_after_the_period(tmp_path: Path) -> None:
    settings = Settings(node_status_report_s=REPORT_S)
    with ControlPlane(tmp_path / "plane", settings=settings) as plane:
        cluster = Cluster.of(plane)
        cluster.kubectl("create", "-f", "-", input_text=json.dumps(nodes.fake_node("drone-1")))
        cluster.wait_nodes_ready(["drone-1"], timeout_s=60)
        node = _node(cluster, "drone-1")
        assert node["status"]["phase"] == "Running"
        assert {a["type"] for a in node["status"]["addresses"]} == {"InternalIP", "Hostname"}
        assert {c["type"] for c in node["status"]["conditions"]} >= {"Ready", "MemoryPressure"}
        first = _heartbeat(node)
        wait_until(
            "a second status report",
            lambda: _heartbeat(_node(cluster, "drone-1")) != first,
            timeout_s=60,
        )
        lease = json.loads(
            cluster.kubectl("get", "lease", "drone-1", "-n", "kube-node-lease", "-o", "json").stdout
        )
        assert lease["spec"]["leaseDurationSeconds"] == settings.node_lease_duration_s
        assert lease["spec"]["renewTime"]
