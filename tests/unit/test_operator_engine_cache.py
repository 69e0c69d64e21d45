"""Which reads of the Vehicle controller reach the API server (``roost_operator.engine.cache``).

The stand-in below replaces ``Kube.get`` only to record which reads would have gone to
the API server: the decision tested here is where a read is answered, not the HTTP.
The real client and stores are exercised against a real control plane in
``tests/integration/test_vehicle_operator.py``.
"""

from __future__ import annotations

from typing import Any, cast

from roost_kube.client import Kube
from roost_kube.resources import CONFIGMAPS, NODES, VEHICLES
from roost_operator.engine.cache import Cached, CachedView
from roost_operator.engine.watches import Store


class RecordedReads:
    """Answers GETs from a dict and records them."""

    def __init__(self, objects: dict[str, Any]) -> None:
        self.objects = objects
        self.reads: list[str] = []

    def get(self, resource: Any, name: str, namespace: str | None = None) -> Any:
        self.reads.append(f"{resource.kind}/{name}")
        return self.objects.get(name)


def _obj(kind: str, name: str, version: str, namespace: str | None = None) -> dict[str, Any]:
    meta: dict[str, Any] = {"name": name, "resourceVersion": version}
    if namespace:
        meta["namespace"] = namespace
    api = {"Vehicle": "roost.dev/v1alpha1", "Node": "v1", "ConfigMap": "v1"}[kind]
    return {"apiVersion": api, "kind": kind, "metadata": meta}


def _view(api: RecordedReads) -> tuple[CachedView, Store, Store, Store]:
    nodes, config, seen = Store(), Store(), Store()
    view = CachedView(
        cast(Kube, api),
        {
            NODES.kind: Cached(nodes),
            CONFIGMAPS.kind: Cached(config, "roost"),
            VEHICLES.kind: Cached(seen, listed=False),
        },
    )
    return view, nodes, config, seen


def test_a_listed_store_answers_for_what_exists_and_what_does_not_once_synced() -> None:
    api = RecordedReads({"n1": _obj("Node", "n1", "3")})
    view, nodes, _, _ = _view(api)
    assert view.get(NODES, "n1") is not None  # before the first list: asked
    assert api.reads == ["Node/n1"]
    nodes.replace([_obj("Node", "n1", "3")], "3")
    assert view.get(NODES, "n1") is not None
    assert view.get(NODES, "n2") is None  # absent from a complete list: does not exist
    assert view.get(CONFIGMAPS, "c", "elsewhere") is None  # another namespace: asked
    assert api.reads == ["Node/n1", "ConfigMap/c"]


def test_a_store_fed_by_events_asks_for_what_it_has_not_seen_and_remembers_it() -> None:
    api = RecordedReads({"drone-1": _obj("Vehicle", "drone-1", "7")})
    view, _, _, seen = _view(api)
    assert view.get(VEHICLES, "drone-1") is not None
    assert view.get(VEHICLES, "drone-1") is not None  # the first answer was kept
    assert view.get(VEHICLES, "drone-2") is None
    assert api.reads == ["Vehicle/drone-1", "Vehicle/drone-2"]
    view.remember(_obj("Vehicle", "drone-1", "9"))  # the answer to a status write
    assert seen.get("drone-1") is not None
    assert view.get(VEHICLES, "drone-1")["metadata"]["resourceVersion"] == "9"  # type: ignore[index]
    assert view.fresh(VEHICLES, "drone-1") is not None  # after a conflict: always asked
    assert api.reads[-1] == "Vehicle/drone-1"
