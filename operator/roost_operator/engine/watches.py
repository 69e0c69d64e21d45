"""Roost's own list+watch threads, for resources kopf should not watch.

kopf filters labels on the client: a handler for Roost's claim Leases makes kopf receive,
and fully process (its per-object worker, cause detection), every Lease in
the cluster — a kubelet renews one per node every few seconds. Node status heartbeats
are the same story. For those resources the operator runs a :class:`Watcher`: the API
server applies the label selector, each event costs one JSON decode, and the callback
decides cheaply whether it matters.

A watch that ends is resumed from the last resourceVersion (bookmarks keep it fresh); one
the server no longer has (410 Gone) is replaced by a fresh list, handed to ``on_list`` so
the owner can compare it with what it knew.

A watcher can also keep what it saw in a :class:`Store` — the last version of every
object, indexed by one label — so that a reconcile reads nodes, claims and its own
ConfigMaps and component Pods from memory instead of asking the API server each time
(:mod:`roost_operator.engine.cache` says when such a read is safe).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Hashable, Iterable, Mapping
from typing import Any, Final

from roost_kube.client import Kube
from roost_kube.errors import ApiError
from roost_kube.patches import content_hash
from roost_kube.resources import Resource

log = logging.getLogger(__name__)

WATCH_TIMEOUT_S: Final = 290
RETRY_S: Final = 2.0
GONE: Final = 410

OnEvent = Callable[[str, Mapping[str, Any], bool], None]
"""``(ADDED|MODIFIED|DELETED, object, news)``; ``news`` is False when the watcher's
store already held this version: the answer to the owner's own write, which the owner
acted on when it wrote it."""
OnList = Callable[[list[Mapping[str, Any]], list[Mapping[str, Any]]], None]
"""Every object after a (re)list, and the last version of each object the watcher's
store held that the list no longer has (none without a store)."""
Key = tuple[str, str]
"""``(namespace, name)``; the namespace is ``""`` for cluster-scoped kinds."""


def key_of(obj: Mapping[str, Any]) -> Key:
    meta = obj.get("metadata") or {}
    return (str(meta.get("namespace") or ""), str(meta.get("name") or ""))


def without_managed_fields(obj: Mapping[str, Any]) -> Mapping[str, Any]:
    """``obj`` without ``metadata.managedFields``: nothing Roost reads is there, and it is
    often most of an object's size."""
    meta = obj.get("metadata") or {}
    if "managedFields" not in meta:
        return obj
    return {**obj, "metadata": {k: v for k, v in meta.items() if k != "managedFields"}}


Trim = Callable[[Mapping[str, Any]], Mapping[str, Any]]


def _revision(obj: Mapping[str, Any]) -> int | None:
    """The object's resourceVersion as a number, when it is one (see :class:`Store`)."""
    version = (obj.get("metadata") or {}).get("resourceVersion")
    try:
        return int(version) if version is not None else None
    except (TypeError, ValueError):
        return None


class Store:
    """The last seen version of each object of one kind, with an index on one label.

    Filled by a :class:`Watcher` (its list replaces the content, its events update it)
    and by the owner's own writes (:meth:`remember`, the object the API server
    returned), so that the process reads what it just wrote even before the watch
    event arrives.

    Ordering: resourceVersions are opaque by API convention, but etcd and kine (K3s)
    both use the store's revision number. When versions are numbers, an older version
    never replaces a newer one: a write's answer and the watch event for an earlier
    change can arrive in either order. A deleted object leaves its deletion's version
    behind, and a list its own, so a write answered before a deletion (or before the
    list) cannot bring the object back. When versions are not numbers, writes are not
    remembered at all and only the watch fills the store: correct, only staler.
    """

    def __init__(self, index_label: str | None = None, trim: Trim = without_managed_fields) -> None:
        self.index_label = index_label
        self.trim = trim
        """What of each object is kept (memory grows with the fleet: keep what is read)."""
        self.synced = threading.Event()
        """Set after the first complete list: before it, an absent object proves nothing."""
        self._objects: dict[Key, Mapping[str, Any]] = {}
        self._index: dict[str, set[Key]] = {}
        self._deleted: dict[Key, int] = {}
        self._floor = 0
        self._lock = threading.Lock()

    def get(self, name: str, namespace: str | None = None) -> Mapping[str, Any] | None:
        with self._lock:
            return self._objects.get((namespace or "", name))

    def select(self, labels: Mapping[str, str]) -> list[Mapping[str, Any]]:
        """The objects carrying every one of ``labels``."""
        with self._lock:
            if self.index_label is not None and self.index_label in labels:
                keys: Iterable[Key] = self._index.get(labels[self.index_label], set())
            else:
                keys = self._objects
            found = [self._objects[key] for key in keys]
        return [
            obj
            for obj in found
            if all(
                ((obj.get("metadata") or {}).get("labels") or {}).get(k) == v
                for k, v in labels.items()
            )
        ]

    def __len__(self) -> int:
        with self._lock:
            return len(self._objects)

    # -- what the watch saw ---------------------------------------------------------

    def replace(
        self, objects: Iterable[Mapping[str, Any]], version: str
    ) -> list[Mapping[str, Any]]:
        """A complete list at ``version``: the content from now on. Returns the last
        version of every object that is no longer there."""
        objects = list(objects)
        with self._lock:
            listed = {key_of(obj) for obj in objects}
            vanished = [obj for key, obj in self._objects.items() if key not in listed]
            self._objects.clear()
            self._index.clear()
            self._deleted.clear()
            for obj in objects:
                self._put(obj)
            try:
                self._floor = int(version)
            except ValueError:
                self._floor = 0
        self.synced.set()
        return vanished

    def observe(self, kind: str, obj: Mapping[str, Any]) -> bool:
        """A watch event (``ADDED``/``MODIFIED``/``DELETED``); whether it was news (False:
        this version, or a newer one, was already here)."""
        key = key_of(obj)
        with self._lock:
            if kind == "DELETED":
                self._drop(key)
                revision = _revision(obj)
                if revision is not None:
                    self._deleted[key] = revision
                return True
            if not self._newer(key, obj, strictly=True):
                return False
            self._deleted.pop(key, None)
            self._put(obj)
            return True

    # -- what the owner wrote ---------------------------------------------------------

    def remember(self, obj: Mapping[str, Any]) -> None:
        """The API server's answer to a write: newer than anything seen, unless a
        deletion or a list already went past it."""
        revision = _revision(obj)
        if revision is None:
            return
        key = key_of(obj)
        with self._lock:
            if revision <= max(self._floor, self._deleted.get(key, 0)):
                return
            if self._newer(key, obj):
                self._put(obj)

    def forget(self, name: str, namespace: str | None = None) -> None:
        """The owner deleted the object (its DELETED event will follow)."""
        with self._lock:
            self._drop((namespace or "", name))

    # -- under the lock -------------------------------------------------------------

    def _newer(self, key: Key, obj: Mapping[str, Any], *, strictly: bool = False) -> bool:
        present = self._objects.get(key)
        if present is None:
            return True
        mine, theirs = _revision(obj), _revision(present)
        if mine is None or theirs is None:
            return True
        return mine > theirs if strictly else mine >= theirs

    def _put(self, obj: Mapping[str, Any]) -> None:
        key = key_of(obj)
        self._drop(key)
        obj = self.trim(obj)
        self._objects[key] = obj
        value = self._label(obj)
        if value is not None:
            self._index.setdefault(value, set()).add(key)

    def _drop(self, key: Key) -> None:
        old = self._objects.pop(key, None)
        value = self._label(old) if old is not None else None
        if value is not None:
            keys = self._index.get(value)
            if keys is not None:
                keys.discard(key)
                if not keys:
                    del self._index[value]

    def _label(self, obj: Mapping[str, Any]) -> str | None:
        if self.index_label is None:
            return None
        value = ((obj.get("metadata") or {}).get("labels") or {}).get(self.index_label)
        return None if value is None else str(value)


class Fingerprints:
    """Remembers a digest per object to skip events that change nothing relevant."""

    def __init__(self) -> None:
        self._seen: dict[Hashable, str] = {}
        self._lock = threading.Lock()

    def changed(self, key: Hashable, relevant: Any) -> bool:
        digest = content_hash(relevant)
        with self._lock:
            if self._seen.get(key) == digest:
                return False
            self._seen[key] = digest
            return True

    def forget(self, key: Hashable) -> bool:
        """Drop ``key``; whether it was known."""
        with self._lock:
            return self._seen.pop(key, None) is not None


class Watcher:
    """Lists and watches one kind in a daemon thread, calling back per event."""

    def __init__(
        self,
        kube: Kube,
        resource: Resource,
        on_event: OnEvent,
        on_list: OnList,
        *,
        label_selector: str = "",
        namespace: str | None = None,
        store: Store | None = None,
    ) -> None:
        self.kube = kube
        self.resource = resource
        self.on_event = on_event
        self.on_list = on_list
        self.label_selector = label_selector
        self.namespace = namespace
        self.store = store
        """Kept current before ``on_list``/``on_event`` are called, if given."""
        self.events = 0
        """Watch events received, for tests and benchmarks."""
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=f"watch-{resource.plural}", daemon=True
        )

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def _run(self) -> None:
        version: str | None = None
        while not self._stop.is_set():
            try:
                if version is None:
                    items, version = self.kube.list_with_version(
                        self.resource,
                        namespace=self.namespace,
                        label_selector=self.label_selector,
                    )
                    vanished = [] if self.store is None else self.store.replace(items, version)
                    self.on_list(list(items), vanished)
                for kind, obj in self.kube.watch_collection(
                    self.resource,
                    resource_version=version,
                    namespace=self.namespace,
                    label_selector=self.label_selector,
                    timeout_s=WATCH_TIMEOUT_S,
                ):
                    if self._stop.is_set():
                        return
                    version = obj.get("metadata", {}).get("resourceVersion", version)
                    if kind == "BOOKMARK":
                        continue
                    self.events += 1
                    news = self.store is None or self.store.observe(kind, obj)
                    self.on_event(kind, obj, news)
            except ApiError as error:
                if error.status == GONE:
                    version = None  # too old: list again
                    continue
                log.warning(
                    "watching %s failed (%s); retrying in %.0f s",
                    self.resource.plural,
                    error,
                    RETRY_S,
                )
                self._stop.wait(RETRY_S)
            except Exception:  # a dropped connection, a bad event: watch again
                log.exception(
                    "watching %s failed; retrying in %.0f s", self.resource.plural, RETRY_S
                )
                self._stop.wait(RETRY_S)
