"""The core/v1 Event manifest every Roost process posts.

Events about cluster-scoped objects (Vehicles, RedundantAutopilots, Nodes) go to the
``default`` namespace, as kubectl expects. An Event's name derives from the object, the
reason, the message and the time, so a post retried after a timeout or a partition is
refused by the server as a duplicate (409) instead of being recorded twice; callers treat
that conflict as success.
"""

from __future__ import annotations

from collections.abc import Mapping
from datetime import datetime
from typing import Any, Final, Literal

from roost_kube.patches import Obj, content_hash

EVENT_NAMESPACE: Final = "default"
MESSAGE_LIMIT: Final = 1024

EventType = Literal["Normal", "Warning"]


def timestamp(at: datetime | str) -> str:
    """RFC 3339 with a ``Z`` for UTC, as the API server writes times."""
    return at if isinstance(at, str) else at.isoformat().replace("+00:00", "Z")


def event_manifest(
    regarding: Mapping[str, Any],
    *,
    reason: str,
    message: str,
    at: datetime | str,
    component: str,
    type: EventType = "Normal",
    instance: str | None = None,
) -> Obj:
    """A core/v1 Event about ``regarding`` (an object as read from the API).

    ``component`` is the reporting process (``roost-operator``, ``roost-agent``);
    ``instance`` the host it runs on, when that matters (the agent's node).
    """
    meta = regarding["metadata"]
    stamp = timestamp(at)
    involved: Obj = {
        "apiVersion": regarding["apiVersion"],
        "kind": regarding["kind"],
        "name": meta["name"],
        "uid": meta.get("uid"),
    }
    if meta.get("namespace"):
        involved["namespace"] = meta["namespace"]
    source: Obj = {"component": component}
    if instance:
        source["host"] = instance
    manifest: Obj = {
        "apiVersion": "v1",
        "kind": "Event",
        "metadata": {
            "name": f"{meta['name']}.{content_hash([meta.get('uid'), reason, message, stamp])}",
            "namespace": meta.get("namespace") or EVENT_NAMESPACE,
        },
        "involvedObject": involved,
        "reason": reason,
        "message": message[:MESSAGE_LIMIT],
        "type": type,
        "source": source,
        "reportingComponent": component,
        "firstTimestamp": stamp,
        "lastTimestamp": stamp,
        "count": 1,
    }
    if instance:
        manifest["reportingInstance"] = instance
    return manifest
