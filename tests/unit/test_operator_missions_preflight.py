"""Preflight checks of one vehicle for a Mission (roost_operator.missions.preflight).

Every input is an API model built as the API server would return it
(:mod:`tests.support.missions`); the functions under test are pure: no mocks.
"""

from __future__ import annotations

from roost_api.meta import Condition
from roost_api.mission import (
    Preflight,
)
from roost_operator.missions.preflight import preflight_failures
from tests.support.missions import (
    autopilots,
    cond,
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


def test_a_firmware_requirement_is_checked_and_the_failure_names_the_autopilot() -> None:
    checks = Preflight()
    required = {"px4Minimum": "1.15.0"}
    below = cond(
        "FirmwareAcceptable",
        "False",
        "FirmwareBelowMinimum",
        message="fc2 runs px4 1.14.3, below the required 1.15.0",
    )
    cases: list[tuple[tuple[dict[str, str], Condition | None] | None, list[str]]] = [
        (None, []),  # nothing required: not checked
        ((required, cond("FirmwareAcceptable", "True", "FirmwareAcceptable")), []),
        ((required, None), ["FirmwareUnacceptable"]),  # the agent has not judged yet
        ((required, below), ["FirmwareUnacceptable"]),
    ]
    for firmware, expected in cases:
        failures = preflight_failures(vehicle("a"), autopilots("a", firmware=firmware), checks)
        assert [f.reason for f in failures] == expected, firmware
    [failure] = preflight_failures(
        vehicle("a"), autopilots("a", firmware=(required, below)), checks
    )
    assert failure.message == (
        "firmware requirement not met: False (FirmwareBelowMinimum: fc2 runs px4 1.14.3, "
        "below the required 1.15.0)"
    )
