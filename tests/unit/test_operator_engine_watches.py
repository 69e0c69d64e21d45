"""The watch cache the Vehicle controller reads: ordering of watch events and own writes.

A reconcile reads nodes, claims and its own ConfigMaps and component Pods from a
``roost_operator.engine.watches.Store``; these are the rules that keep it from going back in
time (a write's answer racing the watch) or bringing back what was deleted.
"""

from __future__ import annotations

from typing import Any

import pytest

from roost_operator.engine.watches import Store


def _obj(name: str, version: str, namespace: str = "roost", **labels: str) -> dict[str, Any]:
    return {
        "metadata": {
            "name": name,
            "namespace": namespace,
            "resourceVersion": version,
            "labels": labels,
        }
    }


def _version(store: Store, name: str) -> str | None:
    found = store.get(name, "roost")
    return None if found is None else found["metadata"]["resourceVersion"]


@pytest.mark.parametrize(
    ("present", "incoming", "how", "kept"),
    [
        # watch events: the stream is in order, but a remembered write may be ahead of it
        (None, "5", "event", "5"),
        ("5", "6", "event", "6"),
        ("7", "6", "event", "7"),  # the event of an older change, after our write's answer
        ("x", "y", "event", "y"),  # versions that are not numbers: the stream decides
        # the answer to our own write
        (None, "5", "write", "5"),
        ("5", "6", "write", "6"),
        ("7", "6", "write", "7"),  # the watch already delivered something newer
        ("5", "z", "write", "5"),  # not a number: never remembered
    ],
)
def test_an_older_version_never_replaces_a_newer_one(
    present: str | None, incoming: str, how: str, kept: str
) -> None:
    store = Store()
    store.replace([], "1")
    if present is not None:
        store.observe("ADDED", _obj("a", present))
    if how == "event":
        store.observe("MODIFIED", _obj("a", incoming))
    else:
        store.remember(_obj("a", incoming))
    assert _version(store, "a") == kept


def test_a_write_answered_before_a_deletion_does_not_bring_the_object_back() -> None:
    store = Store()
    store.replace([_obj("a", "5")], "5")
    store.observe("DELETED", _obj("a", "9"))  # a human deleted it after our write ...
    store.remember(_obj("a", "8"))  # ... whose answer arrives late
    assert store.get("a", "roost") is None
    store.remember(_obj("a", "10"))  # created again by a later write
    assert _version(store, "a") == "10"


def test_a_write_older_than_the_list_is_not_remembered() -> None:
    store = Store()
    store.replace([], "20")  # the list at 20 no longer has it: deleted before then
    store.remember(_obj("a", "15"))
    assert store.get("a", "roost") is None


def test_a_relist_returns_the_last_version_of_what_vanished() -> None:
    store = Store()
    assert not store.synced.is_set()
    store.replace([_obj("a", "1"), _obj("b", "2")], "2")
    assert store.synced.is_set()
    vanished = store.replace([_obj("a", "3")], "4")
    assert [(o["metadata"]["name"], o["metadata"]["resourceVersion"]) for o in vanished] == [
        ("b", "2")
    ]
    assert len(store) == 1


def test_select_uses_the_label_index_and_follows_label_changes() -> None:
    store = Store(index_label="vehicle")
    store.replace(
        [
            _obj("d1", "1", vehicle="drone-1", component="mavros"),
            _obj("d2", "2", vehicle="drone-1", component="vicon"),
            _obj("d3", "3", vehicle="drone-2", component="mavros"),
        ],
        "3",
    )
    names = lambda **labels: sorted(o["metadata"]["name"] for o in store.select(labels))  # noqa: E731
    assert names(vehicle="drone-1") == ["d1", "d2"]
    assert names(vehicle="drone-1", component="vicon") == ["d2"]
    assert names(component="mavros") == ["d1", "d3"]  # no index for it: a scan
    store.observe("MODIFIED", _obj("d2", "4", vehicle="drone-2", component="vicon"))
    assert names(vehicle="drone-1") == ["d1"]
    assert names(vehicle="drone-2") == ["d2", "d3"]
    store.forget("d1", "roost")
    store.observe("DELETED", _obj("d3", "5", vehicle="drone-2"))
    assert names(vehicle="drone-1") == []
    assert names(vehicle="drone-2") == ["d2"]


def test_cluster_scoped_objects_have_no_namespace() -> None:
    store = Store()
    store.replace([_obj("node-1", "1", namespace="")], "1")
    assert store.get("node-1") is not None
    assert store.get("node-1", "roost") is None


def test_the_echo_of_an_own_write_is_no_news() -> None:
    store = Store()
    store.replace([_obj("a", "5")], "5")
    store.remember(_obj("a", "6"))  # the answer to our patch
    assert not store.observe("MODIFIED", _obj("a", "6"))  # its watch event
    assert store.observe("MODIFIED", _obj("a", "7"))  # someone else's change
    assert store.observe("DELETED", _obj("a", "8"))
