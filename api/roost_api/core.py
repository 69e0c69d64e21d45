"""The pydantic-free part of the API: group, name patterns, shared enums and conditions.

The node agent runs on a companion computer where every megabyte counts, and
``import pydantic`` alone costs several MB there (plus libcrypto, pulled in through
``secrets``). So whatever the agent needs besides the models themselves lives here and in
:mod:`roost_api.autopilot_enums`, imported by :mod:`roost_api.meta` and
:mod:`roost_api.autopilot` and re-exported from there: one definition, reachable without
pydantic. The agent's model classes are plain dataclasses generated from the pydantic
models (:mod:`roost_api.plain`).

Conditions follow ``metav1.Condition``. :func:`set_condition` is the one place that
decides when ``lastTransitionTime`` moves (only when ``status`` changes), so agent and
operator cannot disagree about it; it works on any condition class (the pydantic one in
:mod:`roost_api.meta` or the plain one in :mod:`roost_api.plain`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import StrEnum
from typing import Literal, Protocol, TypeVar

GROUP = "roost.dev"
VERSION = "v1alpha1"
API_VERSION = f"{GROUP}/{VERSION}"
CATEGORY = "roost"

# DNS-1123 label: the shape of Kubernetes object names and of autopilot names.
DNS_LABEL_PATTERN = r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?$"
DNS_SUBDOMAIN_PATTERN = r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?(\.[a-z0-9]([-a-z0-9]*[a-z0-9])?)*$"


@dataclass(frozen=True)
class KindName:
    """Where a Roost kind lives in the API: its kind, plural and scope (group and version
    are the API's). :mod:`roost_api.resources` adds the models and the CRD's details; the
    agent's API client needs only this."""

    kind: str
    plural: str
    scope: Literal["Cluster", "Namespaced"]

    @property
    def namespaced(self) -> bool:
        return self.scope == "Namespaced"

    @property
    def group(self) -> str:
        return GROUP

    @property
    def version(self) -> str:
        return VERSION


VEHICLE_KIND = KindName("Vehicle", "vehicles", "Cluster")
REDUNDANT_AUTOPILOT_KIND = KindName("RedundantAutopilot", "redundantautopilots", "Cluster")
MISSION_KIND = KindName("Mission", "missions", "Namespaced")


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

ConditionStatus = Literal["True", "False", "Unknown"]


class ConditionLike(Protocol):
    """What the condition helpers read of a condition (pydantic or plain)."""

    @property
    def type(self) -> str: ...

    @property
    def status(self) -> str: ...

    @property
    def last_transition_time(self) -> datetime: ...


C = TypeVar("C", bound=ConditionLike)


def now() -> datetime:
    """The current time in UTC, truncated to seconds as Kubernetes stores it."""
    return datetime.now(UTC).replace(microsecond=0)


def set_condition(
    conditions: Sequence[C],
    *,
    make: Callable[..., C],
    type: str,
    status: ConditionStatus,
    reason: str,
    message: str = "",
    observed_generation: int | None = None,
    at: datetime | None = None,
) -> list[C]:
    """Return ``conditions`` with ``type`` set, moving lastTransitionTime only on change.

    ``make`` builds a condition from the condition fields (the condition class). The
    list keeps its order; a new type is appended. Pure: the input is not modified.
    """

    def made(since: datetime) -> C:
        return make(
            type=type,
            status=status,
            reason=reason,
            message=message,
            observed_generation=observed_generation,
            last_transition_time=since,
        )

    result: list[C] = []
    found = False
    for cond in conditions:
        if cond.type != type:
            result.append(cond)
            continue
        found = True
        moved = cond.status != status
        result.append(made((at or now()) if moved else cond.last_transition_time))
    if not found:
        result.append(made(at or now()))
    return result


def find_condition(conditions: Iterable[C], type: str) -> C | None:
    """The condition of this type, or None."""
    return next((c for c in conditions if c.type == type), None)


def condition_is_true(conditions: Iterable[ConditionLike], type: str) -> bool:
    """True only when the condition exists and its status is "True"."""
    cond = find_condition(conditions, type)
    return cond is not None and cond.status == "True"


def same_conditions(a: Sequence[ConditionLike], b: Sequence[ConditionLike]) -> bool:
    """Equal ignoring nothing but order-insensitive: used to skip no-op status writes."""
    key = lambda c: c.type  # noqa: E731
    return sorted(a, key=key) == sorted(b, key=key)
