"""Reads from watch caches, writes to the API server: the Vehicle controller's view.

Read from the API server, a first reconcile of a vehicle costs about ten requests, most
of them reads (its node, the nodes labelled for it, its claim, its ConfigMap, its
component pods, each once more inside ``apply``), and a vehicle is reconciled several
times while its components roll out. :class:`CachedView` answers those reads from the
:class:`~.watches.Store` of a :class:`~.watches.Watcher` the
operator runs anyway, and keeps each store current with the answers to its own writes,
so a reconcile that finds nothing to do sends nothing.

Why a read from a cache cannot make the controller do the wrong thing:

* ``apply`` is server-side apply: a cache that lags only costs a write that changes
  nothing. A cache cannot hide a missing object: deletions arrive as watch events and
  stay behind as tombstones (see :class:`~roost_operator.engine.watches.Store`).
* writes that replace a list (node taints) carry the ``resourceVersion`` they were
  computed from; a stale cache makes the API server refuse them (409) and the
  controller retries from :meth:`fresh` reads, which also refresh the store.
* the Vehicle comes from a store fed by kopf's own watch of Vehicles (the events its
  handler receives) and by the answers to the controller's status writes, which carry
  the ``resourceVersion`` they were computed from: a status computed from a stale
  Vehicle is refused (409) and recomputed from a fresh read. A Vehicle with a
  RedundantAutopilot — whose reconcile may act on a failover — is always read fresh,
  and so is the RedundantAutopilot.
* before a listed store's first list completes, for an object a store fed by events
  alone has not seen, and for any other kind or namespace, reads go to the API server.

Objects handed out are the stores' own: callers must not change them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from roost_kube.client import Kube
from roost_kube.patches import Obj
from roost_kube.resources import Resource, resource_of
from roost_operator.engine.watches import Store


@dataclass(frozen=True)
class Cached:
    """A store and the namespace its watcher covers (``""``: cluster-scoped)."""

    store: Store
    namespace: str = ""
    listed: bool = True
    """The store is filled by a list and a watch, so an object it lacks does not exist;
    False: by watch events alone, so an object it lacks is asked for."""


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
        return cached.store if cached.store.synced.is_set() or not cached.listed else None

    def get(self, resource: Resource, name: str, namespace: str | None = None) -> Obj | None:
        store = self._store(resource, namespace)
        found = None if store is None else store.get(name, namespace)
        if found is None and (store is None or not self.caches[resource.kind].listed):
            return self.fresh(resource, name, namespace)
        return None if found is None else dict(found)

    def remember(self, obj: Mapping[str, Any]) -> None:
        """The answer to a write made elsewhere (the Vehicle's status)."""
        store = self._store(resource_of(obj), obj["metadata"].get("namespace"))
        if store is not None:
            store.remember(obj)

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

    def create(self, manifest: Mapping[str, Any]) -> Obj:
        """Create an object (:class:`~roost_kube.errors.ConflictError` if it exists)."""
        created = self.kube.create(manifest)
        self.remember(created)
        return created

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

    def delete(
        self,
        resource: Resource,
        name: str,
        namespace: str | None = None,
        *,
        grace_period_s: int | None = None,
    ) -> bool:
        gone = self.kube.delete(resource, name, namespace, grace_period_s=grace_period_s)
        store = self._store(resource, namespace)
        if store is not None:
            store.forget(name, namespace)
        return gone
