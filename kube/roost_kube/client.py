"""The REST client every Roost process talks to the API server through.

Why our own thin client instead of the generated ``kubernetes.client`` API classes: the
operator, the agent and the CLI need the same few moves on many kinds — get, list by
label, server-side apply, merge patch (with a ``resourceVersion`` precondition when
written whole), create, delete, watch one object, post an Event — and the same error
semantics for all of them. Objects stay plain dicts (the JSON the server speaks), so
the pure planning functions and the wire share one shape.

* **Timeouts are the caller's**: ``timeout=(connect, read)`` at construction (the agent
  on a drone uses 2 s/5 s, the operator 5 s/30 s, the CLI 10 s), overridable per call.
* **Retries are the caller's**: :meth:`Kube.from_environment` sets urllib3's retries
  (the agent 0, since its publisher backs off itself).
* **Errors** are :mod:`roost_kube.errors` classes, transport failures included; GET and
  DELETE of a missing object return None instead of raising.
* Every write is counted in :attr:`Kube.writes` so tests and benchmarks see what a
  reconcile did.
* Every request (watches excepted) is reported to the callbacks registered with
  :func:`observe_requests` — method, outcome, seconds — which is how the operator's
  Prometheus metrics count API calls without this layer importing prometheus_client.

Authentication and TLS come from the ``kubernetes`` client's own config loaders
(:class:`roost_kube.transport.ApiClientTransport`), or, for the node agent, from the
minimal :class:`roost_kube.transport.DirectTransport` (``Kube.from_environment(...,
direct=True)``: a service account or a kubeconfig with a certificate or token, without
importing the ``kubernetes`` package). Requests, errors and results are the same.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

from roost_kube.errors import ApiUnavailableError, ConflictError, error_for_status, transport_of
from roost_kube.events import EventType, event_manifest
from roost_kube.kubeconfig import existing, split_list
from roost_kube.patches import Obj, needs_apply, with_applied_hash
from roost_kube.resources import Resource, resource_of
from roost_kube.transport import (
    ApiClientTransport,
    Credentials,
    DirectTransport,
    Request,
    Response,
    Transport,
    from_kubeconfig,
    in_cluster,
)

Timeout = tuple[float, float]
"""``(connect, read)`` seconds."""

RequestObserver = Callable[[str, str, float], None]
"""``(method, result, seconds)``: result is the HTTP status (``"200"``) or ``"unavailable"``."""

_observers: list[RequestObserver] = []


def observe_requests(observer: RequestObserver) -> Callable[[], None]:
    """Report every request of every :class:`Kube` in this process; returns the undo."""
    _observers.append(observer)
    return lambda: _observers.remove(observer)


def _report(method: str, result: str, started: float) -> None:
    seconds = time.perf_counter() - started
    for observer in _observers:
        observer(method, result, seconds)


class _Unread:
    """Marks an argument the caller did not read (distinct from None, "absent")."""


UNREAD = _Unread()


@dataclass
class Kube:
    """Thin synchronous client for the Kubernetes REST API (thread-safe).

    ``api`` is a ``kubernetes.client.ApiClient`` or a :class:`~roost_kube.transport.Transport`.
    """

    api: Any
    field_manager: str
    timeout: Timeout = (5.0, 30.0)
    writes: Counter[str] = field(default_factory=Counter)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _transport: Transport = field(init=False, repr=False)

    def __post_init__(self) -> None:
        is_transport = isinstance(self.api, (DirectTransport, ApiClientTransport))
        self._transport = self.api if is_transport else ApiClientTransport(self.api)

    @classmethod
    def from_environment(
        cls,
        field_manager: str,
        *,
        kubeconfig: Path | str | None = None,
        context: str | None = None,
        timeout: Timeout = (5.0, 30.0),
        retries: int | None = None,
        connections: int | None = None,
        direct: bool = False,
    ) -> Kube:
        """A client configured like kubectl.

        With no ``kubeconfig``: the in-cluster service account, else ``$KUBECONFIG`` (a
        list is merged) or ``~/.kube/config``. ``retries`` replaces urllib3's default.
        ``connections``: how many connections to keep open for reuse — at least the
        number of threads that send requests at once (each watch holds one for its
        whole length); beyond the pool, every request pays a new TLS handshake.
        ``direct``: through :class:`~roost_kube.transport.DirectTransport` (the agent).
        """
        if direct:
            return cls(
                DirectTransport(
                    _credentials(kubeconfig, context), retries=retries, connections=connections
                ),
                field_manager,
                timeout,
            )
        from kubernetes import client as k8s_client  # noqa: PLC0415 - not for the agent
        from kubernetes import config as k8s_config  # noqa: PLC0415

        configuration = k8s_client.Configuration()
        if connections is not None:
            configuration.connection_pool_maxsize = connections
        if kubeconfig is None:
            try:
                k8s_config.load_incluster_config(client_configuration=configuration)  # type: ignore[no-untyped-call]
            except k8s_config.ConfigException:
                k8s_config.load_kube_config(  # type: ignore[no-untyped-call]
                    context=context, client_configuration=configuration
                )
        else:
            k8s_config.load_kube_config(  # type: ignore[no-untyped-call]
                config_file=str(kubeconfig), context=context, client_configuration=configuration
            )
        if retries is not None:
            configuration.retries = retries
        api = k8s_client.ApiClient(configuration)
        api.user_agent = field_manager  # names the program in the API server's logs and audit
        return cls(api, field_manager, timeout)

    def close(self) -> None:
        """Close the connections; a short-lived client (a test, a benchmark) is used as a
        context manager instead."""
        self._transport.close()

    def __enter__(self) -> Kube:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def server(self) -> str:
        """The API server's URL."""
        return self._transport.host

    # -- raw request -------------------------------------------------------------

    def _send(
        self,
        method: str,
        path: str,
        *,
        query: Mapping[str, str] | None,
        body: Any,
        content_type: str,
        timeout: Timeout | None,
        headers: Mapping[str, str] | None = None,
    ) -> Response:
        headers = {"Accept": "application/json", "Content-Type": content_type, **(headers or {})}
        url = f"{path}?{urlencode(query)}" if query else path
        try:
            return self._transport.send(
                Request(method, url, headers, body, timeout or self.timeout)
            )
        except Exception as exc:
            transport = transport_of(exc)
            if transport is None:
                raise
            raise ApiUnavailableError(
                None, method, path, f"{type(exc).__name__}: {exc}", transport=transport
            ) from exc

    def request(
        self,
        method: str,
        path: str,
        *,
        query: Mapping[str, str] | None = None,
        body: Any = None,
        content_type: str = "application/json",
        timeout: Timeout | None = None,
    ) -> Obj | None:
        """Send one request; JSON response as a dict, None on 404 for GET/DELETE."""
        started = time.perf_counter()
        try:
            response = self._send(
                method,
                path,
                query=query,
                body=body,
                content_type=content_type,
                timeout=timeout or self.timeout,
            )
            raw = response.read() or b"{}"
        except ApiUnavailableError:
            _report(method, "unavailable", started)
            raise
        _report(method, str(response.status), started)
        if method != "GET":
            with self._lock:
                self.writes[method] += 1
        if response.status == 404 and method in ("GET", "DELETE"):
            return None
        if response.status >= 400:
            raise error_for_status(response.status, method, path, raw.decode(errors="replace"))
        decoded: Obj = json.loads(raw)
        return decoded

    def get_bytes(
        self, path: str, *, headers: Mapping[str, str] | None = None, timeout: Timeout | None = None
    ) -> Response:
        """GET ``path`` for bytes, not JSON (a pod proxy's files): the status and the body,
        unread, whatever the status; the caller reads or releases it."""
        return self._send(
            "GET",
            path,
            query=None,
            body=None,
            content_type="application/json",
            timeout=timeout or self.timeout,
            headers={"Accept": "*/*", **(headers or {})},
        )

    # -- reads -------------------------------------------------------------------

    def get(self, resource: Resource, name: str, namespace: str | None = None) -> Obj | None:
        """The object, or None when it does not exist."""
        return self.request("GET", resource.object_path(name, namespace))

    def list_objects(
        self,
        resource: Resource,
        *,
        namespace: str | None = None,
        labels: Mapping[str, str] | None = None,
        field_selector: str | None = None,
        limit: int | None = None,
    ) -> list[Obj]:
        """Objects of a kind (optionally in one namespace, matching labels exactly)."""
        query: dict[str, str] = {}
        if labels:
            query["labelSelector"] = ",".join(f"{k}={v}" for k, v in sorted(labels.items()))
        if field_selector:
            query["fieldSelector"] = field_selector
        if limit:
            query["limit"] = str(limit)
        result = self.request("GET", resource.collection_path(namespace), query=query)
        items: list[Obj] = (result or {}).get("items", [])
        for item in items:  # list items carry no apiVersion/kind; restore them
            item.setdefault("apiVersion", resource.api_version)
            item.setdefault("kind", resource.kind)
        return items

    def list_with_version(
        self,
        resource: Resource,
        *,
        namespace: str | None = None,
        field_selector: str = "",
        label_selector: str = "",
    ) -> tuple[list[Obj], str]:
        """Every object of a kind (matching the selectors) and the list's
        resourceVersion (to watch from)."""
        query = {
            key: value
            for key, value in (("fieldSelector", field_selector), ("labelSelector", label_selector))
            if value
        }
        result = self.request("GET", resource.collection_path(namespace), query=query or None) or {}
        items: list[Obj] = result.get("items", [])
        for item in items:  # list items carry no apiVersion/kind; restore them
            item.setdefault("apiVersion", resource.api_version)
            item.setdefault("kind", resource.kind)
        return items, str(result.get("metadata", {}).get("resourceVersion", ""))

    def watch(
        self, resource: Resource, name: str, *, namespace: str | None = None, timeout_s: int
    ) -> Iterator[tuple[str, Obj]]:
        """Watch events for one object, starting with its current state (ADDED).

        Ends after ``timeout_s`` (server side); raises :class:`ApiUnavailableError` when
        the connection fails. The caller simply watches again: each watch begins with
        the object as it is, so nothing missed in between is lost.
        """
        query = {"fieldSelector": f"metadata.name={name}"}
        return self._watch(resource, namespace, query, timeout_s, f"watch of {name}")

    def watch_collection(
        self,
        resource: Resource,
        *,
        resource_version: str,
        namespace: str | None = None,
        field_selector: str = "",
        label_selector: str = "",
        timeout_s: int,
    ) -> Iterator[tuple[str, Obj]]:
        """Watch every object of a kind (matching the selectors, applied by the server)
        from ``resource_version`` (a list's, see :meth:`list_with_version`). A version the
        server no longer has raises :class:`~roost_kube.errors.ApiError` with status 410:
        list again."""
        query = {"resourceVersion": resource_version, "allowWatchBookmarks": "true"}
        if field_selector:
            query["fieldSelector"] = field_selector
        if label_selector:
            query["labelSelector"] = label_selector
        return self._watch(resource, namespace, query, timeout_s, f"watch of {resource.plural}")

    def _watch(
        self,
        resource: Resource,
        namespace: str | None,
        query: Mapping[str, str],
        timeout_s: int,
        what: str,
    ) -> Iterator[tuple[str, Obj]]:
        path = resource.collection_path(namespace)
        query = {**query, "watch": "true", "timeoutSeconds": str(timeout_s)}
        response = self._send(
            "GET",
            path,
            query=query,
            body=None,
            content_type="application/json",
            timeout=(self.timeout[0], timeout_s + self.timeout[1]),
        )
        if response.status >= 400:
            raw = response.read() or b"{}"
            raise error_for_status(response.status, "GET", path, raw.decode(errors="replace"))
        try:
            for line in response.lines():
                if not line.strip():
                    continue
                event = json.loads(line)
                if event.get("type") == "ERROR":
                    status = event.get("object", {})
                    raise error_for_status(
                        int(status.get("code") or 500), "WATCH", path, json.dumps(status)
                    )
                yield str(event["type"]), event["object"]
        except Exception as exc:
            transport = transport_of(exc)
            if transport is None:
                raise
            raise ApiUnavailableError(
                None, "WATCH", path, f"{what}: {type(exc).__name__}: {exc}", transport=transport
            ) from exc
        finally:
            response.release()

    # -- writes ------------------------------------------------------------------

    def apply(
        self, manifest: Mapping[str, Any], *, current: Mapping[str, Any] | _Unread | None = UNREAD
    ) -> tuple[Obj, bool]:
        """Server-side apply ``manifest`` unless the live object already matches.

        ``current`` is the live object (None: absent) when the caller knows it, from a
        watch cache say; otherwise it is read first. Returns the live object and whether
        a write was sent.
        """
        resource = resource_of(manifest)
        desired = with_applied_hash(manifest)
        meta = desired["metadata"]
        actual = (
            self.get(resource, meta["name"], meta.get("namespace"))
            if isinstance(current, _Unread)
            else current
        )
        if actual is not None and not needs_apply(desired, actual):
            return dict(actual), False
        applied = self.request(
            "PATCH",
            resource.object_path(meta["name"], meta.get("namespace")),
            query={"fieldManager": self.field_manager, "force": "true"},
            body=desired,
            content_type="application/apply-patch+yaml",
        )
        assert applied is not None
        return applied, True

    def merge_patch(
        self,
        resource: Resource,
        name: str,
        patch: Mapping[str, Any],
        *,
        namespace: str | None = None,
        subresource: str | None = None,
    ) -> Obj:
        """JSON merge patch (see :mod:`roost_kube.patches` for nulls and preconditions)."""
        path = resource.object_path(name, namespace)
        if subresource:
            path = f"{path}/{subresource}"
        patched = self.request(
            "PATCH",
            path,
            query={"fieldManager": self.field_manager},
            body=dict(patch),
            content_type="application/merge-patch+json",
        )
        assert patched is not None
        return patched

    def create(self, manifest: Mapping[str, Any]) -> Obj:
        """Create an object (raises :class:`ConflictError` if it exists)."""
        resource = resource_of(manifest)
        created = self.request(
            "POST",
            resource.collection_path(manifest["metadata"].get("namespace")),
            query={"fieldManager": self.field_manager},
            body=dict(manifest),
        )
        assert created is not None
        return created

    def delete(
        self,
        resource: Resource,
        name: str,
        namespace: str | None = None,
        *,
        grace_period_s: int | None = None,
    ) -> bool:
        """Delete an object in the background; False when it was already gone.

        ``grace_period_s`` 0 removes a pod at once, without its kubelet's confirmation
        (for a pod whose node cannot be reached).
        """
        body: dict[str, Any] = {"propagationPolicy": "Background"}
        if grace_period_s is not None:
            body["gracePeriodSeconds"] = grace_period_s
        gone = self.request("DELETE", resource.object_path(name, namespace), body=body)
        return gone is not None

    def delete_all(self, resource: Resource, objects: Sequence[Mapping[str, Any]]) -> list[str]:
        """Delete each listed object; the names actually deleted."""
        deleted = []
        for obj in objects:
            meta = obj["metadata"]
            if self.delete(resource, meta["name"], meta.get("namespace")):
                deleted.append(meta["name"])
        return deleted

    def post_event(
        self,
        regarding: Mapping[str, Any],
        *,
        reason: str,
        message: str,
        at: datetime | str,
        type: EventType = "Normal",
        instance: str | None = None,
    ) -> bool:
        """Record an Event about ``regarding``; False when it was already recorded."""
        manifest = event_manifest(
            regarding,
            reason=reason,
            message=message,
            at=at,
            component=self.field_manager,
            type=type,
            instance=instance,
        )
        try:
            self.create(manifest)
        except ConflictError:
            return False
        return True


def _credentials(kubeconfig: Path | str | None, context: str | None) -> Credentials:
    """What :class:`~roost_kube.transport.DirectTransport` connects with: the in-cluster
    service account, else the kubeconfig (``kubeconfig``, ``$KUBECONFIG`` or
    ``~/.kube/config``, as for the ``kubernetes`` loaders)."""
    if kubeconfig is None:
        pod = in_cluster()
        if pod is not None:
            return pod
        files = existing(split_list(os.environ.get("KUBECONFIG", "")))
        files = files or [Path("~/.kube/config").expanduser()]
    else:
        files = [Path(kubeconfig)]
    return from_kubeconfig(files, context)
