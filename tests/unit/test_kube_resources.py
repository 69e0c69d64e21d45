"""roost_kube.resources: where each kind lives, Roost's kinds spelled once in roost_api."""

from __future__ import annotations

import pytest

from roost_api.resources import KINDS
from roost_kube.resources import (
    CONFIGMAPS,
    JOBS,
    MISSIONS,
    NODES,
    PODS,
    VEHICLES,
    Resource,
    resource_of,
)


def test_paths_for_core_grouped_namespaced_and_cluster_scoped_kinds() -> None:
    assert NODES.object_path("n1") == "/api/v1/nodes/n1"
    assert CONFIGMAPS.collection_path("ns") == "/api/v1/namespaces/ns/configmaps"
    assert CONFIGMAPS.collection_path() == "/api/v1/configmaps"
    assert PODS.object_path("p", "ns") == "/api/v1/namespaces/ns/pods/p"
    assert JOBS.object_path("j", "ns") == "/apis/batch/v1/namespaces/ns/jobs/j"
    assert VEHICLES.object_path("v") == "/apis/roost.dev/v1alpha1/vehicles/v"
    assert MISSIONS.object_path("m", "ns") == "/apis/roost.dev/v1alpha1/namespaces/ns/missions/m"
    with pytest.raises(ValueError, match="namespaced"):
        CONFIGMAPS.object_path("c")


def test_resource_of_a_manifest_and_an_unknown_kind() -> None:
    assert resource_of({"apiVersion": "v1", "kind": "Pod"}) is PODS
    assert resource_of({"apiVersion": "batch/v1", "kind": "Job"}) is JOBS
    with pytest.raises(KeyError, match=r"declare it in roost_kube\.resources"):
        resource_of({"apiVersion": "apps/v1", "kind": "Deployment"})  # no process needs it


@pytest.mark.parametrize("kind", KINDS, ids=lambda k: k.kind)
def test_roost_kinds_come_from_the_api_package(kind: object) -> None:
    from roost_api.resources import ResourceKind  # noqa: PLC0415

    assert isinstance(kind, ResourceKind)
    resource = resource_of({"apiVersion": f"{kind.group}/{kind.version}", "kind": kind.kind})
    assert resource == Resource.of(kind)
    assert resource.kopf == (kind.group, kind.version, kind.plural)
    assert resource.namespaced == kind.namespaced
