"""A Mission's geofence on the way to its vehicles' autopilots (the pure part).

How it travels: the Mission's ``spec.fence`` is copied, with the Mission's name and the
fence's content id, into the ``spec.fence`` of each claimed vehicle's RedundantAutopilot
when its preflight begins, and removed when the Mission releases the vehicle. The node
agent reads only its RedundantAutopilot (the same path as ``spec.parameters`` and the
abort command in ``spec.command``), uploads the fence to every autopilot and reports a
``FenceInSync`` condition per autopilot naming the id it holds; the preflight passes a
vehicle only when every autopilot of it (standbys included) holds this Mission's id.
Why there and not a Mission watch in the agent: docs/design-decisions.md.

What the API server cannot check (a crossing polygon needs pairwise edge tests, past
CEL's cost budget) is checked here before anything is claimed: the Mission fails once
with ``InvalidFence``, a permanent error.
"""

from __future__ import annotations

import hashlib
import json
from typing import Any

from roost_api.autopilot import AssignedFence, AutopilotEntryConditionType, Fence
from roost_api.fence import Area, LatLon, fence_problems, held_id
from roost_api.meta import find_condition
from roost_api.mission import MissionSpec, MissionVehicleReason
from roost_operator.missions.observed import AutopilotView, MissionRef
from roost_operator.missions.preflight import PreflightFailure


def area_of(fence: Fence) -> Area:
    """The fence's horizontal area."""
    if fence.circle is not None:
        c = fence.circle
        return Area(centre=LatLon(c.latitude, c.longitude), radius_m=c.radius_m)
    return Area(polygon=tuple(LatLon(p.latitude, p.longitude) for p in fence.polygon))


def invalid_fence(spec: MissionSpec) -> str | None:
    """Why the Mission's fence cannot be used (None: it can, or there is none)."""
    if spec.fence is None:
        return None
    problems = fence_problems(
        area_of(spec.fence), spec.fence.max_altitude_m, flying_altitude_m=spec.flying_altitude_m
    )
    return "; ".join(problems) or None


def fence_id(document: object) -> str:
    """A short stable id of a fence's content (its camelCase document): an autopilot's
    FenceInSync condition names the id it holds, so a preflight can tell this Mission's
    fence from an earlier one (the agent only compares it: it imports no hashing)."""
    text = json.dumps(document, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def assigned(mission: MissionRef, spec: MissionSpec) -> AssignedFence | None:
    """What the Mission writes into its vehicles' RedundantAutopilots."""
    if spec.fence is None:
        return None
    document: dict[str, Any] = spec.fence.model_dump(by_alias=True, mode="json", exclude_none=True)
    return AssignedFence(mission=mission.key, id=fence_id(document), fence=spec.fence)


def fence_patch(fence: AssignedFence | None) -> dict[str, Any]:
    """The merge patch that sets (or removes) ``spec.fence`` on a RedundantAutopilot."""
    value = (
        None if fence is None else fence.model_dump(by_alias=True, mode="json", exclude_none=True)
    )
    return {"spec": {"fence": value}}


def needs_write(want: AssignedFence | None, autopilots: AutopilotView | None) -> bool:
    """Whether the RedundantAutopilot's ``spec.fence`` is not yet ``want``."""
    if autopilots is None:
        return False
    have = autopilots.spec.fence
    if want is None:
        return False
    return have is None or have.id != want.id or have.mission != want.mission


def held_by(mission: MissionRef, autopilots: AutopilotView | None) -> bool:
    """Whether the RedundantAutopilot carries ``mission``'s fence (to remove on release)."""
    return (
        autopilots is not None
        and autopilots.spec.fence is not None
        and autopilots.spec.fence.mission == mission.key
    )


def fence_failures(
    want: AssignedFence | None, autopilots: AutopilotView | None
) -> list[PreflightFailure]:
    """The preflight failure of a vehicle whose autopilots do not all hold ``want``,
    naming each autopilot that does not and why."""
    if want is None or autopilots is None:
        return []
    missing: list[str] = []
    entries = {h.name: h for h in autopilots.status.autopilots}
    for spec in autopilots.spec.autopilots:
        entry = entries.get(spec.name)
        condition = (
            None
            if entry is None
            else find_condition(entry.conditions, AutopilotEntryConditionType.FENCE_IN_SYNC)
        )
        if condition is None:
            missing.append(f"{spec.name}: no FenceInSync condition from the agent yet")
        elif condition.status != "True" or held_id(condition.message) != want.id:
            missing.append(f"{spec.name}: {condition.reason} ({condition.message})")
    if not missing:
        return []
    return [
        PreflightFailure(
            MissionVehicleReason.FENCE_NOT_HELD,
            f"fence {want.id} not held by every autopilot: " + "; ".join(missing),
        )
    ]
