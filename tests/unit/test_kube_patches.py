"""roost_kube.patches: change detection for apply, owner references, merge patches with
nulls and resourceVersion preconditions."""

from __future__ import annotations

from typing import Any

from roost_api.vehicle import VehicleStatus
from roost_kube.patches import (
    ANNOTATION_APPLIED_HASH,
    contains,
    merge_patch_fields,
    needs_apply,
    owner_reference,
    precondition,
    with_applied_hash,
)


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


def test_owner_reference_names_the_owner_as_controller() -> None:
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


def test_a_merge_patch_nulls_what_was_emptied_and_keeps_lists_whole() -> None:
    old = VehicleStatus.model_validate(
        {
            "activeAutopilot": "fc1",
            "claimedBy": {"namespace": "ns", "name": "m"},
            "conditions": [
                {
                    "type": "Ready",
                    "status": "True",
                    "reason": "R",
                    "message": "",
                    "lastTransitionTime": "2024-01-01T00:00:00Z",
                }
            ],
        }
    )
    new = VehicleStatus.model_validate({"conditions": []})
    patch = merge_patch_fields(new, old=old, fields=["activeAutopilot", "claimedBy", "conditions"])
    assert patch["activeAutopilot"] is None  # emptied scalar: explicit null
    assert patch["conditions"] == []  # lists go whole, never with nulls inside
    assert patch["claimedBy"] is None  # an emptied object field: null removes it


def test_a_merge_patch_of_unchanged_fields_is_empty() -> None:
    status = VehicleStatus.model_validate({"activeAutopilot": "fc1"})
    assert merge_patch_fields(status, old=status, fields=["activeAutopilot"]) == {}
    assert merge_patch_fields(status)["activeAutopilot"] == "fc1"  # no old: every field


def test_a_precondition_carries_the_resource_version_read() -> None:
    read = {"metadata": {"name": "v", "resourceVersion": "42"}}
    patch = precondition(read, {"metadata": {"labels": {"a": "b"}}, "status": {"x": 1}})
    assert patch == {
        "metadata": {"labels": {"a": "b"}, "resourceVersion": "42"},
        "status": {"x": 1},
    }
