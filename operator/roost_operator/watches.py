"""Roost's own list+watch threads, for resources kopf should not watch.

kopf filters labels on the client: a handler for Roost's claim Leases makes kopf receive,
and fully process (its per-object worker, cause detection, a diff base), every Lease in
the cluster — a kubelet renews one per node every few seconds. Node status heartbeats
are the same story. For those resources the operator runs a :class:`Watcher`: the API
server applies the label selector, each event costs one JSON decode, and the callback
decides cheaply whether it matters.

A watch that ends is resumed from the last resourceVersion (bookmarks keep it fresh); one
the server no longer has (410 Gone) is replaced by a fresh list, handed to ``on_list`` so
the owner can compare it with what it knew.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Hashable, Mapping
from typing import Any, Final

from roost_kube.client import Kube
from roost_kube.errors import ApiError
from roost_kube.patches import content_hash
from roost_kube.resources import Resource

log = logging.getLogger(__name__)

WATCH_TIMEOUT_S: Final = 290
RETRY_S: Final = 2.0
GONE: Final = 410

OnEvent = Callable[[str, Mapping[str, Any]], None]
"""``(ADDED|MODIFIED|DELETED, object)``."""
OnList = Callable[[list[Mapping[str, Any]]], None]
"""Every object after a (re)list."""


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

    def keys(self) -> set[Hashable]:
        with self._lock:
            return set(self._seen)


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
    ) -> None:
        self.kube = kube
        self.resource = resource
        self.on_event = on_event
        self.on_list = on_list
        self.label_selector = label_selector
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
                        self.resource, label_selector=self.label_selector
                    )
                    self.on_list(list(items))
                for kind, obj in self.kube.watch_collection(
                    self.resource,
                    resource_version=version,
                    label_selector=self.label_selector,
                    timeout_s=WATCH_TIMEOUT_S,
                ):
                    if self._stop.is_set():
                        return
                    version = obj.get("metadata", {}).get("resourceVersion", version)
                    if kind == "BOOKMARK":
                        continue
                    self.events += 1
                    self.on_event(kind, obj)
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
