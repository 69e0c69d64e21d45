"""Typed views of the objects a mission decision reads, parsed once from API dicts.

The state machine works on these instead of raw dicts so that every field it relies on
is validated by the API models (a malformed status from an old agent raises here, at
the edge, not halfway through a decision).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime
from enum import StrEnum
from typing import Any

from roost_api.autopilot import RedundantAutopilotSpec, RedundantAutopilotStatus
from roost_api.meta import ObjectReference, find_condition
from roost_api.vehicle import (
    VehicleConditionReason,
    VehicleConditionType,
    VehicleSpec,
    VehicleStatus,
)
from roost_operator.claims import Claim


@dataclass(frozen=True)
class MissionRef:
    """Identity of a Mission: what a vehicle's claim (:mod:`roost_operator.claims`) names."""

    namespace: str
    name: str
    uid: str

    @property
    def key(self) -> str:
        return f"{self.namespace}/{self.name}"

    @property
    def reference(self) -> ObjectReference:
        return ObjectReference(namespace=self.namespace, name=self.name)

    def owns(self, claim: ObjectReference | None) -> bool:
        """True when ``claim`` (the holder of a vehicle's claim) is this mission."""
        return claim is not None and claim.namespace == self.namespace and claim.name == self.name


def reference_key(ref: ObjectReference) -> str:
    """``namespace/name`` of a claim, comparable with :attr:`MissionRef.key`."""
    return f"{ref.namespace}/{ref.name}"


@dataclass(frozen=True)
class VehicleView:
    """A Vehicle as read from the API."""

    name: str
    labels: Mapping[str, str]
    spec: VehicleSpec
    status: VehicleStatus
    resource_version: str
    uid: str = ""
    deleting: bool = False
    annotations: Mapping[str, str] = field(default_factory=dict)
    """Its annotations (the fleet guards' pause switch and latch clear live there)."""
    claim: Claim | None = None
    """The mission claim on it (its claim Lease), if any."""

    @property
    def claimed_by(self) -> ObjectReference | None:
        """The Mission holding the vehicle, if any."""
        return self.claim.holder if self.claim is not None else None

    @property
    def unreachable_since(self) -> datetime | None:
        """Since when the vehicle's node cannot be reached (its NodeBound condition says
        NodeUnreachable), or None while it can."""
        bound = find_condition(self.status.conditions, VehicleConditionType.NODE_BOUND)
        if bound is None or bound.reason != VehicleConditionReason.NODE_UNREACHABLE:
            return None
        return bound.last_transition_time

    @property
    def node_name(self) -> str:
        """The node its workloads run on (status wins while a hot swap settles)."""
        return self.status.node_name or self.spec.node_name

    @classmethod
    def from_body(cls, body: Mapping[str, Any], claim: Claim | None = None) -> VehicleView:
        meta = body["metadata"]
        return cls(
            name=meta["name"],
            labels=dict(meta.get("labels") or {}),
            spec=VehicleSpec.model_validate(body["spec"]),
            status=VehicleStatus.model_validate(body.get("status") or {}),
            resource_version=meta.get("resourceVersion", ""),
            uid=meta.get("uid", ""),
            deleting=bool(meta.get("deletionTimestamp")),
            annotations=dict(meta.get("annotations") or {}),
            claim=claim,
        )


@dataclass(frozen=True)
class AutopilotView:
    """A RedundantAutopilot as read from the API (status written by the node agent)."""

    name: str
    spec: RedundantAutopilotSpec
    status: RedundantAutopilotStatus

    @property
    def vehicle_name(self) -> str:
        return self.spec.vehicle_name

    @classmethod
    def from_body(cls, body: Mapping[str, Any]) -> AutopilotView:
        return cls(
            name=body["metadata"]["name"],
            spec=RedundantAutopilotSpec.model_validate(body["spec"]),
            status=RedundantAutopilotStatus.model_validate(body.get("status") or {}),
        )


class JobPhase(StrEnum):
    """What a Job's status says, reduced to what a mission needs."""

    ACTIVE = "Active"
    SUCCEEDED = "Succeeded"
    FAILED = "Failed"


# Job condition types: the terminal ones and the targets the Job controller sets first
# (Kubernetes 1.31+) while it still terminates pods.
_SUCCESS_CONDITIONS = ("Complete", "SuccessCriteriaMet")
_FAILURE_CONDITIONS = ("Failed", "FailureTarget")


@dataclass(frozen=True)
class JobView:
    """A Job as read from the API."""

    name: str
    phase: JobPhase
    active: int = 0
    ready: int = 0
    succeeded: int = 0
    failed: int = 0
    message: str = ""
    created: datetime | None = None
    deleting: bool = False

    @property
    def started(self) -> bool:
        """A pod of this Job is running or has run (ready, succeeded or failed)."""
        return self.ready > 0 or self.succeeded > 0 or self.failed > 0

    @classmethod
    def from_body(cls, body: Mapping[str, Any]) -> JobView:
        meta = body["metadata"]
        status = body.get("status") or {}
        true_conditions = {
            c["type"]: c for c in status.get("conditions") or [] if c.get("status") == "True"
        }
        phase = JobPhase.ACTIVE
        message = ""
        for kind, types in (
            (JobPhase.FAILED, _FAILURE_CONDITIONS),
            (JobPhase.SUCCEEDED, _SUCCESS_CONDITIONS),
        ):
            hit = next((true_conditions[t] for t in types if t in true_conditions), None)
            if hit is not None:
                phase = kind
                message = hit.get("message") or hit.get("reason") or ""
                break
        created = meta.get("creationTimestamp")
        return cls(
            name=meta["name"],
            phase=phase,
            active=int(status.get("active") or 0),
            ready=int(status.get("ready") or 0),
            succeeded=int(status.get("succeeded") or 0),
            failed=int(status.get("failed") or 0),
            message=message,
            created=datetime.fromisoformat(created) if created else None,
            deleting=bool(meta.get("deletionTimestamp")),
        )
