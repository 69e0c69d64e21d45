"""A flight's plot document (roost_cli.dashboard.flightplot) from a real tlog written
with pymavlink's encoder and the agent's decisions: per autopilot (named from its
parameters), modes, health levels, failover and safety-routine markers, trajectory."""

from __future__ import annotations

from pathlib import Path

from roost_cli.dashboard.flightplot import MAX_POINTS, autopilot_names, plot_document
from tests.support.tlogs import write_flight

START = 1_780_000_000.0


def test_a_flight_is_plotted_per_autopilot_with_its_modes_health_and_markers(
    tmp_path: Path,
) -> None:
    write_flight(tmp_path, START, duration_s=60)
    params = {"ap-a": {"SYSID_THISMAV": 1}, "ap-b": {"SYSID_THISMAV": 2}}
    doc = plot_document(tmp_path / "hub.tlog", (tmp_path / "decisions.jsonl").read_text(), params)
    assert doc["start"] == START
    a, b = doc["autopilots"]
    assert (a["name"], b["name"]) == ("ap-a", "ap-b")
    assert max(a["alt"]) == 20.0 and a["alt"][0] == 0.0
    assert max(a["speed"]) == 0.8
    assert max(a["east"]) > 30 and a["t"][-1] > 59
    assert [m["mode"] for m in a["modes"]] == ["GUIDED"]
    assert [m["mode"] for m in b["modes"]] == ["GUIDED", "LAND"]
    assert [(m["kind"], m["t"]) for m in doc["markers"]] == [
        ("Failover", 30.0),
        ("SafetyRoutine", 31.0),
    ]
    assert {(h["autopilot"], h["level"]) for h in doc["health"]} == {
        ("ap-a", "ERROR"),
        ("ap-b", "OK"),
    }


def test_long_flights_are_thinned_and_unknown_systems_are_named_by_id(tmp_path: Path) -> None:
    write_flight(tmp_path, START, duration_s=160)
    doc = plot_document(tmp_path / "hub.tlog", "not json\n", {})
    assert [a["name"] for a in doc["autopilots"]] == ["system 1", "system 2"]
    assert all(len(a["t"]) <= MAX_POINTS for a in doc["autopilots"])
    assert doc["markers"] == [] and doc["health"] == []


def test_autopilot_names_come_from_either_firmwares_system_id_parameter() -> None:
    assert autopilot_names({"px4": {"MAV_SYS_ID": 3}, "ardu": {"SYSID_THISMAV": 1.0}, "x": {}}) == {
        3: "px4",
        1: "ardu",
    }
