"""The rows `roost status`, `roost missions` and the sandbox's event feed show.

Pure functions over API objects shaped as the API server returns them (camelCase dicts),
so these run without a cluster; the e2e sandbox test reads the same columns from a live
fleet.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Any

from rich.console import Console

from roost_cli import render, tables

NOW = datetime(2026, 5, 1, 12, 0, 0, tzinfo=UTC)


def _iso(seconds_ago: float) -> str:
    return (NOW - timedelta(seconds=seconds_ago)).isoformat().replace("+00:00", "Z")


def vehicle(
    name: str, *, ready: str | None = "True", reason: str = "AllGood", **status: Any
) -> dict[str, Any]:
    obj: dict[str, Any] = {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Vehicle",
        "metadata": {"name": name},
        "spec": {"nodeName": f"node-{name}", "sysid": 10},
        "status": dict(status),
    }
    if ready is not None:
        obj["status"]["conditions"] = [
            {"type": "Ready", "status": ready, "reason": reason, "lastTransitionTime": _iso(60)}
        ]
    return obj


def autopilot(
    vehicle_name: str, *, status: dict[str, Any] | None = None, name: str | None = None
) -> dict[str, Any]:
    return {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "RedundantAutopilot",
        "metadata": {"name": name or vehicle_name},
        "spec": {
            "vehicleName": vehicle_name,
            "primary": "fc-a",
            "autopilots": [
                {"name": "fc-a", "stack": "px4", "connection": "udp://127.0.0.1:1", "sysid": 1,
                 "bridgeChannel": 0},
                {"name": "fc-b", "stack": "px4", "connection": "udp://127.0.0.1:2", "sysid": 2,
                 "bridgeChannel": 1},
            ],
        },
        "status": status or {},
    }  # fmt: skip


def mission(name: str, phase: str, vehicles: list[dict[str, Any]], **spec: Any) -> dict[str, Any]:
    return {
        "apiVersion": "roost.dev/v1alpha1",
        "kind": "Mission",
        "metadata": {"name": name, "namespace": "default"},
        "spec": {
            "vehicles": {"names": [v["name"] for v in vehicles] or ["x"], "count": 1},
            "onboard": {"spec": {"containers": []}},
            **spec,
        },
        "status": {"phase": phase, "vehicles": vehicles, "assignedCount": len(vehicles)},
    }


FAILED_OVER: dict[str, Any] = {
    "activeAutopilot": "fc-b",
    "autopilots": [
        {"name": "fc-a", "level": "ERROR", "reasons": ["heartbeat lost 3.1 s", "silent"]},
        {"name": "fc-b", "level": "OK", "reasons": []},
    ],
    "lastFailover": {
        "time": _iso(12),
        "from": "fc-a",
        "to": "fc-b",
        "reason": "heartbeat lost on fc-a",
        "latencyMs": 21.4,
        "trigger": "Automatic",
        "safetyRoutine": "Landed",
    },
    "failoverCount": 1,
}


def test_a_failed_over_vehicle_shows_active_health_and_the_last_failover() -> None:
    [row] = tables.fleet_rows([vehicle("d1")], [autopilot("d1", status=FAILED_OVER)], [], NOW)
    assert row.vehicle == "d1"
    assert row.node == "node-d1"
    assert row.active == "fc-b"
    assert [(c.name, c.level, c.active) for c in row.autopilots] == [
        ("fc-a", "ERROR", False),
        ("fc-b", "OK", True),
    ]
    assert row.health == "fc-a ERROR (heartbeat lost 3.1 s) · fc-b OK"
    assert row.worst_level == "ERROR"
    assert row.last_failover == "fc-a → fc-b 12s ago"
    assert row.failover_detail == "heartbeat lost on fc-a, 21 ms, Automatic, safety routine Landed"


def test_autopilots_the_agent_has_not_reported_show_a_dash_in_spec_order() -> None:
    [row] = tables.fleet_rows([vehicle("d1", ready=None)], [autopilot("d1")], [], NOW)
    assert [(c.name, c.level) for c in row.autopilots] == [("fc-a", "-"), ("fc-b", "-")]
    assert row.active == "-"
    assert row.ready == "-"
    assert row.worst_level == "-"
    assert row.last_failover == "-"


def test_not_ready_shows_the_conditions_reason_and_ready_hides_it() -> None:
    rows = tables.fleet_rows(
        [vehicle("b", ready="False", reason="AgentNotConnected"), vehicle("a")], [], [], NOW
    )
    assert [(r.vehicle, r.ready, r.ready_reason) for r in rows] == [
        ("a", "True", ""),
        ("b", "False", "AgentNotConnected"),
    ]
    assert rows[0].health == "-"


def test_an_autopilot_object_named_differently_from_its_vehicle_still_belongs_to_it() -> None:
    [row] = tables.fleet_rows(
        [vehicle("d1")], [autopilot("d1", name="other", status=FAILED_OVER)], [], NOW
    )
    assert row.active == "fc-b"


def test_a_reported_autopilot_missing_from_the_spec_is_still_shown() -> None:
    status = dict(
        FAILED_OVER, autopilots=[*FAILED_OVER["autopilots"], {"name": "fc-z", "level": "STALE"}]
    )
    [row] = tables.fleet_rows([vehicle("d1")], [autopilot("d1", status=status)], [], NOW)
    assert [c.name for c in row.autopilots] == ["fc-a", "fc-b", "fc-z"]
    assert row.worst_level == "STALE"


def test_a_status_that_breaks_the_contract_leaves_its_columns_empty_not_the_table() -> None:
    broken = vehicle("d1")
    broken["status"] = {"conditions": [{"type": "Ready"}]}  # no status, reason or time
    [row] = tables.fleet_rows(
        [broken], [autopilot("d1", status={"autopilots": [{"level": "OK"}]})], [], NOW
    )
    assert row.ready == "-"
    assert row.node == "node-d1"
    assert [c.level for c in row.autopilots] == ["-", "-"]


def test_the_mission_column_follows_the_claim_and_shows_the_vehicles_phase() -> None:
    claimed = vehicle("d1", claimedBy={"namespace": "default", "name": "survey"})
    missions = [
        mission("old", "Succeeded", [{"name": "d1", "phase": "Succeeded"}]),
        mission("survey", "Running", [{"name": "d1", "phase": "Aborting"}]),
    ]
    [row] = tables.fleet_rows([claimed], [], missions, NOW)
    assert row.mission == "default/survey Aborting"


def test_without_a_claim_only_an_unfinished_mission_listing_the_vehicle_counts() -> None:
    finished = [mission("old", "Succeeded", [{"name": "d1", "phase": "Succeeded"}])]
    assert tables.fleet_rows([vehicle("d1")], [], finished, NOW)[0].mission == "-"
    running = [*finished, mission("new", "Preflight", [{"name": "d1", "phase": "Preflight"}])]
    assert (
        tables.fleet_rows([vehicle("d1")], [], running, NOW)[0].mission == "default/new Preflight"
    )


def test_ages_read_like_kubectl() -> None:
    assert tables.format_age(None, NOW) == "-"
    assert tables.format_age(NOW + timedelta(seconds=5), NOW) == "0s"
    assert tables.format_age(NOW - timedelta(seconds=59), NOW) == "59s"
    assert tables.format_age(NOW - timedelta(minutes=5, seconds=59), NOW) == "5m"
    assert tables.format_age(NOW - timedelta(hours=3), NOW) == "3h"
    assert tables.format_age(NOW - timedelta(days=2, hours=23), NOW) == "2d"


def test_mission_rows_show_assignment_vehicles_degraded_and_abort() -> None:
    degraded = mission(
        "survey",
        "Running",
        [{"name": "d1", "phase": "Running"}, {"name": "d2", "phase": "Aborted"}],
        abort=True,
    )
    degraded["spec"]["vehicles"]["count"] = 2
    degraded["status"]["startTime"] = _iso(90)
    degraded["status"]["message"] = "d2 failed over and landed"
    degraded["status"]["conditions"] = [
        {"type": "Degraded", "status": "True", "reason": "VehicleAborted",
         "lastTransitionTime": _iso(10)}
    ]  # fmt: skip
    rows = tables.mission_rows([degraded, mission("a-first", "Pending", [])], NOW)
    assert [r.name for r in rows] == ["default/a-first", "default/survey"]
    survey = rows[1]
    assert survey.phase == "Running"
    assert survey.assigned == "2/2"
    assert survey.vehicles == "d1 Running, d2 Aborted"
    assert survey.degraded == "True"
    assert survey.abort is True
    assert survey.started == "1m"
    assert survey.message == "d2 failed over and landed"
    assert rows[0].vehicles == "-"
    assert rows[0].started == "-"


def test_a_mission_without_status_is_pending() -> None:
    fresh = mission("new", "Pending", [])
    del fresh["status"]
    [row] = tables.mission_rows([fresh], NOW)
    assert (row.phase, row.assigned, row.degraded) == ("Pending", "0/1", "-")


def _event(
    name: str, seconds_ago: float, api_version: str = "roost.dev/v1alpha1", **extra: Any
) -> dict[str, Any]:
    return {
        "metadata": {"name": name, "creationTimestamp": _iso(seconds_ago + 100)},
        "involvedObject": {"apiVersion": api_version, "kind": "RedundantAutopilot", "name": "d1"},
        "reason": name,
        "message": f"{name} happened",
        "type": "Warning",
        "lastTimestamp": _iso(seconds_ago),
        **extra,
    }


def test_event_rows_keep_the_newest_roost_events_oldest_first() -> None:
    events = [
        _event("FailedOver", 5),
        _event("SafetyRoutine", 2),
        _event("Scheduled", 1, api_version="v1"),
        _event("Claimed", 30),
        _event("Old", 300),
    ]
    rows = tables.event_rows(events, NOW, limit=3)
    assert [(r.reason, r.age) for r in rows] == [
        ("Claimed", "30s"),
        ("FailedOver", "5s"),
        ("SafetyRoutine", "2s"),
    ]
    assert rows[0].object == "RedundantAutopilot/d1"
    assert rows[0].message == "Claimed happened"
    assert tables.event_rows(events, NOW, limit=0) == []


def test_a_repeated_event_sorts_by_its_last_occurrence() -> None:
    repeated = _event("Repeated", 500, series={"lastObservedTime": _iso(1)})
    rows = tables.event_rows([repeated, _event("FailedOver", 5)], NOW, limit=5)
    assert [r.reason for r in rows] == ["FailedOver", "Repeated"]


def _plain(renderable: Any) -> str:
    console = Console(width=200, color_system=None, record=True)
    console.print(renderable)
    return console.export_text()


def test_the_rendered_fleet_table_marks_the_active_autopilot_without_colour() -> None:
    rows = tables.fleet_rows([vehicle("d1")], [autopilot("d1", status=FAILED_OVER)], [], NOW)
    text = _plain(render.fleet_table(rows))
    assert "▸fc-b OK" in text
    assert "fc-a ERROR (heartbeat lost 3.1 s)" in text
    assert "fc-a → fc-b 12s ago" in text
    assert "VEHICLE" in text and "LAST FAILOVER" in text


def test_empty_tables_say_how_to_fill_them() -> None:
    assert "kubectl apply -f examples/vehicle-sim-px4.yaml" in _plain(render.fleet_table([]))
    assert "kubectl apply -f examples/mission.yaml" in _plain(render.missions_table([]))


def test_parameter_drift_and_the_flight_hold_show_per_vehicle() -> None:
    in_sync = {
        "type": "ParametersInSync",
        "status": "True",
        "reason": "InSync",
        "message": "2 parameter(s) hold their declared values",
        "lastTransitionTime": _iso(5),
    }
    drifted = {
        "type": "ParametersInSync",
        "status": "False",
        "reason": "Drifted",
        "message": "changed on the autopilot since the agent set it: GF_ACTION is 1, declared 3",
        "lastTransitionTime": _iso(5),
    }
    status = {
        "activeAutopilot": "fc-a",
        "autopilots": [
            {"name": "fc-a", "level": "OK", "conditions": [in_sync]},
            {"name": "fc-b", "level": "OK", "conditions": [drifted]},
        ],
    }
    hold = {
        "reason": "autopilot fc-a is armed",
        "disruptionBudget": "roost-vehicle-d1-in-flight",
        "deferred": ["mavros"],
    }
    [row] = tables.fleet_rows(
        [vehicle("d1", flightHold=hold)], [autopilot("d1", status=status)], [], NOW
    )
    assert [c.params for c in row.autopilots] == ["", "Drifted: GF_ACTION is 1, declared 3"]
    assert "fc-b OK [params Drifted: GF_ACTION is 1, declared 3]" in row.health
    assert row.flight_hold == "autopilot fc-a is armed; deferred mavros"
    console = Console(width=200, record=True)
    console.print(render.fleet_table([row]))
    shown = console.export_text()
    assert "in flight: autopilot fc-a is armed; deferred mavros" in shown
    assert "[params Drifted: GF_ACTION is 1, declared 3]" in shown


def test_the_fence_state_shows_per_autopilot() -> None:
    def fence(status: str, reason: str, message: str) -> dict[str, str]:
        return {
            "type": "FenceInSync",
            "status": status,
            "reason": reason,
            "message": message,
            "lastTransitionTime": _iso(5),
        }

    status = {
        "activeAutopilot": "fc-a",
        "autopilots": [
            {
                "name": "fc-a",
                "level": "OK",
                "conditions": [fence("True", "FenceHeld", "holds fence 0123456789ab: polygon")],
            },
            {
                "name": "fc-b",
                "level": "OK",
                "conditions": [fence("False", "UploadRefused", "uploading: MISSION_ACK result 1")],
            },
            {"name": "fc-c", "level": "OK"},
        ],
    }
    [row] = tables.fleet_rows([vehicle("d1")], [autopilot("d1", status=status)], [], NOW)
    assert [c.fence for c in row.autopilots] == [
        "held 0123456789ab",
        "UploadRefused: uploading: MISSION_ACK result 1",
        "",
    ]
    console = Console(width=250, record=True)
    console.print(render.fleet_table([row]))
    shown = console.export_text()
    assert "[fence held 0123456789ab]" in shown
    assert "[fence UploadRefused: uploading: MISSION_ACK result 1]" in shown
