"""The agent's door to the Kubernetes API: its own Vehicle and RedundantAutopilot only.

The agent runs on a drone, so everything here assumes the API server can vanish at any
moment (Wi-Fi gone, control plane restarting) and must never hold the agent up:

* short timeouts on every request (connect 2 s, read 5 s by default) and no client-side
  retries — the publisher decides when to try again, with backoff;
* every transport failure and every 5xx/429 answer becomes :class:`ApiUnavailableError`, the
  one exception the publisher treats as "partitioned, keep the state and retry";
* no kopf (it is an operator framework with its own threads and posting), just the
  ``kubernetes`` client's typed calls.

What the agent may do is exactly what the chart's RBAC grants (see ``charts/roost/RBAC.md``):
read Vehicles and RedundantAutopilots, patch ``redundantautopilots/status``, create
Events. Identity: the Vehicle whose ``spec.nodeName`` is this node (``NODE_NAME`` from
the downward API), and the RedundantAutopilot whose ``spec.vehicleName`` is that
Vehicle. RedundantAutopilots are listed by the operator-maintained ``roost.dev/node``
label first (the node-restriction admission policy checks that label), then without it,
so a freshly created object is found before the operator has labelled it.

Events about cluster-scoped objects go to the ``default`` namespace, as the operator's
do; their names derive from object, reason, time and message, so a post retried after a
partition is refused as a duplicate instead of recorded twice.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator, Mapping
from datetime import datetime
from pathlib import Path
from typing import Any, Final

import urllib3
from kubernetes import client as k8s
from kubernetes import config as k8s_config
from kubernetes import watch as k8s_watch
from kubernetes.client.exceptions import ApiException

from roost_api.meta import GROUP, VERSION
from roost_api.resources import REDUNDANT_AUTOPILOT, VEHICLE
from roost_api.wellknown import LABEL_NODE

FIELD_MANAGER: Final = "roost-agent"
EVENT_NAMESPACE: Final = "default"
DEFAULT_TIMEOUT: Final = (2.0, 5.0)

Obj = dict[str, Any]


class ApiUnavailableError(Exception):
    """The API server could not be reached or could not serve the request right now."""


def _unavailable(exc: Exception) -> bool:
    if isinstance(exc, ApiException):
        return exc.status is None or exc.status in {0, 429} or exc.status >= 500
    return isinstance(exc, (urllib3.exceptions.HTTPError, OSError, TimeoutError))


def event_name(regarding_name: str, *parts: object) -> str:
    """A deterministic Event name: a retried post of the same Event is a duplicate."""
    digest = hashlib.sha256(json.dumps([str(p) for p in parts]).encode()).hexdigest()[:16]
    return f"{regarding_name}.{digest}"


def event_manifest(
    regarding: Mapping[str, Any],
    *,
    reason: str,
    message: str,
    warning: bool,
    time: datetime,
    node_name: str,
) -> Obj:
    """A core/v1 Event about ``regarding`` reported by this node's agent."""
    meta = regarding["metadata"]
    stamp = time.isoformat().replace("+00:00", "Z")
    return {
        "apiVersion": "v1",
        "kind": "Event",
        "metadata": {
            "name": event_name(meta["name"], meta.get("uid"), reason, stamp, message),
            "namespace": EVENT_NAMESPACE,
        },
        "involvedObject": {
            "apiVersion": regarding.get("apiVersion", f"{GROUP}/{VERSION}"),
            "kind": regarding.get("kind", REDUNDANT_AUTOPILOT.kind),
            "name": meta["name"],
            "uid": meta.get("uid"),
        },
        "reason": reason,
        "message": message[:1024],
        "type": "Warning" if warning else "Normal",
        "source": {"component": FIELD_MANAGER, "host": node_name},
        "reportingComponent": FIELD_MANAGER,
        "reportingInstance": node_name,
        "firstTimestamp": stamp,
        "lastTimestamp": stamp,
        "count": 1,
    }


class AgentKube:
    """The handful of API calls the agent makes; thread-safe (one connection pool)."""

    def __init__(
        self, api: k8s.ApiClient, *, timeout: tuple[float, float] = DEFAULT_TIMEOUT
    ) -> None:
        self.api = api
        self.timeout = timeout
        self._custom = k8s.CustomObjectsApi(api)
        self._core = k8s.CoreV1Api(api)

    @classmethod
    def from_environment(
        cls, kubeconfig: Path | None = None, *, timeout: tuple[float, float] = DEFAULT_TIMEOUT
    ) -> AgentKube:
        """In-cluster service account, else ``kubeconfig`` / ``$KUBECONFIG``; no retries."""
        configuration = k8s.Configuration()
        if kubeconfig is None:
            try:
                k8s_config.load_incluster_config(client_configuration=configuration)  # type: ignore[no-untyped-call]
            except k8s_config.ConfigException:
                k8s_config.load_kube_config(client_configuration=configuration)  # type: ignore[no-untyped-call]
        else:
            k8s_config.load_kube_config(  # type: ignore[no-untyped-call]
                str(kubeconfig), client_configuration=configuration
            )
        configuration.retries = 0
        return cls(k8s.ApiClient(configuration), timeout=timeout)

    def _call(self, function: Any, *args: Any, **kwargs: Any) -> Any:
        try:
            return function(*args, _request_timeout=self.timeout, **kwargs)
        except Exception as exc:
            if _unavailable(exc):
                raise ApiUnavailableError(f"{type(exc).__name__}: {exc}") from exc
            raise

    def _list(self, plural: str, label_selector: str | None = None) -> list[Obj]:
        kwargs = {"label_selector": label_selector} if label_selector else {}
        listed = self._call(
            self._custom.list_cluster_custom_object, GROUP, VERSION, plural, **kwargs
        )
        items: list[Obj] = listed.get("items", [])
        return items

    # -- identity ---------------------------------------------------------------------

    def find_vehicle(self, node_name: str) -> Obj | None:
        """The Vehicle whose ``spec.nodeName`` is ``node_name`` (oldest if several)."""
        mine = [v for v in self._list(VEHICLE.plural) if v["spec"].get("nodeName") == node_name]
        mine.sort(key=lambda v: v["metadata"].get("creationTimestamp", ""))
        return mine[0] if mine else None

    def find_autopilot(self, vehicle_name: str, node_name: str) -> Obj | None:
        """The RedundantAutopilot of ``vehicle_name`` (by node label first, then all)."""
        for selector in (f"{LABEL_NODE}={node_name}", None):
            found = [
                ra
                for ra in self._list(REDUNDANT_AUTOPILOT.plural, selector)
                if ra["spec"].get("vehicleName") == vehicle_name
            ]
            if found:
                found.sort(key=lambda ra: ra["metadata"].get("creationTimestamp", ""))
                return found[0]
        return None

    def get_autopilot(self, name: str) -> Obj | None:
        """The RedundantAutopilot ``name``, or None when it does not exist."""
        try:
            obj: Obj = self._call(
                self._custom.get_cluster_custom_object,
                GROUP,
                VERSION,
                REDUNDANT_AUTOPILOT.plural,
                name,
            )
        except ApiException as exc:
            if exc.status == 404:
                return None
            raise
        return obj

    # -- reporting --------------------------------------------------------------------

    def patch_autopilot_status(self, name: str, status: Mapping[str, Any]) -> Obj:
        """Merge-patch the RedundantAutopilot's status subresource (the agent owns it)."""
        patched: Obj = self._call(
            self._custom.patch_cluster_custom_object_status,
            GROUP,
            VERSION,
            REDUNDANT_AUTOPILOT.plural,
            name,
            {"status": dict(status)},
            field_manager=FIELD_MANAGER,
        )
        return patched

    def post_event(self, manifest: Obj) -> bool:
        """Create an Event; False when it was already recorded (a retried post)."""
        try:
            self._call(self._core.create_namespaced_event, EVENT_NAMESPACE, manifest)
        except ApiException as exc:
            if exc.status == 409:
                return False
            raise
        return True

    # -- following the spec -----------------------------------------------------------

    def watch_autopilot(self, name: str, timeout_s: int) -> Iterator[tuple[str, Obj]]:
        """Events for one RedundantAutopilot, starting with its current state (ADDED).

        Ends after ``timeout_s`` (server side); raises :class:`ApiUnavailableError` when the
        connection fails. The caller simply watches again: each watch begins with the
        object as it is, so nothing missed in between is lost.
        """
        stream = k8s_watch.Watch().stream(  # type: ignore[no-untyped-call]
            self._custom.list_cluster_custom_object,
            GROUP,
            VERSION,
            REDUNDANT_AUTOPILOT.plural,
            field_selector=f"metadata.name={name}",
            timeout_seconds=timeout_s,
            _request_timeout=(self.timeout[0], timeout_s + self.timeout[1]),
        )
        try:
            for event in stream:
                yield str(event["type"]), event["object"]
        except Exception as exc:
            if _unavailable(exc):
                raise ApiUnavailableError(f"watch of {name}: {type(exc).__name__}: {exc}") from exc
            raise
