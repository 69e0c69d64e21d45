"""Which vehicles a mission may fly, which of them are free, and what to claim.

Claims are all-or-nothing: a mission claims vehicles only when enough free ones are in
view, and gives back a partial set rather than hold it while it waits. Holding partial
sets deadlocks two missions that each need most of the fleet; giving them back costs a
retry at worst. Candidates are ordered deterministically (named vehicles in the order
given, then selector matches by name) so two competing missions collide on the same
first vehicle, and the loser of that collision gives up early.

Exclusivity itself is not decided here: a claim is a Lease created per vehicle (see
:mod:`roost_operator.claims`), so of two missions claiming one vehicle the API server
accepts exactly one (see :mod:`roost_operator.missions.cluster`).

Which vehicles may be claimed: those whose *vehicle-side* readiness holds — the vehicle
operator's ``NodeBound`` and ``ComponentsReady`` are True — rather than the summary
``Ready``. ``Ready`` also folds in ``AgentConnected`` and ``AutopilotsHealthy`` (which is
False when a standby autopilot is down), and whether those matter is each mission's
choice (``spec.preflight``): a mission that does not require redundancy may fly a
vehicle whose second autopilot has failed. Those checks are the preflight gate's
(:mod:`~roost_operator.missions.preflight`); the planner prefers vehicles that would
pass it, so a fit vehicle is claimed before one that would hold the mission in Preflight.

A claim naming a Mission that no longer exists (its finalizer was removed by hand), or
one that has finished and is not still landing that vehicle (its release did not get
through), is an orphan and counts as free (:func:`holding_missions`). The observer lists
Missions *after* Vehicles and claims, so a claim by a Mission created in between is
never mistaken for an orphan, and taking an orphan over carries the resourceVersion the
claim was read at.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from roost_api.meta import condition_is_true, find_condition
from roost_api.mission import (
    LabelSelector,
    MissionPhase,
    MissionStatus,
    MissionVehiclePhase,
    VehicleSelection,
)
from roost_api.vehicle import VehicleConditionType
from roost_operator.missions.observed import MissionRef, VehicleView, reference_key


def matches_selector(labels: Mapping[str, str], selector: LabelSelector) -> bool:
    """metav1.LabelSelector semantics: every matchLabel and every expression holds."""
    if any(labels.get(key) != value for key, value in selector.match_labels.items()):
        return False
    for requirement in selector.match_expressions:
        present = requirement.key in labels
        value = labels.get(requirement.key)
        holds = {
            "In": present and value in requirement.values,
            "NotIn": not present or value not in requirement.values,
            "Exists": present,
            "DoesNotExist": not present,
        }[requirement.operator]
        if not holds:
            return False
    return True


def candidates(selection: VehicleSelection, vehicles: Mapping[str, VehicleView]) -> list[str]:
    """Vehicles the mission may use, in preference order (names first, then matches)."""
    ordered = [name for name in dict.fromkeys(selection.names) if name in vehicles]
    if selection.selector is not None:
        named = set(ordered)
        ordered += sorted(
            name
            for name, vehicle in vehicles.items()
            if name not in named and matches_selector(vehicle.labels, selection.selector)
        )
    return ordered


# The vehicle operator's conditions that say the vehicle itself can run workloads.
CLAIMABLE_CONDITIONS = (VehicleConditionType.NODE_BOUND, VehicleConditionType.COMPONENTS_READY)


def is_claimable(vehicle: VehicleView) -> bool:
    """Node bound and components ready, and not being deleted (see the module docstring)."""
    conditions = vehicle.status.conditions
    return not vehicle.deleting and all(
        condition_is_true(conditions, kind) for kind in CLAIMABLE_CONDITIONS
    )


def unfit_reason(vehicle: VehicleView) -> str:
    """Why :func:`is_claimable` is False, in the vehicle operator's words."""
    if vehicle.deleting:
        return "being deleted"
    problems = []
    for kind in CLAIMABLE_CONDITIONS:
        condition = find_condition(vehicle.status.conditions, kind)
        if condition is None:
            problems.append(f"no {kind} condition yet")
        elif condition.status != "True":
            detail = f": {condition.message}" if condition.message else ""
            problems.append(f"{kind}={condition.status} ({condition.reason}{detail})")
    return "; ".join(problems)


@dataclass(frozen=True)
class Availability:
    """The mission's candidates other than those it already holds, sorted by state.

    ``free`` keeps the preference order of :func:`candidates`.
    """

    free: list[str] = field(default_factory=list)
    claimed_elsewhere: dict[str, str] = field(default_factory=dict)
    not_ready: dict[str, str] = field(default_factory=dict)
    unknown_names: list[str] = field(default_factory=list)


def availability(
    selection: VehicleSelection,
    vehicles: Mapping[str, VehicleView],
    mission: MissionRef,
    live_missions: frozenset[str],
) -> Availability:
    """Sort the candidates not held by ``mission`` into free, claimed and not ready."""
    result = Availability(unknown_names=[n for n in selection.names if n not in vehicles])
    for name in candidates(selection, vehicles):
        vehicle = vehicles[name]
        claim = vehicle.claimed_by
        if mission.owns(claim):
            continue
        if claim is not None and reference_key(claim) in live_missions:
            result.claimed_elsewhere[name] = reference_key(claim)
        elif not is_claimable(vehicle):
            result.not_ready[name] = unfit_reason(vehicle)
        else:
            result.free.append(name)
    return result


def holding_missions(missions: Iterable[Mapping[str, Any]]) -> frozenset[str]:
    """``namespace/name`` of the Missions whose claims still count.

    Every Mission that has not finished, and a finished one only for as long as one of
    its vehicles is still landing after an abort.
    """
    holding = set()
    for body in missions:
        status = MissionStatus.model_validate(body.get("status") or {})
        landing = any(v.phase == MissionVehiclePhase.ABORTING for v in status.vehicles)
        if not MissionPhase(status.phase).finished or landing:
            meta = body["metadata"]
            holding.add(f"{meta['namespace']}/{meta['name']}")
    return frozenset(holding)


def held_by(mission: MissionRef, vehicles: Mapping[str, VehicleView]) -> list[str]:
    """Vehicles claimed by ``mission``, by name."""
    return sorted(name for name, v in vehicles.items() if mission.owns(v.claimed_by))


def shortage_message(*, required: int, held: int, available: Availability) -> str:
    """Why a mission cannot be assigned yet, naming how many vehicles are missing."""
    missing = required - held - len(available.free)
    parts = [
        f"needs {required} vehicle{'s' if required != 1 else ''}, "
        f"{len(available.free) + held} available: {missing} missing"
    ]
    if available.claimed_elsewhere:
        by_mission = sorted(set(available.claimed_elsewhere.values()))
        parts.append(
            f"{len(available.claimed_elsewhere)} claimed by other missions "
            f"({', '.join(by_mission[:5])}{', …' if len(by_mission) > 5 else ''})"
        )
    if available.not_ready:
        listed = [f"{n} ({why})" for n, why in sorted(available.not_ready.items())[:5]]
        more = ", …" if len(available.not_ready) > 5 else ""
        parts.append(f"{len(available.not_ready)} not ready: {', '.join(listed)}{more}")
    if available.unknown_names:
        parts.append(f"no such vehicle: {', '.join(available.unknown_names[:5])}")
    return "; ".join(parts)
