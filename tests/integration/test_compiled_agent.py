"""The agent's suites, run again against the build the image ships.

The image's wheel has the agent's per-message path compiled by mypyc (``setup.py``). A
compiled module checks its annotations at run time and its classes refuse attributes
they do not declare, so a wrong annotation on the message path would drop messages in
the image while the interpreted checkout passed every test. This test builds that wheel
(``docker/build-images.sh --compiled-tree``, cached), then runs the suites that drive the
compiled modules in a pytest of their own with the compiled build first on
``PYTHONPATH``; ``tests/conftest.py`` fails that run unless each compiled module really
imports from it. Tests that put stand-ins into a compiled class are marked
``interpreted_only`` and skip there.

The compiled run keeps the interpreted run's two tiers: its tests not marked ``serial``
run in this file's ``parallel`` case, beside the other files of the parallel pass (as
they do interpreted), and its ``serial`` tests in the ``serial`` case, alone in the
serial pass (they judge real time). Each message path runs once against the compiled
build; ``SUITES`` says which cases are left to the interpreted run and why.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from roost_localcluster.binaries import REPO_ROOT
from tests.support.compiled import compiled_modules, compiled_tree, environment

FAILOVER = "tests/integration/test_agent_failover.py"
SUITES = (
    # the compiled modules' own tests
    "tests/unit/test_mavlink_codec.py",
    "tests/unit/test_agent_health.py",
    "tests/unit/test_agent_steering.py",
    "tests/integration/test_agent_steering_kernel.py",
    "tests/unit/test_agent_trust.py",
    "tests/integration/test_agent_links_sockets.py",
    "tests/integration/test_agent_udp_batch.py",  # the C extension (recvmmsg) and its fallback
    "tests/unit/test_agent_health_replay.py",
    # their callers: the agent's parts, its decisions, its routine, its outputs
    "tests/unit/test_agent_bridge.py",
    "tests/unit/test_agent_state.py",
    "tests/unit/test_agent_main.py",
    "tests/integration/test_agent_imports.py::test_standalone_agent_imports_neither_kopf_nor_heavy_clients",
    "tests/integration/test_agent_imports.py::test_the_agent_never_imports_pymavlink",
    "tests/integration/test_agent_imports.py::"
    "test_the_agent_in_cluster_mode_never_imports_the_kubernetes_package_nor_pydantic",
    "tests/integration/test_agent_imports.py::test_agent_without_metrics_does_not_import_prometheus_client",
    "tests/unit/test_agent_arbiter.py",
    "tests/integration/test_agent_decision_tick.py",
    "tests/unit/test_operator_claims.py",
    "tests/unit/test_operator_autopilots.py",
    "tests/unit/test_agent_safety.py",
    "tests/integration/test_agent_safety_timers.py",
    "tests/unit/test_agent_streams.py",
    "tests/unit/test_agent_hub_rules.py",
    "tests/integration/test_agent_hub_routing.py",
    # the hub itself is compiled: its clients, mirroring and standby judgement. Not the
    # 22 switches counted for leaks (the switch path runs in the test after a switch),
    # the setpoint circle flown mirrored and unmirrored, nor the failover under the
    # circle: the same hub paths, judged again (mirrored commands and a setpoint stream
    # across a failover run in the flight and failover tests, a standby out of step with
    # mirroring off in the drift test). Nor a taken endpoint refused at start, which no
    # message takes part in.
    "tests/integration/test_agent_hub.py::test_client_flies_the_vehicle_through_the_hub_and_the_standby_follows",
    "tests/integration/test_agent_hub.py::test_failover_keeps_the_client_connected_and_its_setpoint_stream_moves",
    "tests/integration/test_agent_hub.py::test_after_a_switch_nothing_from_the_old_active_reaches_the_client",
    "tests/integration/test_agent_hub.py::"
    "test_unmirrored_standby_drifts_out_of_step_and_a_dead_active_still_fails_over",
    "tests/integration/test_agent_hub.py::test_standby_rejecting_a_mirrored_mode_is_out_of_step",
    "tests/integration/test_agent_hub.py::test_silent_standby_is_out_of_step",
    "tests/integration/test_agent_hub.py::test_a_tcp_ground_station_gets_the_vehicle_and_commands_it",
    # a real ground-station library through the compiled hub, before and across a
    # failover; not MAVProxy, plain or signed: the same UDP client path, and signed
    # clients are test_hub_signing's below
    "tests/integration/test_hub_clients.py::test_mavsdk_flies_the_vehicle_through_the_hub",
    "tests/integration/test_hub_clients.py::"
    "test_mavsdk_offboard_stream_continues_to_the_new_autopilot_after_a_failover",
    "tests/unit/test_agent_metrics.py",
    "tests/integration/test_agent_metrics_on_links.py",
    "tests/unit/test_agent_telemetry.py",
    # the fence keeper's mission protocol inbox and sends on the compiled links: an
    # upload read back from each stack, and a breach seen in the position stream
    "tests/integration/test_agent_geofence.py::"
    "test_the_fence_reaches_every_autopilot_of_each_stack_and_the_previous_comes_back",
    "tests/integration/test_agent_geofence.py::test_a_breach_in_flight_triggers_the_configured_action",
    # the agent as a process, over real UDP, against simulated autopilots: each kind of
    # message path once (a fault read from the messages' content on each stack, command
    # answers on udp and udpout, the agent's beat on udp and a serial line, garbage in
    # the stream, streams requested from ArduPilot). Not the other fault kinds, the
    # restarts of the safety routine or the console script: the same path, and state
    # handling the compiled modules take no part in; the interpreted run covers those.
    f"{FAILOVER}::test_fault_on_active_switches_bridge_and_runs_safety_routine[sensor-gyro-px4]",
    f"{FAILOVER}::test_fault_on_active_switches_bridge_and_runs_safety_routine"
    "[state-emergency-ardupilot]",
    f"{FAILOVER}::test_a_fatal_heartbeat_and_command_answers_are_read_when_they_arrive",
    f"{FAILOVER}::test_every_autopilot_hears_the_agent_beat",
    f"{FAILOVER}::test_garbage_and_spoofed_traffic_never_cause_a_failover[px4]",
    "tests/integration/test_firmware_truth.py::test_ardupilot_streaming_only_on_request_fails_over_unaided",
    # foreign senders, signing and a relocked peer on the links (not the opening and
    # refusing of a link at start, which no message takes part in)
    "tests/integration/test_link_trust.py::test_a_hostile_sender_costs_the_autopilots_nothing_and_hears_nothing",
    "tests/integration/test_link_trust.py::test_signing_required_hears_only_well_signed_autopilots",
    "tests/integration/test_link_trust.py::test_the_link_relocks_when_the_autopilot_comes_back_on_another_port",
    # the flight recorder's taps and the autopilot log download on the links
    "tests/integration/test_agent_records_flight.py::"
    "test_a_flight_leaves_tlog_decisions_params_and_both_autopilots_logs",
    # signed hub endpoints and a key rotation (the links re-key, answer each autopilot
    # with the key it proved); not the status's list of signing endpoints nor the
    # refusal at start, which no message takes part in
    "tests/integration/test_hub_signing.py::test_a_signed_client_flies_the_vehicle_and_sees_it_signed",
    "tests/integration/test_hub_signing.py::test_the_hub_signs_what_it_sends_with_the_vehicle_key",
    "tests/integration/test_hub_signing.py::"
    "test_attacks_get_nothing_through_and_the_legitimate_client_loses_nothing",
    "tests/integration/test_hub_signing.py::"
    "test_a_tcp_client_gets_nothing_until_it_signs_and_then_only_signed_frames",
    "tests/integration/test_hub_signing.py::"
    "test_a_rotated_key_is_taken_without_a_restart_and_nothing_breaks_meanwhile",
    # the hub's fast path (_udpbatch.c) against the Python path: the same frames routed
    "tests/integration/test_hub_fast_path.py",
)


TIERS = [
    # the suites' tests that wait, beside the other files of the parallel pass
    pytest.param("not serial", id="parallel"),
    # serial: the suites' tests that judge real time, alone in the serial pass
    pytest.param("serial", id="serial", marks=pytest.mark.serial),
]


@pytest.mark.slow
@pytest.mark.timeout(1500)
@pytest.mark.parametrize("tier", TIERS)
def test_the_agent_suites_pass_against_the_compiled_build(tier: str) -> None:
    tree = compiled_tree()
    assert {
        "roost_mavlink.codec",
        "roost_agent.health",
        "roost_agent.transport",
        "roost_agent.trust",
        "roost_agent.reader",
        "roost_agent.link",
        "roost_agent.hub",
        "roost_agent._udpbatch",
    } <= set(compiled_modules(tree))
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-m", tier, *SUITES],
        cwd=REPO_ROOT,
        env={**_without_pytest_state(), **environment(tree)},
        capture_output=True,
        text=True,
        check=False,
        timeout=1500,
    )
    report = run.stdout[-6000:] + run.stderr[-2000:]
    assert run.returncode == 0, report
    assert "compiled (mypyc): " in run.stdout, report  # the header tests/conftest.py writes


def _without_pytest_state() -> dict[str, str]:
    """This process's environment without what pytest set for its own run."""
    return {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
