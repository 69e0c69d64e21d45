"""One Vehicle reconcile, traced on the real control plane: from the controller the
vehicle's name goes observe → plan → apply → status, each stage module once.

The controller runs in the test's process (so the trace sees its calls), without an
operator process and without watch caches: every read goes to the API server. What is
traced: each call into a stage module, in order; a stage that comes back after a later
one began would be a step calling back into an earlier one. The pure building blocks
(manifests, placement, pods, conditions, config, flight, the failover decision) are
called from within a stage and are not stops of their own.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path
from types import FrameType
from typing import Any

import pytest

import roost_operator.vehicles
from roost_kube.client import Kube
from roost_kube.resources import VEHICLES
from roost_localcluster.cluster import Cluster
from roost_operator.vehicles.controller import VehicleController
from roost_operator.vehicles.observe import Peers
from tests.support.waiting import unique

pytestmark = pytest.mark.cluster

NAMESPACE = "roost-it-reconcile-path"
STAGES = ("observe", "plan", "apply", "status")
FOLDER = Path(roost_operator.vehicles.__file__).parent


def traced(run: Any) -> list[str]:
    """The stage modules entered while ``run()`` runs, consecutive repeats collapsed."""
    seen: list[str] = []

    def profile(frame: FrameType, event: str, _: object) -> None:
        if event != "call":
            return
        # by file: a dataclass's generated __init__ runs where it is constructed
        path = Path(frame.f_code.co_filename)
        if path.parent != FOLDER or path.stem not in STAGES:
            return
        stop = path.stem
        if not seen or seen[-1] != stop:
            seen.append(stop)

    sys.setprofile(profile)
    try:
        run()
    finally:
        sys.setprofile(None)
    return seen


@pytest.fixture
def vehicle(roost_crds: Cluster, kube: Kube, fake_nodes: Any) -> Iterator[str]:
    roost_crds.kubectl("create", "namespace", NAMESPACE, check=False)
    node = unique("path-node")
    fake_nodes(node)
    name = unique("path")
    kube.create(
        {
            "apiVersion": VEHICLES.api_version,
            "kind": VEHICLES.kind,
            "metadata": {"name": name},
            "spec": {"nodeName": node, "sysid": 7, "simulation": {"stack": "px4"}},
        }
    )
    yield name
    roost_crds.kubectl("delete", "vehicle", name, "--ignore-not-found", "--wait=false")


def test_a_reconcile_visits_each_stage_once_in_order(kube: Kube, vehicle: str) -> None:
    controller = VehicleController(kube=kube, namespace=NAMESPACE)
    peers = Peers(claims_on=lambda _: [], autopilots_of=lambda _: None)
    first = traced(lambda: controller.reconcile(vehicle, peers))
    assert first == list(STAGES), first
    again = traced(lambda: controller.reconcile(vehicle, peers))  # nothing left to write
    assert again == list(STAGES), again
    written = kube.get(VEHICLES, vehicle)
    assert written is not None and written["status"]["nodeName"]
    controller.release_if_gone(vehicle)  # still there: nothing released
