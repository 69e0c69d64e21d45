"""`roost sandbox up` end to end, as a user runs it, then `roost sandbox down`.

Everything is real: the `roost` CLI as a subprocess, the control plane it starts, the
operator, one agent per vehicle, the simulated autopilots over UDP, kubectl. The test
plays the user in a second terminal: it waits for the Mission, breaks the active
autopilot of one vehicle with `roost fault`, reads the failover back through kubectl and
`roost status`, stops the sandbox with `roost sandbox down`, and checks that not one of
the processes the sandbox started is left.
"""

from __future__ import annotations

import json
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from roost_cli.sandbox import state as sandbox_state
from tests.support.sandbox import (
    BIN,
    RunningSandbox,
    await_running,
    await_step,
    recorded_processes,
    running_sandbox,
    still_running,
)
from tests.support.syncrun import SHORT_TRAJECTORIES

# serial: the sandbox's simulated autopilots and agents run in real time against a 200 ms
# silence limit; on two busy cores a stall of both autopilots of a vehicle lands it (the
# agent rightly finds no healthy standby), so `make e2e` runs these after the rest,
# beside at most one other serial file (Makefile, E2E_SERIAL).
pytestmark = [
    pytest.mark.cluster,
    pytest.mark.slow,
    pytest.mark.serial,
    pytest.mark.timeout(600),
]

VEHICLES = 2
FAULT_VEHICLE = "drone-1"
STEP_TIMEOUT_S = 90.0


def mission_vehicle(sandbox: RunningSandbox, mission: str, vehicle: str) -> dict[str, Any]:
    """``status.vehicles[]`` entry of ``vehicle`` in Mission ``default/<mission>``."""
    found = sandbox.get("mission", mission, "default")
    entry: dict[str, Any] = next(v for v in found["status"]["vehicles"] if v["name"] == vehicle)
    return entry


@pytest.fixture
def sandbox(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[RunningSandbox]:
    """``roost sandbox up`` headless without the scripted fault; an indirect parameter adds
    arguments (``--mission sync-paths``)."""
    extra: list[str] = list(getattr(request, "param", ()))
    args = ["--vehicles", str(VEHICLES), "--no-live", "--no-fault", "--dashboard-port", "0"]
    with running_sandbox(tmp_path, [*args, *extra]) as running:
        yield running


def test_sandbox_flies_a_mission_fails_over_and_leaves_nothing_behind(
    sandbox: RunningSandbox,
) -> None:
    recorded = await_running(sandbox)
    assert [v.name for v in recorded.vehicles] == ["drone-1", "drone-2"]
    assert "export KUBECONFIG=" in sandbox.log()
    assert recorded.dashboard is not None and recorded.dashboard in sandbox.log()
    assert all(v.telemetry for v in recorded.vehicles)

    def mission_phase() -> str | None:
        phase: str | None = (
            sandbox.get("mission", "survey", "default").get("status", {}).get("phase")
        )
        return phase

    await_step(
        "Mission survey to run", lambda: mission_phase() == "Running", sandbox, STEP_TIMEOUT_S
    )

    def active_of(vehicle: str) -> str | None:
        status = sandbox.get("redundantautopilot", vehicle).get("status", {})
        active: str | None = status.get("activeAutopilot")
        return active

    await_step("the agent to report", lambda: active_of(FAULT_VEHICLE) == "px4-a", sandbox, 60)
    fault = sandbox.roost("fault", FAULT_VEHICLE, "px4-a", "silence")
    assert "faults now silence" in fault.stdout

    await_step("the failover", lambda: active_of(FAULT_VEHICLE) == "px4-b", sandbox, STEP_TIMEOUT_S)
    ra = sandbox.get("redundantautopilot", FAULT_VEHICLE)
    last = ra["status"]["lastFailover"]
    assert (last["from"], last["to"], last["trigger"]) == ("px4-a", "px4-b", "Automatic")
    assert last["latencyMs"] >= 0
    conditions = {c["type"]: c["status"] for c in ra["status"]["conditions"]}
    assert conditions["FailedOver"] == "True"
    assert active_of("drone-2") == "apm-a", "the other vehicle is untouched"

    def failover_event() -> bool:
        events = json.loads(
            sandbox.kubectl(
                "get",
                "events",
                "-A",
                "--field-selector",
                f"involvedObject.name={FAULT_VEHICLE}",
                "-o",
                "json",
            )
        )["items"]
        return any("px4-b" in e.get("message", "") for e in events)

    await_step("an Event about the failover", failover_event, sandbox, 30)

    def vehicle_in_mission(name: str) -> dict[str, Any]:
        return mission_vehicle(sandbox, "survey", name)

    # The Mission's onFailover is AbortVehicle: drone-1 lands and leaves, drone-2 flies on.
    await_step(
        "the mission to abort drone-1",
        lambda: vehicle_in_mission(FAULT_VEHICLE)["phase"] in ("Aborting", "Aborted"),
        sandbox,
        STEP_TIMEOUT_S,
    )
    assert mission_phase() == "Running"
    assert vehicle_in_mission("drone-2")["phase"] == "Running"

    table = sandbox.roost("status").stdout
    row = next(line for line in table.splitlines() if FAULT_VEHICLE in line)
    assert "px4-a → px4-b" in row
    assert "▸px4-b" in row
    rows = {r["vehicle"]: r for r in json.loads(sandbox.roost("status", "-o", "json").stdout)}
    assert rows[FAULT_VEHICLE]["active"] == "px4-b"
    assert rows["drone-2"]["last_failover"] == "-"
    assert rows["drone-2"]["mission"] == "default/survey Running"
    missions = json.loads(sandbox.roost("missions", "-o", "json").stdout)
    assert [(m["name"], m["phase"], m["degraded"]) for m in missions] == [
        ("default/survey", "Running", "True")
    ]

    # E-stop through the CLI, the API and the agent to the simulated autopilot.
    sims_of_drone_2 = sandbox.directory / "sims" / "drone-2"
    estop = sandbox.roost("estop", "--vehicle", "drone-2", "--yes")
    assert "Executed" in estop.stdout
    sim = json.loads(
        subprocess.run(
            [str(BIN / "roost-sim"), "--state-dir", str(sims_of_drone_2), "status", "apm-a"],
            capture_output=True,
            text=True,
            timeout=30,
            check=True,
        ).stdout
    )
    assert sim["state"]["armed"] is False

    aborted = sandbox.roost("abort", "survey")
    assert "abort requested" in aborted.stdout
    assert sandbox.get("mission", "survey", "default")["spec"]["abort"] is True
    await_step(
        "the mission to end",
        lambda: mission_phase() in ("Aborting", "Aborted", "Failed"),
        sandbox,
        STEP_TIMEOUT_S,
    )

    identities = recorded_processes(sandbox.directory)
    assert len(identities) >= 1 + VEHICLES * 2 + 1 + 5  # up, sims + agents, operator, plane
    down = sandbox.roost("sandbox", "down")
    assert "sandbox stopped" in down.stdout
    sandbox.process.wait(timeout=60)
    assert still_running(identities) == []
    assert sandbox_state.load(sandbox.directory) is None


@pytest.mark.parametrize(
    "sandbox",
    [("--mission", "sync-paths", "--trajectories", str(SHORT_TRAJECTORIES))],
    indirect=True,
)
def test_the_sync_paths_mission_flies_through_the_hubs_and_goes_on_without_a_failed_vehicle(
    sandbox: RunningSandbox,
) -> None:
    """The reference mission's programs fly the sandbox through the agents' MAVLink hubs.
    drone-2's primary goes silent on the first leg: its agent fails over (the follower's
    connection to the hub is untouched), the Mission's ``onFailover: AbortVehicle`` takes
    it out, the sandbox stops its follower as the kubelet would stop its pod, and drone-1
    flies every task without waiting for drone-2's delay reports. The followers fly the
    tests' shorter trajectories (6 s legs instead of the example's 20 s: the test takes
    about 45 s instead of 105)."""
    recorded = await_running(sandbox)
    hubs = {v.name: v.hub for v in recorded.vehicles}
    assert all(hub is not None and hub.startswith("127.0.0.1:") for hub in hubs.values())
    for name, hub in hubs.items():
        assert sandbox.get("redundantautopilot", name)["spec"]["hub"]["udp"] == hub
    monitor_log = sandbox.directory / "logs" / "sync-monitor.log"

    def legs_started() -> bool:
        return monitor_log.is_file() and "starting " in monitor_log.read_text()

    await_step("the monitor to start the legs", legs_started, sandbox, STEP_TIMEOUT_S)
    time.sleep(3.0)  # 1 s into leg 1 (6 s): drone-2 is silenced before it reaches task 1
    fault = sandbox.roost("fault", "drone-2", "apm-a", "silence")
    assert "faults now silence" in fault.stdout

    await_step(
        "the mission to take drone-2 out",
        lambda: (
            mission_vehicle(sandbox, "sync-paths", "drone-2")["phase"] in ("Aborting", "Aborted")
        ),
        sandbox,
        STEP_TIMEOUT_S,
    )
    await_step(
        "the sandbox to stop drone-2's follower",
        lambda: "drone-2 left mission default/sync-paths" in sandbox.log(),
        sandbox,
        30,
    )
    ra = sandbox.get("redundantautopilot", "drone-2")
    assert ra["status"]["activeAutopilot"] == "apm-b"
    results_file = sandbox.directory / "mission-results" / "results.json"
    await_step("drone-1 to finish the mission", results_file.is_file, sandbox, 180)
    results = json.loads(results_file.read_text())
    assert results["drone-2"]["type"] == "leave"
    assert results["drone-1"]["type"] == "done"
    records = results["drone-1"]["records"]
    assert [r["task"] for r in records] == [1, 2, 3, 4]
    assert all(r["wait_s"] < 1.0 for r in records[1:]), records  # nobody to wait for
    assert mission_vehicle(sandbox, "sync-paths", "drone-1")["phase"] in ("Running", "Succeeded")
    follower_log = (sandbox.directory / "logs" / "sync-follower-drone-1.log").read_text()
    assert f"flying through udpout:{hubs['drone-1']}" in follower_log
