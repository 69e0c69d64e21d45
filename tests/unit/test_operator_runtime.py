"""The operator's runtime: what a claim Lease event reaches (the Vehicle queue and the
Mission queue)."""

from __future__ import annotations

from typing import Any, cast

from roost_kube.client import Kube
from roost_operator.claims import ANNOTATION_CLAIMED_VEHICLE
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


def test_a_claim_queues_its_vehicle_its_claimant_and_the_waiting_missions() -> None:
    rt = Runtime.start(cast(Kube, object()), Settings())  # no reconcile: nothing runs
    rt.missions.interest.track("flights/waiting", vehicles=[], waiting=True)
    rt.missions.interest.track("flights/flying", vehicles=["drone-9"], waiting=False)
    rt._claims_listed(
        [_lease("drone-1", "flights/survey"), _lease(None, "flights/survey")],
        [_lease("drone-2", "flights/old")],  # released while the watch was away
    )
    assert rt.vehicle_queue.depth() == 2  # the Lease without a vehicle is no claim
    # survey, old and waiting; not flying, which holds another vehicle
    assert rt.mission_queue.depth() == 3
