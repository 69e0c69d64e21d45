"""A Mission's fence in the operator (roost_operator.missions.fence and its hooks in the
mission machine): written to the claimed vehicles' RedundantAutopilots, required of
every autopilot by the preflight, refused once when the API server could not refuse it."""

from __future__ import annotations

from typing import Any

from roost_api.autopilot import AssignedFence
from roost_api.fence import held_message
from roost_api.mission import MissionPhase, MissionReason, MissionVehicleReason
from roost_operator.missions.fence import (
    assigned,
    fence_failures,
    fence_id,
    fence_patch,
    invalid_fence,
)
from roost_operator.missions.machine import plan_mission
from roost_operator.missions.observed import AutopilotView
from tests.support.missions import ME, autopilots, claimed, mission_spec, observe, vehicle_status

SQUARE = [
    {"latitude": 47.0, "longitude": 8.0},
    {"latitude": 47.0, "longitude": 8.001},
    {"latitude": 47.001, "longitude": 8.001},
    {"latitude": 47.001, "longitude": 8.0},
]
FENCE = {"polygon": SQUARE, "maxAltitudeM": 40}
NAMES = {"names": ["a"], "count": 1}


def with_fence(
    ap: AutopilotView, fence: AssignedFence | None, held: dict[str, str]
) -> AutopilotView:
    """``ap`` carrying ``fence`` in its spec and each named autopilot's FenceInSync
    (a fence id it holds, or a failure reason)."""
    spec = ap.spec.model_copy(update={"fence": fence})
    entries = []
    for entry in ap.status.autopilots:
        state = held.get(entry.name)
        conditions: list[dict[str, Any]] = []
        if state is not None:
            ok = not state.startswith("!")
            conditions.append(
                {
                    "type": "FenceInSync",
                    "status": "True" if ok else "False",
                    "reason": "FenceHeld" if ok else state[1:],
                    "message": held_message(state, "polygon") if ok else "uploading: refused",
                    "lastTransitionTime": "2026-01-01T00:00:00Z",
                }
            )
        entries.append({**entry.to_api(), "conditions": conditions})
    status = ap.status.model_validate({**ap.status.to_api(), "autopilots": entries})
    return AutopilotView(name=ap.name, spec=spec, status=status)


def test_the_fence_goes_to_the_vehicle_and_preflight_waits_for_every_autopilot() -> None:
    spec = mission_spec(vehicles=NAMES, fence=FENCE)
    want = assigned(ME, spec)
    assert want is not None and want.mission == ME.key
    plan = plan_mission(observe(claimed("a"), spec=spec))
    assert plan.fences == {"a": want}
    assert plan.status.phase == MissionPhase.PREFLIGHT
    v = vehicle_status(plan, "a")
    assert v.reason == MissionVehicleReason.FENCE_NOT_HELD
    assert "fc1: no FenceInSync condition from the agent yet" in v.message


def test_preflight_names_the_autopilot_that_does_not_hold_the_fence() -> None:
    spec = mission_spec(vehicles=NAMES, fence=FENCE)
    want = assigned(ME, spec)
    assert want is not None
    cases = [
        ({"fc1": want.id, "fc2": want.id}, []),
        ({"fc1": want.id, "fc2": "!UploadRefused"}, ["fc2: UploadRefused (uploading: refused)"]),
        ({"fc1": want.id, "fc2": "0123456789ab"}, ["fc2: FenceHeld (holds fence 0123456789ab"]),
        ({"fc1": want.id}, ["fc2: no FenceInSync condition"]),
    ]
    for held, named in cases:
        failures = fence_failures(want, with_fence(autopilots("a"), want, held))
        text = "; ".join(f.message for f in failures)
        assert all(n in text for n in named), (held, text)
        assert bool(failures) == bool(named)
        assert "fc1" not in text


def test_a_vehicle_whose_autopilots_hold_the_fence_starts_and_the_fence_is_not_rewritten() -> None:
    spec = mission_spec(vehicles=NAMES, fence=FENCE)
    want = assigned(ME, spec)
    assert want is not None
    ap = with_fence(autopilots("a"), want, {"fc1": want.id, "fc2": want.id})
    plan = plan_mission(observe(claimed("a"), spec=spec, aps=[ap]))
    assert plan.status.phase == MissionPhase.RUNNING
    assert plan.fences == {}


def test_a_self_crossing_polygon_fails_the_mission_once_before_anything_is_claimed() -> None:
    bowtie = [SQUARE[0], SQUARE[2], SQUARE[1], SQUARE[3]]
    spec = mission_spec(vehicles=NAMES, fence={"polygon": bowtie, "maxAltitudeM": 40})
    assert (invalid_fence(spec) or "").startswith("fence polygon: the polygon intersects itself")
    plan = plan_mission(observe([], spec=spec))
    assert (plan.status.phase, plan.status.reason) == (
        MissionPhase.FAILED,
        MissionReason.INVALID_FENCE,
    )
    assert plan.claims == [] and plan.fences == {}
    again = plan_mission(observe([], spec=spec, status=plan.status))
    assert again.status.phase == MissionPhase.FAILED
    assert [e.reason for e in again.events] == []  # reported once


def test_the_patch_sets_or_removes_the_fence() -> None:
    want = assigned(ME, mission_spec(vehicles=NAMES, fence=FENCE))
    assert want is not None
    patch = fence_patch(want)
    assert patch["spec"]["fence"]["id"] == want.id
    assert patch["spec"]["fence"]["fence"]["maxAltitudeM"] == 40
    assert fence_patch(None) == {"spec": {"fence": None}}


def test_the_fence_id_follows_the_content_not_the_key_order() -> None:
    a = fence_id({"circle": {"latitude": 47.0}, "maxAltitudeM": 40})
    assert a == fence_id({"maxAltitudeM": 40, "circle": {"latitude": 47.0}})
    assert a != fence_id({"maxAltitudeM": 41, "circle": {"latitude": 47.0}})
    assert len(a) == 12
