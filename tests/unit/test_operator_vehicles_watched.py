"""The operator's own watches of Nodes and owned objects: which events queue which vehicles."""

from __future__ import annotations

from typing import Any

from roost_api.wellknown import LABEL_VEHICLE
from roost_operator.vehicles.manifests import COMPONENT_POD_SELECTOR
from roost_operator.vehicles.observe import Peers
from roost_operator.vehicles.placement import NodeClaim
from roost_operator.vehicles.watched import (
    OWNED_SELECTOR,
    VehicleTrigger,
    labelled_vehicle,
    node_relevant,
    pod_relevant,
    vehicles_of,
)


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


class Recorder:
    """A trigger for nodes labelled with their vehicle, recording what it queues."""

    def __init__(self) -> None:
        self.queued: list[str] = []
        self.trigger = VehicleTrigger(node_relevant, labelled_vehicle, self.queued.append)

    def take(self) -> list[str]:
        queued, self.queued[:] = list(self.queued), []
        return queued


def _labelled(name: str, **kw: Any) -> Any:
    return _node(name, **{LABEL_VEHICLE: f"v-{name}"}, **kw)


def test_a_heartbeat_changes_nothing_roost_reads() -> None:
    seen = Recorder()
    seen.trigger.on_event("ADDED", _labelled("n1"))
    assert seen.take() == ["v-n1"]
    seen.trigger.on_event("MODIFIED", _labelled("n1", heartbeat="t1"))
    seen.trigger.on_event("MODIFIED", _labelled("n1", heartbeat="t2"))
    assert seen.take() == []


def test_readiness_labels_and_deletion_do() -> None:
    seen = Recorder()
    seen.trigger.on_event("ADDED", _labelled("n1"))
    seen.trigger.on_event("MODIFIED", _labelled("n1", ready="False"))
    seen.trigger.on_event("MODIFIED", _labelled("n1", ready="False", team="blue"))
    seen.trigger.on_event("DELETED", _labelled("n1"))
    seen.trigger.on_event("DELETED", _labelled("n1"))  # twice gone is not news
    assert seen.take() == ["v-n1"] * 4


def test_a_relist_queues_what_changed_or_vanished_meanwhile() -> None:
    seen = Recorder()
    for name in ("n1", "n2", "n3"):
        seen.trigger.on_event("ADDED", _labelled(name))
    seen.take()
    seen.trigger.on_list(
        [_labelled("n1", heartbeat="t9"), _labelled("n2", ready="False")],
        [_labelled("n3")],  # the store's last version of what the list no longer has
    )
    assert seen.take() == ["v-n2", "v-n3"]


def test_status_noise_of_a_component_pod_queues_nothing() -> None:
    queued: list[str] = []
    trigger = VehicleTrigger(pod_relevant, labelled_vehicle, queued.append)

    def pod(phase: str, ready: str, at: str) -> Any:
        return {
            "metadata": {"name": "drone-1-mavros", "labels": {LABEL_VEHICLE: "drone-1"}},
            "status": {
                "phase": phase,
                "podIP": at,
                "conditions": [{"type": "Ready", "status": ready, "lastProbeTime": at}],
            },
        }

    trigger.on_event("ADDED", pod("Pending", "False", "t0"))
    trigger.on_event("MODIFIED", pod("Pending", "False", "t1"))
    trigger.on_event("MODIFIED", pod("Running", "True", "t2"))
    trigger.on_event("MODIFIED", pod("Running", "True", "t3"))
    trigger.on_event("DELETED", pod("Running", "True", "t3"))
    assert queued == ["drone-1", "drone-1", "drone-1"]


def test_only_component_pods_are_watched_not_a_missions_onboard_pods() -> None:
    assert "!roost.dev/mission" in COMPONENT_POD_SELECTOR
    assert OWNED_SELECTOR in COMPONENT_POD_SELECTOR


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


def test_the_echo_of_the_controllers_own_write_queues_nothing_but_is_remembered() -> None:
    seen = Recorder()
    seen.trigger.on_event("ADDED", _labelled("n1"))
    seen.take()
    labelled = _labelled("n1", team="blue")
    seen.trigger.on_event("MODIFIED", labelled, False)  # the reconcile that wrote it knows
    seen.trigger.on_event("MODIFIED", _labelled("n1", team="blue", heartbeat="t3"))
    assert seen.take() == []  # and the next heartbeat is compared with the echo
