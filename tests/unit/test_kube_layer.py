"""The API layer's pure parts: paths, change detection for apply, Event shape."""

from __future__ import annotations

from typing import Any

import pytest

from roost_operator.kube import (
    ANNOTATION_APPLIED_HASH,
    CONFIGMAPS,
    DEPLOYMENTS,
    NODES,
    VEHICLES,
    contains,
    event_manifest,
    needs_apply,
    owner_reference,
    resource_of,
    with_applied_hash,
)


def test_paths_for_core_grouped_namespaced_and_cluster_scoped_kinds() -> None:
    assert NODES.object_path("n1") == "/api/v1/nodes/n1"
    assert CONFIGMAPS.collection_path("ns") == "/api/v1/namespaces/ns/configmaps"
    assert CONFIGMAPS.collection_path() == "/api/v1/configmaps"
    assert DEPLOYMENTS.object_path("d", "ns") == "/apis/apps/v1/namespaces/ns/deployments/d"
    assert VEHICLES.object_path("v") == "/apis/roost.dev/v1alpha1/vehicles/v"
    with pytest.raises(ValueError, match="namespaced"):
        CONFIGMAPS.object_path("c")


def test_resource_of_a_manifest_and_an_unknown_kind() -> None:
    assert resource_of({"apiVersion": "apps/v1", "kind": "Deployment"}) is DEPLOYMENTS
    with pytest.raises(KeyError):
        resource_of({"apiVersion": "v1", "kind": "Secret"})


def test_contains_ignores_server_defaults_and_list_order() -> None:
    actual = {
        "a": 1,
        "defaulted": True,
        "items": [{"name": "y", "x": 2, "extra": 0}, {"name": "x"}],
    }
    assert contains(actual, {"a": 1, "items": [{"name": "x"}, {"name": "y", "x": 2}]})
    assert not contains(actual, {"a": 2})
    assert not contains(actual, {"missing": None})
    assert not contains(actual, {"items": [{"name": "z"}]})


def manifest(data: dict[str, str]) -> dict[str, Any]:
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {"name": "c", "namespace": "n", "annotations": {"keep": "me"}},
        "data": data,
    }


def live_after_apply(desired: dict[str, Any]) -> dict[str, Any]:
    """What the API server returns: our fields plus defaults it added."""
    return {
        **desired,
        "metadata": {**desired["metadata"], "uid": "u", "resourceVersion": "7"},
    }


def test_an_applied_object_needs_no_second_apply() -> None:
    desired = with_applied_hash(manifest({"A": "1"}))
    assert desired["metadata"]["annotations"]["keep"] == "me"
    assert needs_apply(desired, live_after_apply(desired)) is False
    assert with_applied_hash(desired) == desired


def test_a_removed_field_is_detected_by_the_hash() -> None:
    old = with_applied_hash(manifest({"A": "1", "B": "2"}))
    new = with_applied_hash(manifest({"A": "1"}))
    assert contains(live_after_apply(old), manifest({"A": "1"}))  # containment alone misses it
    assert needs_apply(new, live_after_apply(old)) is True


def test_a_hand_edit_under_an_unchanged_hash_is_detected() -> None:
    desired = with_applied_hash(manifest({"A": "1"}))
    edited = live_after_apply(desired)
    edited["data"] = {"A": "tampered"}
    assert needs_apply(desired, edited) is True
    assert needs_apply(desired, None) is True
    assert ANNOTATION_APPLIED_HASH in desired["metadata"]["annotations"]


def test_owner_reference_and_event_shape() -> None:
    vehicle = {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Vehicle",
        "metadata": {"name": "drone1", "uid": "u1"},
    }
    ref = owner_reference(vehicle)
    assert ref == {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Vehicle",
        "name": "drone1",
        "uid": "u1",
        "controller": True,
        "blockOwnerDeletion": False,
    }
    event = event_manifest(
        vehicle, reason="NodeNotFound", message="m", type="Warning", at="2024-01-01T00:00:00Z"
    )
    assert event["metadata"]["namespace"] == "default"
    assert event["involvedObject"]["uid"] == "u1"
    assert "namespace" not in event["involvedObject"]
    again = event_manifest(
        vehicle, reason="NodeNotFound", message="m", type="Warning", at="2024-01-01T00:00:00Z"
    )
    assert again["metadata"]["name"] == event["metadata"]["name"]
