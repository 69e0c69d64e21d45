"""A Mission's claim on a Vehicle: one ``coordination.k8s.io`` Lease per claimed vehicle.

Why a Lease of its own rather than a field of ``Vehicle.status``: the Vehicle's status
has exactly one writer, the vehicle controller. A claim is decided elsewhere (by the
mission controller, for the Mission), so it lives in an object whose only writer is the
mission controller. The vehicle controller merely mirrors the holder into
``Vehicle.status.claimedBy`` for ``kubectl get vehicles`` and the CLI; nothing decides
on that mirror.

The Lease is the claim:

* it **exists exactly while the vehicle is claimed**; its ``spec.holderIdentity`` is
  the Mission's ``namespace/name``;
* it is **created** to claim (``POST``): of two missions claiming one vehicle, the API
  server accepts exactly one create and answers the other 409 AlreadyExists;
* an **orphaned** claim (its Mission is gone or finished) is taken over by a patch that
  carries the ``resourceVersion`` it was judged orphaned at, so two missions taking it
  over at once again leave exactly one winner;
* it is **released** by a delete with ``preconditions`` (uid and resourceVersion): a
  release never removes a claim someone else made since;
* it is **owned by the Vehicle** (owner reference): deleting the Vehicle deletes its
  claim, so a claim never outlives its vehicle.

Claims live in the operator's namespace. This module is pure: names, manifests and
parsing; the writes are in :mod:`roost_operator.missions.cluster`.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Final

from roost_api.meta import API_VERSION, ObjectReference
from roost_api.resources import VEHICLE
from roost_api.wellknown import LABEL_COMPONENT, LABEL_MANAGED_BY, MANAGED_BY, PREFIX
from roost_kube.patches import Obj
from roost_kube.resources import LEASES

CLAIM_COMPONENT: Final = "claim"
"""``roost.dev/component`` of claim Leases (what the controllers list and watch)."""

ANNOTATION_CLAIMED_VEHICLE: Final = f"{PREFIX}claimed-vehicle"
"""The vehicle a claim Lease is about (a Vehicle name can be longer than a label)."""

ANNOTATION_MISSION_UID: Final = f"{PREFIX}mission-uid"
"""uid of the holding Mission: a Mission re-created under the same name is another one."""

NAME_PREFIX: Final = "claim."
MAX_NAME: Final = 253

CLAIM_LABELS: Final = {LABEL_MANAGED_BY: MANAGED_BY, LABEL_COMPONENT: CLAIM_COMPONENT}


def lease_name(vehicle: str) -> str:
    """Name of the Lease that claims ``vehicle`` (a DNS subdomain of at most 253 chars)."""
    name = f"{NAME_PREFIX}{vehicle}"
    if len(name) <= MAX_NAME:
        return name
    digest = hashlib.sha256(vehicle.encode()).hexdigest()[:10]
    return f"{name[: MAX_NAME - len(digest) - 1].rstrip('.-')}-{digest}"


@dataclass(frozen=True)
class Claim:
    """A claim Lease as read from the API."""

    vehicle: str
    holder: ObjectReference
    mission_uid: str
    resource_version: str
    uid: str

    @property
    def holder_key(self) -> str:
        """``namespace/name`` of the holding Mission."""
        return str(self.holder)


def holder_of(identity: str | None) -> ObjectReference | None:
    """The Mission a Lease's ``holderIdentity`` names, or None when it names none."""
    namespace, _, name = (identity or "").partition("/")
    if not namespace or not name:
        return None
    return ObjectReference(namespace=namespace, name=name)


def claim_of(lease: Mapping[str, Any]) -> Claim | None:
    """The :class:`Claim` a Lease records; None for a Lease that is not a valid claim."""
    meta = lease.get("metadata") or {}
    annotations = meta.get("annotations") or {}
    vehicle = annotations.get(ANNOTATION_CLAIMED_VEHICLE)
    holder = holder_of((lease.get("spec") or {}).get("holderIdentity"))
    if not vehicle or holder is None:
        return None
    return Claim(
        vehicle=vehicle,
        holder=holder,
        mission_uid=annotations.get(ANNOTATION_MISSION_UID, ""),
        resource_version=meta.get("resourceVersion", ""),
        uid=meta.get("uid", ""),
    )


def claims_by_vehicle(leases: Iterable[Mapping[str, Any]]) -> dict[str, Claim]:
    """Claims keyed by vehicle name; Leases that record no claim are left out."""
    claims = (claim_of(lease) for lease in leases)
    return {claim.vehicle: claim for claim in claims if claim is not None}


def micro_time(at: datetime) -> str:
    """A Lease's MicroTime (RFC 3339 with microseconds, UTC)."""
    return at.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def claim_lease(
    *,
    vehicle: str,
    vehicle_uid: str,
    holder: ObjectReference,
    mission_uid: str,
    namespace: str,
    at: datetime,
) -> Obj:
    """The Lease that claims ``vehicle`` for Mission ``holder``; owned by the Vehicle."""
    return {
        "apiVersion": LEASES.api_version,
        "kind": LEASES.kind,
        "metadata": {
            "name": lease_name(vehicle),
            "namespace": namespace,
            "labels": dict(CLAIM_LABELS),
            "annotations": {
                ANNOTATION_CLAIMED_VEHICLE: vehicle,
                ANNOTATION_MISSION_UID: mission_uid,
            },
            "ownerReferences": [
                {
                    "apiVersion": API_VERSION,
                    "kind": VEHICLE.kind,
                    "name": vehicle,
                    "uid": vehicle_uid,
                    "controller": False,
                    "blockOwnerDeletion": False,
                }
            ],
        },
        "spec": {"holderIdentity": str(holder), "acquireTime": micro_time(at)},
    }


def takeover_patch(claim: Claim, holder: ObjectReference, mission_uid: str, at: datetime) -> Obj:
    """Merge patch moving an orphaned ``claim`` to ``holder``, conditional on its version."""
    return {
        "metadata": {
            "resourceVersion": claim.resource_version,
            "annotations": {ANNOTATION_MISSION_UID: mission_uid},
        },
        "spec": {"holderIdentity": str(holder), "acquireTime": micro_time(at)},
    }


def release_options(claim: Claim) -> Obj:
    """DeleteOptions that delete ``claim`` only if nobody changed it since it was read."""
    return {
        "propagationPolicy": "Background",
        "preconditions": {"uid": claim.uid, "resourceVersion": claim.resource_version},
    }
