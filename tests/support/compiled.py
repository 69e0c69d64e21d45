"""Roost's compiled build, as the images ship it, run from this checkout.

The image build compiles the agent's per-message path with mypyc (``setup.py``,
``ROOST_COMPILE=1``); ``docker/build-images.sh --compiled-tree`` installs the packages of
that same wheel that hold compiled modules (``roost_agent``, ``roost_mavlink``) into a
cached directory of its own. Putting the directory first on ``PYTHONPATH`` makes a
Python process (an agent started by a test or a benchmark, or a whole pytest run) import
those packages from it, compiled modules included, and everything else from the
checkout.

A run that means to test or measure the compiled build says so with
``ROOST_COMPILED_TREE`` (the directory); :func:`check_compiled_imports` then fails it
when any module the tree holds compiled was imported from elsewhere, so a stale path can
never pass the pure-Python modules off as the compiled ones.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Mapping
from pathlib import Path

from tests.support.images import run_build_script

TREE_VARIABLE = "ROOST_COMPILED_TREE"

# The suites tests/integration/test_compiled_agent.py runs against the compiled build: the
# tests that drive the compiled modules, each message path once. In `make test` the
# integration passes leave these integration tests to that run (--leave-to-compiled,
# tests/conftest.py), so each runs once, against what the images ship.
FAILOVER = "tests/integration/test_agent_failover.py"
SUITES: tuple[str, ...] = (
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


def left_to_compiled(nodeid: str) -> bool:
    """Whether ``nodeid`` is an integration test the compiled run runs: its file, its
    function (every parameter) or the test itself is listed in :data:`SUITES`."""
    for entry in SUITES:
        if not entry.startswith("tests/integration/"):
            continue
        if nodeid == entry or nodeid.startswith((entry + "::", entry + "[")):
            return True
    return False


def compiled_tree() -> Path:
    """Build Roost's compiled wheel into the cache unless it is current; its directory."""
    return run_build_script("--compiled-tree", timeout_s=900)


def compiled_modules(tree: Path) -> list[str]:
    """Dotted names of the Roost modules ``tree`` holds as extension modules."""
    names = []
    for library in sorted(tree.glob("roost_*/**/*.so")):
        relative = library.relative_to(tree)
        stem = relative.name.split(".", 1)[0]
        names.append(".".join([*relative.parent.parts, stem]))
    return names


def environment(tree: Path) -> Mapping[str, str]:
    """Variables that make a child Python process run Roost from ``tree``."""
    path = os.environ.get("PYTHONPATH", "")
    return {
        "PYTHONPATH": f"{tree}{os.pathsep}{path}" if path else str(tree),
        TREE_VARIABLE: str(tree),
    }


def check_compiled_imports() -> list[str]:
    """With ``ROOST_COMPILED_TREE`` set, the compiled modules as imported; else nothing.

    Raises ``RuntimeError`` when the tree holds no compiled module, or when one of them
    imports from anywhere but the tree as its extension module.
    """
    root = os.environ.get(TREE_VARIABLE)
    if not root:
        return []
    tree = Path(root).resolve()
    names = compiled_modules(tree)
    if not names:
        raise RuntimeError(f"{tree} holds no compiled Roost module")
    for name in names:
        origin = Path(importlib.import_module(name).__file__ or "").resolve()
        if origin.suffix != ".so" or not origin.is_relative_to(tree):
            raise RuntimeError(f"{name} was imported from {origin}, not compiled from {tree}")
    return names
