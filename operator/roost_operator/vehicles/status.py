"""Writing a Vehicle's status: only the fields that changed, never over a newer status.

The Vehicle controller (:mod:`.controller`) is the only writer of ``Vehicle.status``.
:func:`write_vehicle_status` sends a JSON merge patch of the fields that changed,
carrying the ``resourceVersion`` the new status was computed from: a write in between
(a human, kopf's own annotations) causes a 409 and a decision from a fresh read, never a
lost update of a list written whole (the conditions).

Nothing is sent when nothing changed, which keeps idle reconciles free of writes.
Transitions of the chosen condition types are recorded as Events.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from roost_api.meta import now
from roost_api.vehicle import VehicleStatus
from roost_kube.client import Kube
from roost_kube.patches import Obj, merge_patch_fields
from roost_kube.resources import VEHICLES
from roost_operator.vehicles.desired import transitions


def status_patch(
    old: VehicleStatus, new: VehicleStatus, fields: Iterable[str]
) -> dict[str, Any] | None:
    """Merge patch of ``fields`` (camelCase) that differ, or None when none do.

    In a merge patch a missing key means "keep", so a field that became empty is sent as
    an explicit null, and an object field carries nulls for its emptied members (objects
    merge recursively). Lists are replaced whole and sent without nulls, which the
    schema would reject inside list items.
    """
    return merge_patch_fields(new, old=old, fields=fields) or None


def write_vehicle_status(
    kube: Kube,
    vehicle: Mapping[str, Any],
    old: VehicleStatus,
    new: VehicleStatus,
    *,
    fields: Iterable[str],
    event_types: Iterable[str],
) -> Obj | None:
    """Patch the owned ``fields`` of ``vehicle``'s status if they changed; the Vehicle as
    written, or None when nothing needed writing.

    Raises :class:`~roost_kube.errors.ConflictError` when the Vehicle changed since
    ``vehicle`` was read: recompute from a fresh read and call again.
    """
    patch = status_patch(old, new, fields)
    if patch is None:
        return None
    meta = vehicle["metadata"]
    written = kube.merge_patch(
        VEHICLES,
        meta["name"],
        {"metadata": {"resourceVersion": meta["resourceVersion"]}, "status": patch},
        subresource="status",
    )
    at = now()
    for cond in transitions(old.conditions, new.conditions, event_types):
        kube.post_event(
            vehicle,
            reason=cond.reason,
            message=f"{cond.type} is {cond.status}: {cond.message}",
            type="Normal" if cond.status == "True" else "Warning",
            at=at,
        )
    return written
