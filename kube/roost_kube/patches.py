"""How Roost writes objects: apply only what changed, merge patches that leave nothing stale.

* **Server-side apply, skipped when the live object already matches.** Each applied
  manifest carries a hash of itself in :data:`ANNOTATION_APPLIED_HASH`;
  :func:`needs_apply` compares hashes (which catch fields Roost stopped setting) and
  checks containment (which catches hand edits under an unchanged hash). A reconcile
  that changes nothing then sends nothing.
* **Merge patches with explicit nulls** (:func:`merge_patch_fields`). In a JSON merge
  patch a missing key means "keep", so a field that became empty is sent as ``null``,
  and an object field carries nulls for its emptied members (objects merge
  recursively). Lists are replaced whole and sent without nulls (the schema would
  reject a null inside a list item).
* **Optimistic locking** (:func:`precondition`): a patch that carries
  ``metadata.resourceVersion`` is refused with 409 when someone wrote in between.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping
from typing import Any, Final, Protocol

from roost_api.wellknown import PREFIX

Obj = dict[str, Any]


class ApiDocument(Protocol):
    """An API object as JSON: a pydantic :class:`roost_api.meta.ApiModel` or its plain twin
    from :mod:`roost_api.plain` (the node agent's, which runs without pydantic)."""

    def to_api(self) -> dict[str, Any]:
        """camelCase, no nulls."""
        ...

    def api_dump(self) -> dict[str, Any]:
        """camelCase, nulls included."""
        ...


ANNOTATION_APPLIED_HASH: Final = f"{PREFIX}applied-hash"
"""Annotation carrying the hash of the manifest Roost last applied to an object."""


def content_hash(value: Any) -> str:
    """A short stable hash of JSON-able data (key order does not matter)."""
    encoded = json.dumps(value, sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(encoded).hexdigest()[:16]


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
    """Whether applying ``desired`` (already hashed) would change ``actual``."""
    if actual is None:
        return True
    want = desired["metadata"].get("annotations", {}).get(ANNOTATION_APPLIED_HASH)
    have = actual.get("metadata", {}).get("annotations", {}).get(ANNOTATION_APPLIED_HASH)
    return want != have or not contains(actual, desired)


def merge_patch_fields(
    new: ApiDocument, *, old: ApiDocument | None = None, fields: Iterable[str] | None = None
) -> Obj:
    """A JSON merge patch that makes the live object's ``fields`` equal to ``new``'s.

    ``fields`` are camelCase names (all of ``new``'s when None); with ``old`` (what the
    live object holds), only the fields that differ are included, so an empty result
    means there is nothing to send. Emptied fields go as explicit nulls, as described in
    the module docstring.
    """
    compact = new.to_api()
    with_nulls = new.api_dump()
    before = old.to_api() if old is not None else None
    names = list(with_nulls) if fields is None else list(fields)
    return {
        f: with_nulls[f] if isinstance(with_nulls.get(f), dict) else compact.get(f)
        for f in names
        if before is None or before.get(f) != compact.get(f)
    }


def precondition(obj: Mapping[str, Any], patch: Mapping[str, Any]) -> Obj:
    """``patch`` that only applies while ``obj`` (as read) is unchanged: 409 otherwise."""
    meta = dict(patch.get("metadata", {}))
    meta["resourceVersion"] = obj["metadata"]["resourceVersion"]
    return {**patch, "metadata": meta}
