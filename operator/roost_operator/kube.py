"""The one layer through which Roost's handlers talk to the Kubernetes API.

Why a layer of our own instead of the generated ``kubernetes.client`` classes or kopf's
patch objects: every handler (vehicles, missions, autopilots) needs the same four moves
on many kinds — read, list by label, apply desired state, patch with optimistic
locking — and the level-based rule "a reconcile that changes nothing writes nothing"
must hold for all of them. Doing it once here means the rule is tested once.

* Objects are plain dicts (the JSON the API server speaks); the pure desired-state
  functions return the same shape, so there is no model conversion in between.
* :meth:`Kube.apply` is server-side apply with the field manager ``roost-operator``,
  but it first reads the object and skips the request when the live object already
  carries everything desired (see :func:`needs_apply`). Server-side apply alone would
  be correct but would still send one request per object per reconcile.
* :meth:`Kube.merge_patch` can carry ``metadata.resourceVersion``: the server then
  rejects the patch with 409 when someone wrote in between (:class:`ConflictError`), which
  is how Node labels/taints and status conditions (written whole) avoid lost updates.
* Every write is counted in :attr:`Kube.writes` so tests and benchmarks can see what
  a reconcile did.

Authentication and TLS come from ``kubernetes.config`` (in-cluster service account,
else ``$KUBECONFIG``/``~/.kube/config``); requests go through the client's REST layer
with explicit timeouts.

The resource kinds the operator touches are declared below as :class:`Resource`
constants; add one here when a handler needs a new kind (and list its verbs in
``charts/roost/RBAC.md``).
"""

from __future__ import annotations

import hashlib
import json
import threading
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final
from urllib.parse import quote, urlencode

from kubernetes import client as k8s_client
from kubernetes import config as k8s_config

from roost_api.meta import GROUP, VERSION
from roost_api.wellknown import PREFIX

FIELD_MANAGER: Final = "roost-operator"

# Annotation carrying the hash of the manifest Roost last applied to an object, so a
# reconcile can tell "already applied" from "changed" without re-sending it.
ANNOTATION_APPLIED_HASH: Final = f"{PREFIX}applied-hash"

Obj = dict[str, Any]


@dataclass(frozen=True)
class Resource:
    """An API resource: where its objects live in the REST tree."""

    group: str
    version: str
    plural: str
    kind: str
    namespaced: bool

    @property
    def api_version(self) -> str:
        return f"{self.group}/{self.version}" if self.group else self.version

    def collection_path(self, namespace: str | None = None) -> str:
        """Path of the collection (all namespaces when ``namespace`` is None)."""
        base = f"/apis/{self.group}/{self.version}" if self.group else f"/api/{self.version}"
        if self.namespaced and namespace is not None:
            return f"{base}/namespaces/{quote(namespace)}/{self.plural}"
        return f"{base}/{self.plural}"

    def object_path(self, name: str, namespace: str | None = None) -> str:
        if self.namespaced and namespace is None:
            raise ValueError(f"{self.kind} {name} is namespaced: give a namespace")
        return f"{self.collection_path(namespace)}/{quote(name)}"


NODES: Final = Resource("", "v1", "nodes", "Node", namespaced=False)
NAMESPACES: Final = Resource("", "v1", "namespaces", "Namespace", namespaced=False)
CONFIGMAPS: Final = Resource("", "v1", "configmaps", "ConfigMap", namespaced=True)
PODS: Final = Resource("", "v1", "pods", "Pod", namespaced=True)
EVENTS: Final = Resource("", "v1", "events", "Event", namespaced=True)
DEPLOYMENTS: Final = Resource("apps", "v1", "deployments", "Deployment", namespaced=True)
JOBS: Final = Resource("batch", "v1", "jobs", "Job", namespaced=True)
VEHICLES: Final = Resource(GROUP, VERSION, "vehicles", "Vehicle", namespaced=False)
REDUNDANT_AUTOPILOTS: Final = Resource(
    GROUP, VERSION, "redundantautopilots", "RedundantAutopilot", namespaced=False
)
MISSIONS: Final = Resource(GROUP, VERSION, "missions", "Mission", namespaced=True)
LEASES: Final = Resource("coordination.k8s.io", "v1", "leases", "Lease", namespaced=True)

_BY_KIND: Final = {
    (r.api_version, r.kind): r
    for r in (
        NODES,
        NAMESPACES,
        CONFIGMAPS,
        PODS,
        EVENTS,
        DEPLOYMENTS,
        JOBS,
        VEHICLES,
        REDUNDANT_AUTOPILOTS,
        MISSIONS,
        LEASES,
    )
}


def resource_of(manifest: Mapping[str, Any]) -> Resource:
    """The :class:`Resource` a manifest's apiVersion and kind name."""
    key = (manifest["apiVersion"], manifest["kind"])
    if key not in _BY_KIND:
        raise KeyError(f"unknown kind {key}: declare it in roost_operator.kube")
    return _BY_KIND[key]


class ApiError(Exception):
    """The API server answered with an error status."""

    def __init__(self, status: int, method: str, path: str, body: str) -> None:
        self.status = status
        self.body = body
        try:
            self.message = str(json.loads(body).get("message") or body[:500])
        except (ValueError, AttributeError):
            self.message = body[:500]
        super().__init__(f"{method} {path}: HTTP {status}: {self.message}")


class ConflictError(ApiError):
    """409: the object changed since it was read (or already exists)."""


def owner_reference(owner: Mapping[str, Any], *, controller: bool = True) -> Obj:
    """An ownerReference to ``owner`` (any object read from the API)."""
    meta = owner["metadata"]
    return {
        "apiVersion": owner["apiVersion"],
        "kind": owner["kind"],
        "name": meta["name"],
        "uid": meta["uid"],
        "controller": controller,
        "blockOwnerDeletion": False,
    }


def content_hash(value: Any) -> str:
    """A short stable hash of JSON-able data (key order does not matter)."""
    encoded = json.dumps(value, sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(encoded).hexdigest()[:16]


def contains(actual: Any, desired: Any) -> bool:
    """True when every field set in ``desired`` has the same value in ``actual``.

    Fields the server defaulted (present only in ``actual``) are ignored. List elements
    are matched in any order, so entries other managers added do not count as drift.
    """
    if isinstance(desired, Mapping):
        return isinstance(actual, Mapping) and all(
            key in actual and contains(actual[key], value) for key, value in desired.items()
        )
    if isinstance(desired, list):
        return isinstance(actual, list) and all(
            any(contains(candidate, item) for candidate in actual) for item in desired
        )
    return bool(actual == desired)


def with_applied_hash(manifest: Mapping[str, Any]) -> Obj:
    """``manifest`` with its own hash in :data:`ANNOTATION_APPLIED_HASH`."""
    meta = dict(manifest.get("metadata", {}))
    annotations = {
        k: v for k, v in meta.get("annotations", {}).items() if k != ANNOTATION_APPLIED_HASH
    }
    stripped = {**manifest, "metadata": {**meta, "annotations": annotations}}
    annotations[ANNOTATION_APPLIED_HASH] = content_hash(stripped)
    return {**manifest, "metadata": {**meta, "annotations": annotations}}


def needs_apply(desired: Mapping[str, Any], actual: Mapping[str, Any] | None) -> bool:
    """Whether applying ``desired`` (already hashed) would change ``actual``.

    The hash catches fields Roost stopped setting (which a containment check cannot
    see); containment catches hand edits that left the hash in place.
    """
    if actual is None:
        return True
    want = desired["metadata"].get("annotations", {}).get(ANNOTATION_APPLIED_HASH)
    have = actual.get("metadata", {}).get("annotations", {}).get(ANNOTATION_APPLIED_HASH)
    return want != have or not contains(actual, desired)


@dataclass
class Kube:
    """Thin synchronous client for the Kubernetes REST API (thread-safe)."""

    api: k8s_client.ApiClient
    request_timeout: tuple[float, float] = (5.0, 30.0)
    field_manager: str = FIELD_MANAGER
    writes: Counter[str] = field(default_factory=Counter)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @classmethod
    def from_environment(cls) -> Kube:
        """A client configured like kubectl: in-cluster account, else $KUBECONFIG."""
        try:
            k8s_config.load_incluster_config()  # type: ignore[no-untyped-call]
        except k8s_config.ConfigException:
            k8s_config.load_kube_config()  # type: ignore[no-untyped-call]
        return cls(api=k8s_client.ApiClient())

    # -- raw request -------------------------------------------------------------

    def request(
        self,
        method: str,
        path: str,
        *,
        query: Mapping[str, str] | None = None,
        body: Any = None,
        content_type: str = "application/json",
    ) -> Obj | None:
        """Send one request; JSON response as a dict, None on 404 for GET/DELETE."""
        headers = {"Accept": "application/json", "Content-Type": content_type}
        _, url, headers, _, _ = self.api.param_serialize(
            method,
            path,
            header_params=headers,
            auth_settings=["BearerToken"],
        )
        if query:
            url = f"{url}?{urlencode(query)}"
        response = self.api.call_api(
            method, url, header_params=headers, body=body, _request_timeout=self.request_timeout
        )
        raw: bytes = response.read() or b"{}"  # type: ignore[no-untyped-call]
        if method != "GET":
            with self._lock:
                self.writes[method] += 1
        if response.status == 404 and method in ("GET", "DELETE"):
            return None
        if response.status >= 400:
            error = ConflictError if response.status == 409 else ApiError
            raise error(response.status, method, path, raw.decode(errors="replace"))
        decoded: Obj = json.loads(raw)
        return decoded

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
    ) -> list[Obj]:
        """Objects of a kind (optionally in one namespace, matching labels exactly)."""
        query: dict[str, str] = {}
        if labels:
            query["labelSelector"] = ",".join(f"{k}={v}" for k, v in sorted(labels.items()))
        if field_selector:
            query["fieldSelector"] = field_selector
        result = self.request("GET", resource.collection_path(namespace), query=query)
        items: list[Obj] = (result or {}).get("items", [])
        for item in items:  # list items carry no apiVersion/kind; restore them
            item.setdefault("apiVersion", resource.api_version)
            item.setdefault("kind", resource.kind)
        return items

    # -- writes ------------------------------------------------------------------

    def apply(self, manifest: Mapping[str, Any]) -> tuple[Obj, bool]:
        """Server-side apply ``manifest`` unless the live object already matches.

        Returns the live object and whether a write was sent.
        """
        resource = resource_of(manifest)
        desired = with_applied_hash(manifest)
        meta = desired["metadata"]
        actual = self.get(resource, meta["name"], meta.get("namespace"))
        if actual is not None and not needs_apply(desired, actual):
            return actual, False
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
        """JSON merge patch; put ``metadata.resourceVersion`` in it for optimistic locking."""
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

    def delete(self, resource: Resource, name: str, namespace: str | None = None) -> bool:
        """Delete an object in the background; False when it was already gone."""
        gone = self.request(
            "DELETE",
            resource.object_path(name, namespace),
            body={"propagationPolicy": "Background"},
        )
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
        type: str = "Normal",
        at: str,
    ) -> None:
        """Record an Event about ``regarding``; a duplicate post is ignored."""
        try:
            self.create(event_manifest(regarding, reason=reason, message=message, type=type, at=at))
        except ConflictError:
            return


def event_manifest(
    regarding: Mapping[str, Any],
    *,
    reason: str,
    message: str,
    type: str = "Normal",
    at: str,
) -> Obj:
    """A core/v1 Event about ``regarding``; cluster-scoped objects' events go to default.

    ``at`` is an RFC 3339 timestamp. The name is derived from object, reason and time so
    a retried post of the same Event is rejected as a duplicate, not recorded twice.
    """
    meta = regarding["metadata"]
    namespace = meta.get("namespace") or "default"
    name = f"{meta['name']}.{content_hash([meta.get('uid'), reason, message, at])}"
    return {
        "apiVersion": "v1",
        "kind": "Event",
        "metadata": {"name": name, "namespace": namespace},
        "involvedObject": {
            "apiVersion": regarding["apiVersion"],
            "kind": regarding["kind"],
            "name": meta["name"],
            "uid": meta.get("uid"),
            **({"namespace": meta["namespace"]} if meta.get("namespace") else {}),
        },
        "reason": reason,
        "message": message[:1024],
        "type": type,
        "source": {"component": FIELD_MANAGER},
        "reportingComponent": FIELD_MANAGER,
        "firstTimestamp": at,
        "lastTimestamp": at,
        "count": 1,
    }
