"""Shared building blocks of the Roost API: the model base, conditions and identifiers.

Every resource model inherits :class:`ApiModel`, which maps snake_case Python names to
the camelCase JSON names Kubernetes uses, so one model serves the CRD generator, the
operator and the agent alike.

Identifiers, name patterns, the shared enums and the condition helpers live in the
pydantic-free :mod:`roost_api.core` (the node agent runs without pydantic) and are
re-exported here.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import datetime
from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from pydantic.alias_generators import to_camel
from pydantic.config import JsonDict

from roost_api import core

# Defined in the pydantic-free roost_api.core (the node agent runs without pydantic).
API_VERSION = core.API_VERSION
CATEGORY = core.CATEGORY
DNS_LABEL_PATTERN = core.DNS_LABEL_PATTERN
DNS_SUBDOMAIN_PATTERN = core.DNS_SUBDOMAIN_PATTERN
GROUP = core.GROUP
VERSION = core.VERSION
ConditionStatus = core.ConditionStatus
HealthLevel = core.HealthLevel
Stack = core.Stack
condition_is_true = core.condition_is_true
find_condition = core.find_condition
now = core.now
same_conditions = core.same_conditions


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

    def api_dump(self) -> dict[str, Any]:
        """Every field by its camelCase name, nulls included (as the plain twins give it)."""
        return self.model_dump(by_alias=True, mode="json")


# Conditions are a list map keyed by type, as in every built-in Kubernetes status.
CONDITIONS_SCHEMA: JsonDict = {
    "x-kubernetes-list-type": "map",
    "x-kubernetes-list-map-keys": ["type"],
}


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
    """:func:`roost_api.core.set_condition` for API model conditions."""
    return core.set_condition(
        conditions,
        make=Condition,
        type=type,
        status=status,
        reason=reason,
        message=message,
        observed_generation=observed_generation,
        at=at,
    )


class ObjectReference(ApiModel):
    """A reference to a namespaced object by namespace and name."""

    namespace: str = Field(max_length=63, description="Namespace of the object.")
    name: str = Field(max_length=253, description="Name of the object.")

    def __str__(self) -> str:
        return f"{self.namespace}/{self.name}"
