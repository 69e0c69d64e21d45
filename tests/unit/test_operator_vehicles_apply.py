"""A component pod's step, as the plan decides it and the apply carries it out, against a
fake API (a stand-in that records writes, so a test can say "exactly this write"): one
write per step, never two pods of a component. The step's decision table is in
``test_operator_vehicles_desired``."""

from __future__ import annotations

import json
from typing import Any, cast

from roost_api.vehicle import VehicleSpec
from roost_kube.client import Kube
from roost_kube.errors import ConflictError
from roost_kube.patches import Obj
from roost_kube.resources import Resource
from roost_operator.engine.cache import CachedView
from roost_operator.vehicles.apply import converge_pod
from roost_operator.vehicles.config import vehicle_config
from roost_operator.vehicles.flight import hold_step
from roost_operator.vehicles.manifests import component_pod, component_workloads, pod_hash
from roost_operator.vehicles.plan import PodMove
from roost_operator.vehicles.pods import pod_step


class FakeApi:
    """Pods by name; records every write."""

    def __init__(self, *pods: Obj, exists_behind_the_cache: Obj | None = None) -> None:
        self.pods = {p["metadata"]["name"]: p for p in pods}
        self.hidden = exists_behind_the_cache
        self.writes: list[tuple[str, str]] = []

    def get(self, resource: Resource, name: str, namespace: str | None = None) -> Obj | None:
        return self.pods.get(name)

    def create(self, manifest: Obj) -> Obj:
        name = manifest["metadata"]["name"]
        self.writes.append(("create", name))
        if self.hidden is not None:
            self.pods[name] = self.hidden
            body = json.dumps({"reason": "AlreadyExists", "message": "pods exists"})
            raise ConflictError(409, "POST", "/api/v1/namespaces/n/pods", body)
        self.pods[name] = {**manifest, "status": {"phase": "Pending"}}
        return self.pods[name]

    def delete(
        self,
        resource: Resource,
        name: str,
        namespace: str | None = None,
        *,
        grace_period_s: int | None = None,
    ) -> bool:
        self.writes.append(("delete", name))
        return self.pods.pop(name, None) is not None


def desired(node: str = "node-a") -> Obj:
    spec = VehicleSpec.model_validate({"nodeName": node, "sysid": 1})
    values = vehicle_config(
        name="drone1", spec=spec, fcu_url="udp://:14540@", firmware=None, active_autopilot=None
    )
    (mavros,) = component_workloads(spec, [], vehicle_name="drone1")
    return component_pod("drone1", node, mavros, values, namespace="n", owners=[])


def step(api: FakeApi, want: Obj, *, node_exists: bool, holding: bool = False) -> Obj | None:
    """Decide the pod's step as the plan does, then take it as the apply does."""
    live = api.pods.get(want["metadata"]["name"])
    decided = hold_step(pod_step(live, want, node_exists=node_exists), holding=holding)
    move = PodMove("mavros", want, live, decided)
    return converge_pod(CachedView(cast(Kube, api)), move)


def running(pod: Obj, **meta: Any) -> Obj:
    return {**pod, "metadata": {**pod["metadata"], **meta}, "status": {"phase": "Running"}}


def test_a_missing_pod_is_created_once_its_node_exists() -> None:
    api = FakeApi()
    assert step(api, desired(), node_exists=False) is None
    assert api.writes == []
    live = step(api, desired(), node_exists=True)
    assert live is not None and pod_hash(live) == pod_hash(desired())
    assert api.writes == [("create", "drone1-mavros")]


def test_an_outdated_pod_is_deleted_and_its_successor_waits_for_the_deletion() -> None:
    api = FakeApi(running(desired("node-old")))
    live = step(api, desired(), node_exists=True)
    assert live is not None and live["spec"]["nodeName"] == "node-old"  # reported outdated
    assert api.writes == [("delete", "drone1-mavros")]  # no create beside it


def test_in_the_air_an_outdated_pod_is_kept_and_an_ended_or_missing_one_still_comes_back() -> None:
    outdated = running(desired("node-old"))
    api = FakeApi(outdated)
    assert step(api, desired(), node_exists=True, holding=True) == outdated
    assert api.writes == []  # replaced after the landing
    ended = {**desired(), "status": {"phase": "Failed"}}
    api = FakeApi(ended)
    step(api, desired(), node_exists=True, holding=True)
    assert api.writes == [("delete", "drone1-mavros")]
    api = FakeApi()
    step(api, desired(), node_exists=True, holding=True)
    assert api.writes == [("create", "drone1-mavros")]


def test_a_terminating_pod_is_left_alone_and_the_desired_one_kept() -> None:
    leaving = running(desired(), deletionTimestamp="2024-01-01T00:00:00Z")
    api = FakeApi(leaving)
    assert step(api, desired(), node_exists=True) == leaving
    api = FakeApi(running(desired()))
    step(api, desired(), node_exists=True)
    assert api.writes == []


def test_a_create_racing_a_pod_the_cache_missed_judges_the_pod_that_exists() -> None:
    old = running(desired("node-old"), deletionTimestamp="2024-01-01T00:00:00Z")
    api = FakeApi(exists_behind_the_cache=old)
    assert step(api, desired(), node_exists=True) == old
    assert api.writes == [("create", "drone1-mavros")]
