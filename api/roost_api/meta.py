"""Shared building blocks of the Roost API: the model base, conditions and identifiers.

Every resource model inherits :class:`ApiModel`, which maps snake_case Python names to
the camelCase JSON names Kubernetes uses, so one model serves the CRD generator, the
operator and the agent alike.

Conditions follow ``metav1.Condition``. :func:`set_condition` is the one place that
decides when ``lastTransitionTime`` moves (only when ``status`` changes), so agent and
operator cannot disagree about it.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from datetime import UTC, datetime
from enum import StrEnum
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field
from pydantic.alias_generators import to_camel
from pydantic.config import JsonDict

GROUP = "roost.dev"
VERSION = "v1alpha1"
API_VERSION = f"{GROUP}/{VERSION}"
CATEGORY = "roost"

# DNS-1123 label: the shape of Kubernetes object names and of autopilot names.
DNS_LABEL_PATTERN = r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?$"
DNS_SUBDOMAIN_PATTERN = r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?(\.[a-z0-9]([-a-z0-9]*[a-z0-9])?)*$"


class ApiModel(BaseModel):
    """Base for every API object: camelCase on the wire, tolerant of unknown fields.

    Unknown fields are ignored rather than rejected so an older agent keeps reading a
    newer spec; the API server's structural schema is what rejects bad input.
    """

    model_config = ConfigDict(
        alias_generator=to_camel,
        populate_by_name=True,
        extra="ignore",
        use_enum_values=True,
        # Validators are built on first use, not at import: a standalone node agent
        # uses a few of the API's models, and every built one costs memory.
        defer_build=True,
    )

    def to_api(self) -> dict[str, Any]:
        """The JSON body Kubernetes expects: camelCase, no nulls."""
        return self.model_dump(by_alias=True, exclude_none=True, mode="json")


class Stack(StrEnum):
    """Autopilot flight stack; decides heartbeat, mode and sensor-bit conventions."""

    PX4 = "px4"
    ARDUPILOT = "ardupilot"


class HealthLevel(StrEnum):
    """Health of one autopilot, in the order of diagnostic_msgs levels (worse is larger)."""

    OK = "OK"
    WARN = "WARN"
    STARTING = "STARTING"  # booting, estimator or GPS start-up: not failed, not usable yet
    ERROR = "ERROR"
    STALE = "STALE"

    @property
    def rank(self) -> int:
        """0 for OK up to 4 for STALE, for comparisons."""
        return _HEALTH_RANK[self]


_HEALTH_RANK = {
    HealthLevel.OK: 0,
    HealthLevel.WARN: 1,
    HealthLevel.STARTING: 2,
    HealthLevel.ERROR: 3,
    HealthLevel.STALE: 4,
}

# Conditions are a list map keyed by type, as in every built-in Kubernetes status.
CONDITIONS_SCHEMA: JsonDict = {
    "x-kubernetes-list-type": "map",
    "x-kubernetes-list-map-keys": ["type"],
}

ConditionStatus = Literal["True", "False", "Unknown"]


class Condition(ApiModel):
    """One aspect of an object's state, in the shape of ``metav1.Condition``."""

    type: str = Field(
        max_length=316,
        pattern=r"^([a-z0-9]([-a-z0-9]*[a-z0-9])?(\.[a-z0-9]([-a-z0-9]*[a-z0-9])?)*/)?"
        r"(([A-Za-z0-9][-A-Za-z0-9_.]*)?[A-Za-z0-9])$",
        description="Type of condition in CamelCase, e.g. Ready.",
    )
    status: ConditionStatus = Field(description="True, False or Unknown.")
    reason: str = Field(
        max_length=1024,
        pattern=r"^[A-Za-z]([A-Za-z0-9_,:]*[A-Za-z0-9_])?$",
        description="Programmatic CamelCase identifier for the last transition.",
    )
    message: str = Field(
        default="", max_length=32768, description="Human-readable details of the transition."
    )
    observed_generation: int | None = Field(
        default=None,
        ge=0,
        description="metadata.generation of the object this condition was computed from.",
    )
    last_transition_time: datetime = Field(
        description="When status last changed (not when the condition was last written)."
    )


def now() -> datetime:
    """The current time in UTC, truncated to seconds as Kubernetes stores it."""
    return datetime.now(UTC).replace(microsecond=0)


def set_condition(
    conditions: Sequence[Condition],
    *,
    type: str,
    status: ConditionStatus,
    reason: str,
    message: str = "",
    observed_generation: int | None = None,
    at: datetime | None = None,
) -> list[Condition]:
    """Return ``conditions`` with ``type`` set, moving lastTransitionTime only on change.

    The list keeps its order; a new type is appended. Pure: the input is not modified.
    """
    result: list[Condition] = []
    found = False
    for cond in conditions:
        if cond.type != type:
            result.append(cond)
            continue
        found = True
        moved = cond.status != status
        result.append(
            Condition(
                type=type,
                status=status,
                reason=reason,
                message=message,
                observed_generation=observed_generation,
                last_transition_time=(at or now()) if moved else cond.last_transition_time,
            )
        )
    if not found:
        result.append(
            Condition(
                type=type,
                status=status,
                reason=reason,
                message=message,
                observed_generation=observed_generation,
                last_transition_time=at or now(),
            )
        )
    return result


def find_condition(conditions: Iterable[Condition], type: str) -> Condition | None:
    """The condition of this type, or None."""
    return next((c for c in conditions if c.type == type), None)


def condition_is_true(conditions: Iterable[Condition], type: str) -> bool:
    """True only when the condition exists and its status is "True"."""
    cond = find_condition(conditions, type)
    return cond is not None and cond.status == "True"


def same_conditions(a: Sequence[Condition], b: Sequence[Condition]) -> bool:
    """Equal ignoring nothing but order-insensitive: used to skip no-op status writes."""
    key = lambda c: c.type  # noqa: E731
    return sorted(a, key=key) == sorted(b, key=key)


class ObjectReference(ApiModel):
    """A reference to a namespaced object by namespace and name."""

    namespace: str = Field(max_length=63, description="Namespace of the object.")
    name: str = Field(max_length=253, description="Name of the object.")

    def __str__(self) -> str:
        return f"{self.namespace}/{self.name}"
