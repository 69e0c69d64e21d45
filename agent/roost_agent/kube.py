"""The agent's door to the Kubernetes API: its own Vehicle and RedundantAutopilot only.

The agent runs on a drone, so everything here assumes the API server can vanish at any
moment (Wi-Fi gone, control plane restarting) and must never hold the agent up:

* short timeouts on every request (connect 2 s, read 5 s by default) and no client-side
  retries — the publisher decides when to try again, with backoff;
* every transport failure and every 5xx/429 answer is
  :class:`~roost_kube.errors.ApiUnavailableError`, the one exception the publisher treats
  as "partitioned, keep the state and retry";
* no kopf: the requests, Events and error classes are the shared layer's
  (:mod:`roost_kube`), and this module is imported only in cluster mode, so a standalone
  agent never loads the ``kubernetes`` client.

What the agent may do is exactly what the chart's RBAC grants (see ``charts/roost/RBAC.md``):
read Vehicles and RedundantAutopilots, patch ``redundantautopilots/status``, create
Events, and patch its own Vehicle's telemetry annotations. Identity: the Vehicle whose
``spec.nodeName`` is this node (``NODE_NAME`` from the downward API), and the
RedundantAutopilot whose ``spec.vehicleName`` is that Vehicle. RedundantAutopilots are
listed by the operator-maintained ``roost.dev/node`` label first (the node-restriction
admission policy checks that label), then without it,
so a freshly created object is found before the operator has labelled it.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from datetime import datetime
from pathlib import Path
from typing import Any, Final

from roost_api.wellknown import LABEL_NODE
from roost_kube.client import Kube, Timeout
from roost_kube.patches import Obj
from roost_kube.resources import REDUNDANT_AUTOPILOTS, VEHICLES

FIELD_MANAGER: Final = "roost-agent"
DEFAULT_TIMEOUT: Final[Timeout] = (2.0, 5.0)


class AgentKube:
    """The handful of API calls the agent makes; thread-safe (one connection pool)."""

    def __init__(self, kube: Kube) -> None:
        self.kube = kube

    @classmethod
    def from_environment(
        cls,
        kubeconfig: Path | None = None,
        *,
        timeout: Timeout = DEFAULT_TIMEOUT,
    ) -> AgentKube:
        """In-cluster service account, else ``kubeconfig`` / ``$KUBECONFIG``; no retries.
        Through the minimal transport (:class:`roost_kube.transport.DirectTransport`):
        the ``kubernetes`` package is never imported on a vehicle."""
        kube = Kube.from_environment(
            FIELD_MANAGER, kubeconfig=kubeconfig, timeout=timeout, retries=0, direct=True
        )
        return cls(kube)

    # -- identity ---------------------------------------------------------------------

    def find_vehicle(self, node_name: str) -> Obj | None:
        """The Vehicle whose ``spec.nodeName`` is ``node_name`` (oldest if several)."""
        mine = [
            v for v in self.kube.list_objects(VEHICLES) if v["spec"].get("nodeName") == node_name
        ]
        mine.sort(key=lambda v: v["metadata"].get("creationTimestamp", ""))
        return mine[0] if mine else None

    def find_autopilot(self, vehicle_name: str, node_name: str) -> Obj | None:
        """The RedundantAutopilot of ``vehicle_name`` (by node label first, then all)."""
        for labels in ({LABEL_NODE: node_name}, None):
            found = [
                ra
                for ra in self.kube.list_objects(REDUNDANT_AUTOPILOTS, labels=labels)
                if ra["spec"].get("vehicleName") == vehicle_name
            ]
            if found:
                found.sort(key=lambda ra: ra["metadata"].get("creationTimestamp", ""))
                return found[0]
        return None

    def get_autopilot(self, name: str) -> Obj | None:
        """The RedundantAutopilot ``name``, or None when it does not exist."""
        return self.kube.get(REDUNDANT_AUTOPILOTS, name)

    # -- reporting --------------------------------------------------------------------

    def patch_autopilot_status(self, name: str, status: Mapping[str, Any]) -> Obj:
        """Merge-patch the RedundantAutopilot's status subresource (the agent owns it)."""
        return self.kube.merge_patch(
            REDUNDANT_AUTOPILOTS, name, {"status": dict(status)}, subresource="status"
        )

    def post_event(
        self,
        regarding: Mapping[str, Any],
        *,
        reason: str,
        message: str,
        warning: bool,
        at: datetime,
        node_name: str,
    ) -> bool:
        """Record an Event from this node's agent; False when it was already recorded."""
        return self.kube.post_event(
            regarding,
            reason=reason,
            message=message,
            at=at,
            type="Warning" if warning else "Normal",
            instance=node_name,
        )

    def annotate_vehicle(self, name: str, annotations: Mapping[str, str]) -> Obj:
        """Merge ``annotations`` into Vehicle ``name``'s (the telemetry announcement; the
        chart's admission policy lets the agent change nothing else of its Vehicle)."""
        return self.kube.merge_patch(
            VEHICLES, name, {"metadata": {"annotations": dict(annotations)}}
        )

    # -- following the spec -----------------------------------------------------------

    def watch_autopilot(self, name: str, timeout_s: int) -> Iterator[tuple[str, Obj]]:
        """Events for one RedundantAutopilot, starting with its current state (ADDED)."""
        return self.kube.watch(REDUNDANT_AUTOPILOTS, name, timeout_s=timeout_s)
