"""The operator's own Node watch: which node events queue which vehicles."""

from __future__ import annotations

from typing import Any

from roost_api.wellknown import LABEL_VEHICLE
from roost_operator.vehicles.controller import Peers
from roost_operator.vehicles.nodewatch import NodeFingerprints, vehicles_of
from roost_operator.vehicles.placement import NodeClaim


def _node(name: str, *, ready: str = "True", heartbeat: str = "t0", **labels: str) -> Any:
    return {
        "metadata": {"name": name, "labels": labels, "resourceVersion": heartbeat},
        "spec": {},
        "status": {
            "conditions": [
                {
                    "type": "Ready",
                    "status": ready,
                    "reason": "KubeletReady",
                    "message": "ok",
                    "lastHeartbeatTime": heartbeat,
                },
            ]
        },
    }


def test_a_heartbeat_changes_nothing_roost_reads() -> None:
    prints = NodeFingerprints()
    assert prints.changed_node("ADDED", _node("n1"))
    assert not prints.changed_node("MODIFIED", _node("n1", heartbeat="t1"))
    assert not prints.changed_node("MODIFIED", _node("n1", heartbeat="t2"))


def test_readiness_labels_and_deletion_do() -> None:
    prints = NodeFingerprints()
    prints.changed_node("ADDED", _node("n1"))
    assert prints.changed_node("MODIFIED", _node("n1", ready="False"))
    assert prints.changed_node("MODIFIED", _node("n1", ready="False", team="blue"))
    assert prints.changed_node("DELETED", _node("n1"))
    assert not prints.changed_node("DELETED", _node("n1"))  # twice gone is not news


def test_a_relist_reports_what_changed_or_vanished_meanwhile() -> None:
    prints = NodeFingerprints()
    for name in ("n1", "n2", "n3"):
        prints.changed_node("ADDED", _node(name))
    changed = prints.relist([_node("n1", heartbeat="t9"), _node("n2", ready="False")])
    assert sorted(n["metadata"]["name"] for n in changed) == ["n2", "n3"]


def test_a_node_concerns_the_vehicles_claiming_it_and_the_one_it_is_labelled_for() -> None:
    peers = Peers(
        claims_on=lambda node: (
            [NodeClaim("drone-1", "t0"), NodeClaim("drone-9", "t1")] if node == "n1" else []
        ),
        autopilots_of=lambda vehicle: None,
    )
    assert vehicles_of(_node("n1", **{LABEL_VEHICLE: "drone-2"}), peers) == {
        "drone-1",
        "drone-9",
        "drone-2",
    }
    assert vehicles_of(_node("n2"), peers) == set()
    assert vehicles_of(_node("n2", **{LABEL_VEHICLE: "drone-2"}), None) == {"drone-2"}
