"""What the dashboard shows, from cluster objects and agent samples, without a browser.

The model is pure: objects shaped as the API server returns them and samples shaped as
the agent sends them go in, the document the page renders comes out. The browser test
(tests/e2e/test_dashboard_browser.py) checks the same fields on a live sandbox.
"""

from __future__ import annotations

from typing import Any

import pytest

from roost_api.telemetry import Origin, north_east_m
from roost_cli.dashboard import actions_api
from roost_cli.dashboard.model import (
    TELEMETRY_STALE_S,
    TRAIL_POINTS,
    FleetModel,
    fence_doc,
    timeline_kind,
    worst,
)
from tests.unit.test_cli_tables import autopilot, vehicle

ORIGIN = Origin(47.397742, 8.545594)


class Clock:
    def __init__(self) -> None:
        self.now = 1_800_000_000.0

    def __call__(self) -> float:
        return self.now


def sample(
    name: str,
    at: float,
    *,
    active: str = "fc-a",
    health: dict[str, str] | None = None,
    **extra: Any,
) -> dict[str, Any]:
    doc: dict[str, Any] = {
        "vehicle": name,
        "time": at,
        "seq": 1,
        "active": active,
        "latched": False,
        "health": health or {"fc-a": "OK", "fc-b": "OK"},
        "position": {
            "north": 0.0,
            "east": 0.0,
            "down": -2.5,
            "lat": ORIGIN.lat,
            "lon": ORIGIN.lon,
            "heading": 90.0,
            "age": 0.0,
        },
        "origin": {"lat": ORIGIN.lat, "lon": ORIGIN.lon},
        "lastFailover": None,
    }
    doc.update(extra)
    return doc


def model_with_fleet(clock: Clock) -> FleetModel:
    model = FleetModel(clock=clock)
    model.replace("Vehicle", [vehicle("v1"), vehicle("v2")])
    model.replace("RedundantAutopilot", [autopilot("v1"), autopilot("v2")])
    return model


def test_a_fresh_sample_overrides_the_reported_health_and_active_autopilot() -> None:
    clock = Clock()
    model = model_with_fleet(clock)
    model.telemetry(
        "v1", sample("v1", clock.now, active="fc-b", health={"fc-a": "STALE", "fc-b": "OK"})
    )
    doc = model.snapshot(read_only=False, server="https://api")
    v1, v2 = doc["vehicles"]
    assert (v1["name"], v1["active"], v1["worst"], v1["telemetry"]) == (
        "v1",
        "fc-b",
        "STALE",
        "live",
    )
    assert [(a["name"], a["level"], a["active"]) for a in v1["autopilots"]] == [
        ("fc-a", "STALE", False),
        ("fc-b", "OK", True),
    ]
    assert v1["altitude"] == pytest.approx(2.5) and v1["landed"] is False
    assert (v2["telemetry"], v2["position"], v2["worst"]) == ("none", None, "-")


def test_a_stale_sample_no_longer_overrides_the_status() -> None:
    clock = Clock()
    model = model_with_fleet(clock)
    model.telemetry("v1", sample("v1", clock.now, health={"fc-a": "ERROR", "fc-b": "OK"}))
    clock.now += TELEMETRY_STALE_S + 0.1
    v1 = model.snapshot(read_only=False, server="")["vehicles"][0]
    assert v1["telemetry"] == "stale"
    assert v1["worst"] == "-"  # the agent reported no status in this fixture
    assert v1["position"] is None


def test_positions_land_in_the_dashboard_frame_with_a_bounded_trail() -> None:
    clock = Clock()
    model = FleetModel(ORIGIN, clock=clock)
    east_lon = ORIGIN.lon + 0.0001
    for i in range(TRAIL_POINTS + 5):
        s = sample("v1", clock.now + i)
        s["position"]["lon"] = east_lon
        model.telemetry("v1", s)
    [v1] = model.snapshot(read_only=True, server="")["vehicles"]
    expected_north, expected_east = north_east_m(ORIGIN, ORIGIN.lat, east_lon)
    assert v1["position"]["e"] == pytest.approx(expected_east, abs=0.01)
    assert v1["position"]["n"] == pytest.approx(expected_north, abs=0.01)
    assert len(v1["trail"]) == TRAIL_POINTS


def test_the_first_agent_origin_becomes_the_frame_when_none_is_given() -> None:
    clock = Clock()
    model = FleetModel(clock=clock)
    model.telemetry("v1", sample("v1", clock.now))
    assert model.snapshot(read_only=True, server="")["origin"] == {
        "lat": ORIGIN.lat,
        "lon": ORIGIN.lon,
    }


def test_timeline_merges_roost_events_and_live_failovers_in_time_order() -> None:
    clock = Clock()
    model = model_with_fleet(clock)
    events = [
        {
            "metadata": {"uid": "e1", "namespace": "default", "name": "e1"},
            "involvedObject": {"apiVersion": "roost.dev/v1alpha1", "kind": "Mission", "name": "m"},
            "reason": "Started",
            "message": "preflight passed",
            "type": "Normal",
            "lastTimestamp": "2026-05-01T12:00:00Z",
        },
        {
            "metadata": {"uid": "e2", "namespace": "default", "name": "e2"},
            "involvedObject": {"apiVersion": "v1", "kind": "Pod", "name": "p"},
            "reason": "Scheduled",
            "type": "Normal",
            "lastTimestamp": "2026-05-01T12:00:01Z",
        },
    ]
    model.replace("Event", events)
    record = {
        "time": "2026-05-01T12:00:05Z",
        "from": "fc-a",
        "to": "fc-b",
        "reason": "fc-a silent",
        "trigger": "Automatic",
        "latencyMs": 0.4,
    }
    model.telemetry("v1", sample("v1", clock.now, lastFailover=record))
    timeline = model.snapshot(read_only=False, server="")["timeline"]
    assert [(e["kind"], e["object"], e["source"]) for e in timeline] == [
        ("mission", "Mission/m", "event"),
        ("failover", "Vehicle/v1", "agent"),
    ]
    assert "fc-a → fc-b" in timeline[1]["message"]
    model.apply("Event", "DELETED", events[0])
    assert len(model.snapshot(read_only=False, server="")["timeline"]) == 1


@pytest.mark.parametrize(
    ("kind", "reason", "lane"),
    [
        ("RedundantAutopilot", "FailedOver", "failover"),
        ("RedundantAutopilot", "SwitchedByCommand", "failover"),
        ("RedundantAutopilot", "SafetyRoutineLanded", "safety"),
        ("Mission", "Started", "mission"),
        ("Mission", "VehicleFailedOver", "mission"),
        ("Vehicle", "Claimed", "other"),
    ],
)
def test_timeline_lanes(kind: str, reason: str, lane: str) -> None:
    assert timeline_kind(kind, reason) == lane


def test_worst_level_ignores_unknown_levels() -> None:
    assert worst(["OK", "WARN", "-"]) == "WARN"
    assert worst(["OK", "STALE", "ERROR"]) == "STALE"
    assert worst(["-"]) == "-"


def test_an_abort_acts_only_on_the_targets_the_user_confirmed() -> None:
    model = FleetModel()
    model.replace(
        "Mission",
        [
            {
                "metadata": {"uid": "m", "namespace": "default", "name": "survey"},
                "status": {"phase": "Running", "vehicles": [
                    {"name": "v2", "phase": "Running"}, {"name": "v1", "phase": "Running"},
                ]},
            }
        ],
    )  # fmt: skip
    assert actions_api.abort_targets(model, "survey") == ("default", "survey", ["v1", "v2"])
    with pytest.raises(actions_api.RefusedError, match="changed since you confirmed") as refused:
        actions_api._check(["default/survey", "v1", "v2"], ["default/survey", "v1"])
    assert refused.value.status == 409
    actions_api._check(["default/survey", "v1", "v2"], sorted(["v2", "default/survey", "v1"]))
    with pytest.raises(actions_api.RefusedError, match="confirmed"):
        actions_api._confirmed({"confirmed": "v1"})


def fenced_mission(name: str, fence: dict[str, Any], phase: str = "Preflight") -> dict[str, Any]:
    return {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Mission",
        "metadata": {"name": name, "namespace": "default"},
        "spec": {"vehicles": {"names": ["v1"], "count": 1}, "onboard": {}, "fence": fence},
        "status": {"phase": phase},
    }


def test_a_missions_fence_is_placed_in_the_arena_while_the_mission_is_not_finished() -> None:
    polygon = {
        "polygon": [
            {"latitude": ORIGIN.lat, "longitude": ORIGIN.lon},
            {"latitude": ORIGIN.lat, "longitude": ORIGIN.lon + 0.001},
            {"latitude": ORIGIN.lat + 0.001, "longitude": ORIGIN.lon},
        ],
        "maxAltitudeM": 30,
        "action": "Land",
    }
    circle = {
        "circle": {"latitude": ORIGIN.lat, "longitude": ORIGIN.lon, "radiusM": 50},
        "maxAltitudeM": 20,
    }
    model = FleetModel(origin=ORIGIN, clock=Clock())
    model.replace(
        "Mission",
        [
            fenced_mission("poly", polygon),
            fenced_mission("round", circle),
            fenced_mission("done", circle, phase="Succeeded"),
        ],
    )
    doc = model.snapshot(read_only=True, server="s")
    fences = {m["name"]: m["fence"] for m in doc["missions"]}
    assert fences["default/done"] is None
    assert fences["default/round"] == {
        "maxAltitudeM": 20.0,
        "action": "Return",
        "circle": [0.0, 0.0, 50.0],
    }
    north, east = north_east_m(ORIGIN, ORIGIN.lat + 0.001, ORIGIN.lon)
    assert fences["default/poly"]["polygon"][2] == [round(north, 2), round(east, 2)]
    assert "spec" not in doc["missions"][0]
    assert fence_doc({"polygon": "nonsense"}, ORIGIN) is None


def test_without_an_origin_no_fence_is_placed() -> None:
    model = FleetModel(clock=Clock())
    model.replace(
        "Mission",
        [
            fenced_mission(
                "poly", {"circle": {"latitude": 1, "longitude": 2, "radiusM": 5}, "maxAltitudeM": 9}
            )
        ],
    )
    assert model.snapshot(read_only=True, server="s")["missions"][0]["fence"] is None
