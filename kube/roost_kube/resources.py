"""Where each kind the Roost processes touch lives in the REST tree.

Roost's own kinds are derived from :mod:`roost_api.core`'s kind names (plural, scope,
group and version are spelled there and nowhere else; :data:`roost_api.resources.KINDS`
uses the same, and this module imports no pydantic model, so the node agent stays free of
pydantic); the built-in kinds are declared
below. Add a kind here when a process needs a new one, and list its verbs in
``charts/roost/RBAC.md``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final, Protocol
from urllib.parse import quote

from roost_api.core import MISSION_KIND, REDUNDANT_AUTOPILOT_KIND, VEHICLE_KIND


class KindLike(Protocol):
    """A Roost kind: :class:`roost_api.core.KindName` or a
    :class:`roost_api.resources.ResourceKind`."""

    @property
    def group(self) -> str: ...
    @property
    def version(self) -> str: ...
    @property
    def plural(self) -> str: ...
    @property
    def kind(self) -> str: ...
    @property
    def namespaced(self) -> bool: ...


@dataclass(frozen=True)
class Resource:
    """An API resource: where its objects live in the REST tree."""

    group: str
    version: str
    plural: str
    kind: str
    namespaced: bool

    @classmethod
    def of(cls, kind: KindLike) -> Resource:
        """The REST location of a Roost custom resource kind."""
        return cls(kind.group, kind.version, kind.plural, kind.kind, kind.namespaced)

    @property
    def api_version(self) -> str:
        return f"{self.group}/{self.version}" if self.group else self.version

    @property
    def kopf(self) -> tuple[str, str, str]:
        """``(group, version, plural)``, the resource spec kopf's decorators take."""
        return (self.group, self.version, self.plural)

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
SECRETS: Final = Resource("", "v1", "secrets", "Secret", namespaced=True)
PODS: Final = Resource("", "v1", "pods", "Pod", namespaced=True)
EVENTS: Final = Resource("", "v1", "events", "Event", namespaced=True)
JOBS: Final = Resource("batch", "v1", "jobs", "Job", namespaced=True)
VEHICLES: Final = Resource.of(VEHICLE_KIND)
REDUNDANT_AUTOPILOTS: Final = Resource.of(REDUNDANT_AUTOPILOT_KIND)
MISSIONS: Final = Resource.of(MISSION_KIND)
LEASES: Final = Resource("coordination.k8s.io", "v1", "leases", "Lease", namespaced=True)
PODDISRUPTIONBUDGETS: Final = Resource(
    "policy", "v1", "poddisruptionbudgets", "PodDisruptionBudget", namespaced=True
)

ALL: Final = (
    NODES,
    NAMESPACES,
    CONFIGMAPS,
    SECRETS,
    PODS,
    EVENTS,
    JOBS,
    VEHICLES,
    REDUNDANT_AUTOPILOTS,
    MISSIONS,
    LEASES,
    PODDISRUPTIONBUDGETS,
)
_BY_KIND: Final = {(r.api_version, r.kind): r for r in ALL}


def resource_of(manifest: Mapping[str, Any]) -> Resource:
    """The :class:`Resource` a manifest's apiVersion and kind name."""
    key = (manifest["apiVersion"], manifest["kind"])
    if key not in _BY_KIND:
        raise KeyError(f"unknown kind {key}: declare it in roost_kube.resources")
    return _BY_KIND[key]
