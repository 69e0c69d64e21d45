"""Preflight checks of one vehicle for a Mission (roost_operator.missions.preflight).

Every input is an API model built as the API server would return it
(:mod:`tests.support.missions`); the functions under test are pure: no mocks.
"""

from __future__ import annotations

from roost_api.mission import (
    Preflight,
)
from roost_operator.missions.preflight import preflight_failures
from tests.support.missions import (
    autopilots,
    vehicle,
)


def test_preflight_checks_each_writer_and_counts_an_absent_condition_as_failing() -> None:
    checks = Preflight()
    v = vehicle("a", agent=None)
    reasons = [f.reason for f in preflight_failures(v, autopilots("a"), checks)]
    assert reasons == ["AgentNotConnected"]
    assert preflight_failures(v, autopilots("a"), Preflight(require_agent_connected=False)) == []
    unhealthy = autopilots("a", healthy=False, redundant=False)
    reasons = [f.reason for f in preflight_failures(vehicle("a"), unhealthy, checks)]
    assert reasons == ["ActiveAutopilotUnhealthy", "NotRedundant"]
    relaxed = Preflight(require_redundancy=False)
    assert [f.reason for f in preflight_failures(vehicle("a"), unhealthy, relaxed)] == [
        "ActiveAutopilotUnhealthy"
    ]
    no_autopilots = [f.reason for f in preflight_failures(vehicle("a", ready=False), None, checks)]
    assert no_autopilots == ["VehicleNotReady", "ActiveAutopilotUnhealthy", "NotRedundant"]
    nothing_required = Preflight(
        require_agent_connected=False, require_active_healthy=False, require_redundancy=False
    )
    assert preflight_failures(vehicle("a", agent=None), None, nothing_required) == []
    assert [f.reason for f in preflight_failures(None, None, checks)] == ["VehicleMissing"]
