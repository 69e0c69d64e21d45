"""Nothing changes under a vehicle in the air: the decisions the Vehicle controller takes
while any autopilot of the vehicle is armed.

Armed is the node agent's report (``status.autopilots[].armed`` of the vehicle's
RedundantAutopilot); a vehicle without one, or whose agent never said, is on the ground
as far as the cluster knows. While armed:

- a component pod that differs from the desired one (a config or image change) is not
  replaced: :func:`hold_step` turns the replacement into :attr:`PodStep.DEFER`, the old
  pod keeps running (and counts as Ready), and ``status.flightHold.deferred`` names the
  component; the replacement happens at the first reconcile after landing (the agent's
  report of the disarm is an event). Replacements a failover consequence needs (mavros
  re-pointed at the new active autopilot, without a hub) are not held: that is the
  vehicle flying on. A pod that ended is still recreated (nothing runs to keep), and a
  missing one created;
- a PodDisruptionBudget over the vehicle's component pods with ``maxUnavailable: 0``
  (:func:`disruption_budget`) makes the API server refuse every eviction, so a
  ``kubectl drain`` of its node stops at the vehicle's pods (their names carry the
  vehicle's) and retries until the vehicle has landed; it is deleted on the ground.
  The budget exists only in flight: a fleet on the ground costs no extra object;
- the agent defers its parameter writes by itself (``roost_agent.params``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from roost_api.autopilot import RedundantAutopilotStatus
from roost_api.wellknown import LABEL_MANAGED_BY, LABEL_VEHICLE, MANAGED_BY
from roost_kube.patches import Obj
from roost_operator.vehicles.manifests import pod_hash
from roost_operator.vehicles.pods import PodStep


def hold_reason(status: RedundantAutopilotStatus | None) -> str | None:
    """Why the vehicle counts as in the air (an armed autopilot), or None."""
    armed = [h.name for h in (status.autopilots if status else []) if h.armed]
    if not armed:
        return None
    return f"autopilot {', '.join(armed)} {'is' if len(armed) == 1 else 'are'} armed"


def hold_step(step: PodStep, *, holding: bool) -> PodStep:
    """The pod step to take while ``holding`` (in the air, no failover consequence)."""
    return PodStep.DEFER if holding and step is PodStep.REPLACE else step


def budget_name(vehicle: str) -> str:
    """The name of the vehicle's in-flight PodDisruptionBudget."""
    return f"roost-vehicle-{vehicle}-in-flight"


def disruption_budget(vehicle: str, *, namespace: str, owners: Sequence[Obj]) -> Obj:
    """A PodDisruptionBudget that allows no eviction of the vehicle's component pods."""
    selector = {LABEL_MANAGED_BY: MANAGED_BY, LABEL_VEHICLE: vehicle}
    return {
        "apiVersion": "policy/v1",
        "kind": "PodDisruptionBudget",
        "metadata": {
            "name": budget_name(vehicle),
            "namespace": namespace,
            "labels": dict(selector),
            "ownerReferences": list(owners),
        },
        "spec": {
            "maxUnavailable": 0,
            "selector": {"matchLabels": selector},
            # Not Ready pods are not evictable either: the budget is never "healthy"
            # enough to spare one while maxUnavailable is 0.
            "unhealthyPodEvictionPolicy": "IfHealthyBudget",
        },
    }


def deferred(pods: Mapping[str, Obj], live: Mapping[str, Any | None]) -> list[str]:
    """The components whose live pod is not the desired one (their replacement waits)."""
    out = []
    for component, desired in pods.items():
        pod = live.get(component)
        if pod is None or (pod.get("metadata") or {}).get("deletionTimestamp"):
            continue
        if pod_hash(pod) != pod_hash(desired):
            out.append(component)
    return sorted(out)
