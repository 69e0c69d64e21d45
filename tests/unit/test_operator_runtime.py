"""The operator's runtime: what a claim Lease event reaches (the Vehicle queue and the
mission controller's listener)."""

from __future__ import annotations

from typing import Any, cast

from roost_kube.client import Kube
from roost_operator.claims import ANNOTATION_CLAIMED_VEHICLE, Claim
from roost_operator.runtime import Runtime
from roost_operator.settings import Settings


def _lease(vehicle: str | None, holder: str) -> dict[str, Any]:
    annotations = {ANNOTATION_CLAIMED_VEHICLE: vehicle} if vehicle else {}
    return {
        "metadata": {
            "name": "claim",
            "annotations": annotations,
            "uid": "u1",
            "resourceVersion": "7",
        },
        "spec": {"holderIdentity": holder},
    }


def test_a_claim_queues_its_vehicle_and_tells_the_listeners() -> None:
    rt = Runtime.start(cast(Kube, object()), Settings())  # no reconcile: nothing runs
    heard: list[Claim] = []
    rt.claim_listeners.append(heard.append)
    rt._claims_listed(
        [_lease("drone-1", "flights/survey"), _lease(None, "flights/survey")],
        [_lease("drone-2", "flights/old")],  # released while the watch was away
    )
    assert rt.vehicle_queue.depth() == 2  # the Lease without a vehicle is no claim
    assert [(c.vehicle, c.holder_key) for c in heard] == [
        ("drone-1", "flights/survey"),
        ("drone-2", "flights/old"),
    ]
