"""Where the dashboard's data comes from: Kubernetes watches and the agents' streams.

* **Watches** (one daemon thread per kind: Vehicles, RedundantAutopilots, Missions,
  Events): list, then watch from the list's resourceVersion; a watch that ends is resumed
  from the last version seen, a version the server forgot (410) or a failure lists again
  after a pause. Every object and event goes into the :class:`~.model.FleetModel`. The
  API server is read with the identity of whoever runs the dashboard.
* **Telemetry** (one asyncio task per vehicle): a WebSocket client of the vehicle's agent
  (:mod:`roost_agent.telemetry`) feeding each sample into the model, reconnecting with a
  growing pause while the agent is unreachable. The set of endpoints is re-read every
  second (a Vehicle annotated later is picked up), see :class:`Endpoints`. On a real
  cluster the agents are reached through the API server's pod proxy
  (:class:`ApiProxy`), with the same credentials as the watches: the dashboard needs no
  route to the vehicles' network, and the cluster's RBAC (``get pods/proxy``) decides.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import ssl
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from websockets.asyncio.client import connect
from websockets.exceptions import WebSocketException

from roost_api.meta import API_VERSION
from roost_api.telemetry import pod_proxy_path
from roost_api.wellknown import ANNOTATION_TELEMETRY, ANNOTATION_TELEMETRY_POD
from roost_cli.dashboard.model import FleetModel
from roost_kube.client import Kube
from roost_kube.errors import ApiError, ApiUnavailableError
from roost_kube.resources import EVENTS, MISSIONS, REDUNDANT_AUTOPILOTS, VEHICLES, Resource

log = logging.getLogger(__name__)

TELEMETRY_ANNOTATION = ANNOTATION_TELEMETRY
"""A Vehicle annotation naming its agent's telemetry URL (``ws://HOST:PORT/``)."""
WATCH_TIMEOUT_S = 240
RETRY_S = 2.0
RECONNECT_MAX_S = 5.0
ENDPOINTS_EVERY_S = 1.0
ROOST_EVENTS = f"involvedObject.apiVersion={API_VERSION}"
"""Only the Events about Roost objects: the API server filters, the dashboard keeps less."""
WATCHED: tuple[tuple[str, Resource, str], ...] = (
    ("Vehicle", VEHICLES, ""),
    ("RedundantAutopilot", REDUNDANT_AUTOPILOTS, ""),
    ("Mission", MISSIONS, ""),
    ("Event", EVENTS, ROOST_EVENTS),
)


class Watcher:
    """Keeps the model in step with one kind, on a daemon thread, until :meth:`stop`."""

    def __init__(
        self, kube: Kube, model: FleetModel, kind: str, resource: Resource, selector: str = ""
    ) -> None:
        self._kube = kube
        self._model = model
        self._kind = kind
        self._resource = resource
        self._selector = selector
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"watch-{kind}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                items, version = self._kube.list_with_version(
                    self._resource, field_selector=self._selector
                )
                self._model.replace(self._kind, items)
                self._model.set_cluster_error(None)
                while not self._stop.is_set():
                    version = self._watch(version)
            except (ApiError, ApiUnavailableError) as error:
                if getattr(error, "status", None) != 410:  # 410: forgotten version: list again
                    self._model.set_cluster_error(f"{self._kind}: {error}")
                    self._stop.wait(RETRY_S)

    def _watch(self, version: str) -> str:
        for change, obj in self._kube.watch_collection(
            self._resource,
            resource_version=version,
            field_selector=self._selector,
            timeout_s=WATCH_TIMEOUT_S,
        ):
            version = str(obj.get("metadata", {}).get("resourceVersion") or version)
            if change != "BOOKMARK":
                self._model.apply(self._kind, change, obj)
            if self._stop.is_set():
                break
        return version


@dataclass(frozen=True)
class ApiProxy:
    """The API server as a way to the agents (its pod proxy), with the dashboard's
    credentials: ``server`` (``https://…``), the TLS context and the headers (a bearer
    token, re-read on every connection as kubectl does)."""

    server: str
    ssl: ssl.SSLContext
    headers: Callable[[], Mapping[str, str]] = dict

    @property
    def base(self) -> str:
        """The server's address as a WebSocket URL prefix (``wss://host:port``)."""
        return "wss://" + self.server.rstrip("/").split("://", 1)[-1]

    def url(self, pod_reference: str) -> str | None:
        """The stream's URL through the pod proxy (None: a malformed reference)."""
        path = pod_proxy_path(pod_reference)
        return None if path is None else self.base + path

    def options(self, url: str) -> dict[str, Any]:
        """What ``connect`` needs for ``url``: TLS and credentials when it is ours."""
        if not url.startswith(self.base + "/"):
            return {}
        return {"ssl": self.ssl, "additional_headers": dict(self.headers())}


@dataclass
class Endpoints:
    """Which URL each vehicle's telemetry is read from, by precedence:

    ``--agent VEHICLE=URL`` flags, then a running sandbox's record (its agents announce
    their URLs), then the agent pod the Vehicle's ``roost.dev/telemetry-pod`` annotation
    names, through the API server's pod proxy (``proxy``: the dashboard has a cluster),
    then the Vehicle's ``roost.dev/telemetry`` annotation (a direct connection, for a
    dashboard on the vehicles' network). Both annotations are written by the agent.
    """

    flags: Mapping[str, str] = field(default_factory=dict)
    sandbox: Callable[[], Mapping[str, str]] = dict
    proxy: ApiProxy | None = None

    def resolve(self, model: FleetModel) -> dict[str, str]:
        found = model.telemetry_endpoints(TELEMETRY_ANNOTATION)
        if self.proxy is not None:
            for vehicle, reference in model.telemetry_endpoints(ANNOTATION_TELEMETRY_POD).items():
                url = self.proxy.url(reference)
                if url is not None:
                    found[vehicle] = url
        found.update(self.sandbox())
        found.update(self.flags)
        return found

    def options(self, url: str) -> dict[str, Any]:
        """Extra arguments of ``connect`` for ``url`` (see :meth:`ApiProxy.options`)."""
        return self.proxy.options(url) if self.proxy is not None else {}


class TelemetryClients:
    """One WebSocket client per vehicle endpoint, kept in step with :class:`Endpoints`."""

    def __init__(self, model: FleetModel, endpoints: Endpoints) -> None:
        self._model = model
        self._endpoints = endpoints
        self._tasks: dict[str, tuple[str, asyncio.Task[None]]] = {}

    async def run(self) -> None:
        """Reconcile the clients with the endpoints every second, until cancelled."""
        try:
            while True:
                wanted = self._endpoints.resolve(self._model)
                for vehicle, (url, task) in list(self._tasks.items()):
                    if wanted.get(vehicle) != url:
                        task.cancel()
                        del self._tasks[vehicle]
                for vehicle, url in wanted.items():
                    if vehicle not in self._tasks:
                        task = asyncio.create_task(self._follow(vehicle, url))
                        self._tasks[vehicle] = (url, task)
                await asyncio.sleep(ENDPOINTS_EVERY_S)
        finally:
            for _, task in self._tasks.values():
                task.cancel()

    async def _follow(self, vehicle: str, url: str) -> None:
        pause = 0.2
        while True:
            try:
                options = self._endpoints.options(url)
                async with connect(url, compression=None, open_timeout=3, **options) as ws:
                    pause = 0.2
                    async for message in ws:
                        self._model.telemetry(vehicle, json.loads(message))
            except (OSError, WebSocketException, TimeoutError, ValueError) as error:
                log.debug("telemetry of %s at %s: %s", vehicle, url, error)
            self._model.telemetry_lost(vehicle)
            await asyncio.sleep(pause)
            pause = min(RECONNECT_MAX_S, pause * 2)


def start_watchers(kube: Kube, model: FleetModel) -> list[Watcher]:
    watchers = [Watcher(kube, model, *watched) for watched in WATCHED]
    for watcher in watchers:
        watcher.start()
    return watchers


async def cancel(task: asyncio.Task[None]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
