"""The agent's durable state file (atomic, a corrupt file moved aside) and what the agent
restores from it."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path

from roost_agent.spec_changes import restore_state
from roost_agent.state import PersistedState, StateFile
from roost_api.autopilot import CommandResult
from tests.support.agentspec import SPEC

NOW = datetime(2026, 5, 1, 12, 0, tzinfo=UTC)


def test_state_file_round_trip_is_atomic(tmp_path: Path) -> None:
    store = StateFile(tmp_path / "agent-state.json")
    assert store.load() is None
    result = CommandResult(id="c1", result="Executed", message="ok", time=NOW)
    state = saved(latched=True, failedFrom=["fc1"], failoverCount=2, commands=[result.to_api()])
    store.save(state)
    assert store.load() == state
    assert [p.name for p in tmp_path.iterdir()] == ["agent-state.json"]  # no temp file left
    doc = json.loads((tmp_path / "agent-state.json").read_text())
    assert doc["active"] == "fc2" and doc["failedFrom"] == ["fc1"]


def test_corrupt_state_file_is_moved_aside_not_trusted(tmp_path: Path) -> None:
    path = tmp_path / "agent-state.json"
    path.write_text('{"active": "fc2", "spec": ')
    assert StateFile(path).load() is None
    assert (tmp_path / "agent-state.json.corrupt").exists() and not path.exists()


def saved(active: str = "fc2", **fields: object) -> PersistedState:
    return PersistedState.from_api(
        {"spec": SPEC.to_api(), "active": active, "savedAt": NOW, **fields}
    )


def test_restore_keeps_the_saved_active_autopilot_and_latch() -> None:
    state = restore_state(SPEC, saved(latched=True, failedFrom=["fc1", "gone"], failoverCount=1))
    assert (state.active, state.latched, state.failover_count) == ("fc2", True, 1)
    assert state.failed_from == {"fc1"}  # names no longer in the spec are dropped
    assert state.in_flight is None and state.failing_since is None  # rebuilt from telemetry


def test_restore_falls_back_to_the_primary() -> None:
    assert restore_state(SPEC, None).active == "fc1"
    assert restore_state(SPEC, saved(active="removed")).active == "fc1"
