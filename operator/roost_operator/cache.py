"""Reads from watch caches, writes to the API server: the Vehicle controller's view.

A first reconcile of a vehicle used to cost about ten requests, most of them reads
(its node, the nodes labelled for it, its claim, its ConfigMap, its Deployments, each
once more inside ``apply``), and a vehicle is reconciled several times while its
components roll out. :class:`CachedView` answers those reads from the
:class:`~roost_operator.watches.Store` of a :class:`~roost_operator.watches.Watcher`
the operator runs anyway, and keeps each store current with the answers to its own
writes, so a reconcile that finds nothing to do sends nothing.

Why a read from a cache cannot make the controller do the wrong thing:

* ``apply`` is server-side apply: a cache that lags only costs a write that changes
  nothing. A cache cannot hide a missing object: deletions arrive as watch events and
  stay behind as tombstones (see :class:`~roost_operator.watches.Store`).
* writes that replace a list (node taints) carry the ``resourceVersion`` they were
  computed from; a stale cache makes the API server refuse them (409) and the
  controller retries from :meth:`fresh` reads, which also refresh the store.
* the objects whose status the controller writes (the Vehicle) or decides on (its
  RedundantAutopilot) are not cached: they are read fresh every time.
* before a store's first list completes, and for any other kind or namespace, reads go
  to the API server.

Objects handed out are the stores' own: callers must not change them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from roost_kube.client import Kube
from roost_kube.patches import Obj
from roost_kube.resources import Resource, resource_of
from roost_operator.watches import Store


@dataclass(frozen=True)
class Cached:
    """A store and the namespace its watcher covers (``""``: cluster-scoped)."""

    store: Store
    namespace: str = ""


@dataclass
class CachedView:
    """The :class:`~roost_kube.client.Kube` moves the Vehicle controller makes, with
    reads served from stores by kind (see the module docstring)."""

    kube: Kube
    caches: Mapping[str, Cached] = field(default_factory=dict)
    """By ``Resource.kind``."""

    def _store(self, resource: Resource, namespace: str | None) -> Store | None:
        cached = self.caches.get(resource.kind)
        if cached is None or (namespace or "") != cached.namespace:
            return None
        return cached.store if cached.store.synced.is_set() else None

    def get(self, resource: Resource, name: str, namespace: str | None = None) -> Obj | None:
        store = self._store(resource, namespace)
        if store is None:
            return self.fresh(resource, name, namespace)
        found = store.get(name, namespace)
        return None if found is None else dict(found)

    def fresh(self, resource: Resource, name: str, namespace: str | None = None) -> Obj | None:
        """Read from the API server (after a conflict), keeping the store current."""
        obj = self.kube.get(resource, name, namespace)
        store = self._store(resource, namespace)
        if obj is not None and store is not None:
            store.remember(obj)
        return obj

    def list_objects(
        self, resource: Resource, *, namespace: str | None = None, labels: Mapping[str, str]
    ) -> list[Obj]:
        store = self._store(resource, namespace)
        if store is None:
            return self.kube.list_objects(resource, namespace=namespace, labels=labels)
        return [dict(obj) for obj in store.select(labels)]

    def apply(self, manifest: Mapping[str, Any]) -> tuple[Obj, bool]:
        resource = resource_of(manifest)
        meta = manifest["metadata"]
        store = self._store(resource, meta.get("namespace"))
        if store is None:
            return self.kube.apply(manifest)
        current = store.get(meta["name"], meta.get("namespace"))
        live, wrote = self.kube.apply(manifest, current=current)
        if wrote:
            store.remember(live)
        return live, wrote

    def merge_patch(
        self,
        resource: Resource,
        name: str,
        patch: Mapping[str, Any],
        *,
        namespace: str | None = None,
    ) -> Obj:
        patched = self.kube.merge_patch(resource, name, patch, namespace=namespace)
        store = self._store(resource, namespace)
        if store is not None:
            store.remember(patched)
        return patched

    def delete(self, resource: Resource, name: str, namespace: str | None = None) -> bool:
        gone = self.kube.delete(resource, name, namespace)
        store = self._store(resource, namespace)
        if store is not None:
            store.forget(name, namespace)
        return gone
