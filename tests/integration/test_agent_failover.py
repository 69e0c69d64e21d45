"""The node agent against simulated autopilots over real UDP sockets and a serial pty.

Each test flies two or three simulated autopilots (roost_sim: real MAVLink 2 bytes, PX4 or
ArduPilot conventions), runs the real agent on them with a simulated bridge (the only
stand-in: no GPIO hardware here), injects a fault and checks what a person would check:
the bridge switched to the healthy autopilot, the safety routine ran on it as seen by the
simulator (hold mode entered, landing only after the hold time, touchdown), the failed
autopilot got no commands, and garbage or spoofed traffic changed nothing.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest
import yaml

from roost_agent import Agent, reader
from roost_agent.agent import STEERED_TICK_S
from roost_agent.bridge import SimulatedBridge
from roost_agent.state import STATE_FILE_NAME, StateFile
from roost_api.autopilot import (
    AutopilotCommand,
    FinalAction,
    Thresholds,
)
from roost_api.meta import HealthLevel, Stack
from roost_mavlink import (
    AGENT_COMPONENT_ID,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_NAV_LAND,
    ModeIntent,
    custom_mode,
    intent_mode,
    set_mode_params,
)
from roost_mavlink.modes import custom_mode_from_set_mode
from roost_sim import (
    FaultKind,
    SimConfig,
    SimulatedAutopilot,
    message_id,
    start_vehicle_sims,
    stop_sims,
)
from tests.support.agent import AgentProcess
from tests.support.flight import CLEAR_S, HOLD_S, POLL_S, Flight, make_spec, take_off
from tests.support.waiting import wait_until

# serial: silence thresholds and failovers judged in real time
pytestmark = [pytest.mark.slow, pytest.mark.serial]

# Sub-second start-up; ArduPilot streams only what the agent requests, as the firmware.
SIM_CONFIG = SimConfig.fast()


def all_ok(agent: Agent, names: list[str]) -> bool:
    assessments = agent.assessments()
    return all(n in assessments and assessments[n].level == HealthLevel.OK for n in names)


@contextlib.contextmanager
def flying(
    stacks: list[str],
    tmp_path: Path,
    *,
    transport: str = "udp",
    final_action: FinalAction = FinalAction.LAND,
    thresholds: Thresholds | None = None,
    steered_tick_s: float = STEERED_TICK_S,
) -> Iterator[Flight]:
    """Sims started and airborne, an agent watching them, every standby ready.

    ``transport``: ``udp`` (the agent listens), ``pty`` (serial) or ``udpout`` (the agent
    sends to each sim's own port; the sim streams back to whoever sent it a packet).
    """
    if transport == "udpout":
        sims = [
            SimulatedAutopilot.udp(stack, i + 1, name=f"fc{i + 1}", config=SIM_CONFIG).start()
            for i, stack in enumerate(stacks)
        ]
    else:
        sims = start_vehicle_sims(stacks, transport=transport, config=SIM_CONFIG)
    agent: Agent | None = None
    try:
        spec = make_spec(sims, final_action, thresholds)
        bridge = SimulatedBridge(range(len(sims)))
        state_path = tmp_path / STATE_FILE_NAME
        agent = Agent(spec, bridge, state_file=StateFile(state_path), steered_tick_s=steered_tick_s)
        agent.start()
        take_off(sims)
        names = [s.name for s in sims]
        wait_until("every autopilot OK", lambda: all_ok(agent, names), 10, POLL_S)
        # Not a wait for a condition: T_off is a required duration (a standby becomes a
        # failover target only after CLEAR_S without a failure), and nothing may fail in
        # it. A warning may come and go (a message late while the sims and the agent share
        # a loaded machine): it is no failure and does not restart T_off
        # (arbiter._ok_since), so the flight starts once every autopilot is OK again.
        clear_until = time.monotonic() + CLEAR_S + 0.2
        while time.monotonic() < clear_until:
            failing = {
                name: a
                for name, a in agent.assessments().items()
                if a.level.rank >= HealthLevel.ERROR.rank
            }
            assert not failing, failing
            time.sleep(POLL_S)
        wait_until("every autopilot OK after T_off", lambda: all_ok(agent, names), 10, POLL_S)
        yield Flight(sims, agent, bridge, spec, state_path)
    finally:
        if agent is not None:
            agent.stop()
        stop_sims(sims)


def assert_held_then_landed(flight: Flight, name: str, since: float) -> None:
    """The simulator saw hold requested and entered, then land after the hold time, then
    touchdown; all commanded by the agent."""
    sim = flight.sim(name)
    stack = Stack(sim.stack)
    hold = custom_mode(stack, intent_mode(stack, ModeIntent.HOLD))
    land = custom_mode(stack, intent_mode(stack, ModeIntent.LAND))
    sim.wait_until(lambda s: s.landed_state == "OnGround", timeout=20)
    sent = flight.agent_commands(name, since)
    holds = [
        c
        for c in sent
        if c.command == MAV_CMD_DO_SET_MODE
        and custom_mode_from_set_mode(stack, *c.params[:3]) == hold
        and c.result == 0
    ]
    lands = [c for c in sent if c.command == MAV_CMD_NAV_LAND and c.result == 0]
    assert holds and lands, [(c.name, c.result) for c in sent]
    assert lands[0].at - holds[0].at >= HOLD_S
    modes = sim.mode_history
    holding = [m.mode for m in modes if m.at <= holds[0].at + HOLD_S / 2][-1]
    assert custom_mode(stack, holding) == hold, modes  # held (PX4 may already have been)
    assert custom_mode(stack, modes[-1].mode) == land, modes  # then landed
    assert modes[-1].at - holds[0].at >= HOLD_S

    def routine_outcome() -> str | None:
        record = flight.agent.status().last_failover
        return record.safety_routine if record else None

    wait_until("safety routine reported Landed", lambda: routine_outcome() == "Landed", 5, POLL_S)


# Each fault must be reported by its own detector: a rebooting ArduPilot streams nothing
# (requests do not survive a reboot) for longer than the default 200 ms silence, which
# would then name the failover first. Silence here takes 500 ms (fixed: floor = ceiling).
DETECTORS = Thresholds(
    message_warn_ms=200, message_error_ms=500, message_error_min_ms=500, confirm_ms=100
)
FAULTS = [
    (FaultKind.SILENCE, None, "silent", "silence"),
    (FaultKind.FREEZE, None, "frozen", "freeze"),
    (FaultKind.SENSOR, "gyro", "gyro unhealthy", "sensor-gyro"),
    (FaultKind.STATE, "EMERGENCY", "MAV_STATE EMERGENCY", "state-emergency"),
    (FaultKind.REBOOT, 0.0, "rebooted", "reboot"),
]
# Every fault on each stack, but for two pairs whose other stack flies the same fault on
# the same message elsewhere in this file: a gyro failure on ArduPilot (the three-autopilot
# and the udpout tests), MAV_STATE EMERGENCY on PX4 (the fatal-heartbeat test over udp
# and udpout, and both-bad). Each stack's safety routine runs in every other case.
ELSEWHERE = {("sensor-gyro", "ardupilot"), ("state-emergency", "px4")}
FAULT_CASES = [
    pytest.param(fault, value, reason, stack, id=f"{name}-{stack}")
    for fault, value, reason, name in FAULTS
    for stack in ("px4", "ardupilot")
    if (name, stack) not in ELSEWHERE
]


@pytest.mark.parametrize(("fault", "value", "reason", "stack"), FAULT_CASES)
def test_fault_on_active_switches_bridge_and_runs_safety_routine(
    tmp_path: Path, stack: str, fault: FaultKind, value: Any, reason: str
) -> None:
    with flying([stack, stack], tmp_path, thresholds=DETECTORS) as flight:
        injected = time.monotonic()
        flight.sim("fc1").inject(fault, value)
        (event,) = wait_until("a failover", flight.agent.failovers, 10, POLL_S)
        record = event.record
        assert (record.from_autopilot, record.to_autopilot, record.trigger) == (
            "fc1",
            "fc2",
            "Automatic",
        )
        assert reason in record.reason
        assert record.latency_ms >= 0 and event.switched_at >= injected
        assert flight.bridge.selected == 1
        assert [s.channel for s in flight.bridge.history] == [0, 1]
        assert flight.agent.active == "fc2" and flight.agent.latched
        assert_held_then_landed(flight, "fc2", injected)
        assert flight.agent_commands("fc1", injected) == []
        assert len(flight.agent.failovers()) == 1


# Far longer than the test waits: with no urgent socket the reader would not wake for
# the fatal heartbeat, nor for the answers to the safety routine's commands, in that time.
RARE_READ_S = 60.0


@pytest.mark.parametrize("transport", ["udp", "udpout"])
def test_a_fatal_heartbeat_and_command_answers_are_read_when_they_arrive(
    tmp_path: Path, transport: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The kernel steers heartbeats and COMMAND_ACKs to the urgent socket
    (roost_agent.steering). With the bulk read interval at a minute, a heartbeat claiming
    EMERGENCY still wakes the reader, the claim is settled by the frames after it (read
    soon after, as a claim waits) and the switch follows; the safety routine's first
    command is answered within its 0.4 s wait, so it is sent once, not retried. (The
    reader's longest sleep is raised to the same minute: nothing else wakes it.)"""
    monkeypatch.setattr(reader, "READ_WAIT_S", RARE_READ_S)
    with flying(
        ["px4", "px4"], tmp_path, transport=transport, steered_tick_s=RARE_READ_S
    ) as flight:
        assert flight.agent.read_interval_s == RARE_READ_S  # every link is steered
        injected = time.monotonic()
        flight.sim("fc1").inject(FaultKind.STATE, "EMERGENCY")
        (event,) = wait_until("a failover", flight.agent.failovers, 10, POLL_S)
        assert "MAV_STATE EMERGENCY" in event.record.reason
        assert event.switched_at >= injected
        assert flight.bridge.selected == 1
        first = wait_until(
            "the safety routine's first command",
            lambda: flight.agent_commands("fc2", injected)[:1],
            10,
            POLL_S,
        )[0]
        time.sleep(1.0)  # past the routine's 0.4 s answer wait and its retry gap
        again = [
            c
            for c in flight.agent_commands("fc2", injected)
            if (c.command, c.params) == (first.command, first.params)
        ]
        assert (first.result, len(again)) == (0, 1), again


# A heartbeat pause this long misses two or three heartbeats (a gap of 2.8-3.8 s, with the
# phase of the last one): past the default warn, short of the default error.
HEARTBEAT_PAUSE_S = 2.8


def test_default_heartbeat_thresholds_ride_out_lost_heartbeats_and_catch_a_dead_one(
    tmp_path: Path,
) -> None:
    """Telemetry keeps streaming while the active's HEARTBEAT pauses: a few missed in a
    row (what a lossy link does) are a warning and nothing moves; heartbeats gone for
    good fail over on the heartbeat age, once the default error age is reached."""
    defaults = Thresholds()
    heartbeat = message_id("HEARTBEAT")
    with flying(["px4", "px4"], tmp_path) as flight:
        fc1 = flight.sim("fc1")
        levels: list[HealthLevel] = []
        paused = time.monotonic()
        fc1.set_rate(heartbeat, 0.0)
        while time.monotonic() - paused < HEARTBEAT_PAUSE_S:
            levels.append(flight.agent.assessments()["fc1"].level)
            time.sleep(POLL_S)
        fc1.set_rate(heartbeat, 1.0)
        wait_until("fc1 OK again", lambda: all_ok(flight.agent, ["fc1"]), 5, POLL_S)
        assert HealthLevel.WARN in levels and HealthLevel.ERROR not in levels, levels
        assert flight.agent.failovers() == [] and flight.bridge.selected == 0

        stopped = time.monotonic()
        fc1.set_rate(heartbeat, 0.0)
        (event,) = wait_until("a failover", flight.agent.failovers, 10, POLL_S)
        assert "heartbeat lost" in event.record.reason
        assert (event.record.from_autopilot, event.record.to_autopilot) == ("fc1", "fc2")
        # the last heartbeat came at most a period before the stop
        assert event.switched_at - stopped >= defaults.heartbeat_error_ms / 1000 - 1.0
        assert flight.bridge.selected == 1


def test_three_autopilots_fail_over_in_turn_and_never_back(tmp_path: Path) -> None:
    with flying(["px4", "ardupilot", "px4"], tmp_path, final_action=FinalAction.HOLD) as flight:
        flight.sim("fc1").inject(FaultKind.SILENCE)
        wait_until("first failover", lambda: len(flight.agent.failovers()) == 1, 10, POLL_S)
        flight.sim("fc1").clear()  # fc1 recovers, but it was left this flight
        wait_until("fc1 OK again", lambda: all_ok(flight.agent, ["fc1"]), 10, POLL_S)
        time.sleep(CLEAR_S + 0.5)  # its T_off passes: it would now be a target, were it not left
        flight.sim("fc2").inject(FaultKind.SENSOR, "gyro")
        wait_until("second failover", lambda: len(flight.agent.failovers()) == 2, 10, POLL_S)
        time.sleep(1.0)  # nothing happens for 1 s: no third switch, no return to fc1
        moves = [(e.record.from_autopilot, e.record.to_autopilot) for e in flight.agent.failovers()]
        assert moves == [("fc1", "fc2"), ("fc2", "fc3")]
        assert [s.channel for s in flight.bridge.history] == [0, 1, 2]
        assert flight.agent.status().active_autopilot == "fc3"


def test_both_bad_keeps_the_active_and_lands_it(tmp_path: Path) -> None:
    with flying(["px4", "px4"], tmp_path) as flight:
        flight.sim("fc2").inject(FaultKind.SENSOR, "gyro")
        wait_until("fc2 failing", lambda: flight.agent.assessments()["fc2"].failing, 5, POLL_S)
        started = time.monotonic()
        flight.sim("fc1").inject(FaultKind.STATE, "EMERGENCY")
        flight.sim("fc1").wait_until(lambda s: s.landed_state == "OnGround", timeout=20)
        assert flight.agent.failovers() == []
        assert [s.channel for s in flight.bridge.history] == [0]
        lands = [c for c in flight.agent_commands("fc1", started) if c.command == MAV_CMD_NAV_LAND]
        assert len(lands) == 1
        assert flight.agent_commands("fc2", started) == []


@pytest.mark.parametrize("stack", ["px4", "ardupilot"])
def test_garbage_and_spoofed_traffic_never_cause_a_failover(tmp_path: Path, stack: str) -> None:
    with flying([stack, stack], tmp_path) as flight:
        for sim in flight.sims:
            sim.inject(FaultKind.GARBAGE, 8000)
            sim.inject(FaultKind.SPOOF)

        def hostile_traffic_seen() -> bool:
            links = flight.agent.links.values()
            return all(link.counters.other > 0 and link.counters.bad > 0 for link in links)

        wait_until("garbage and spoofed frames at every link", hostile_traffic_seen, 10, POLL_S)
        time.sleep(4.0)  # nothing happens for 4 s under that traffic: no failover
        assert flight.agent.failovers() == []
        assert [s.channel for s in flight.bridge.history] == [0]
        for name, link in flight.agent.links.items():
            assert link.counters.other > 0, name  # spoofed sysid and the gimbal were seen
            assert link.counters.bad > 0, name  # and garbage was parsed and dropped
            assert not flight.agent.assessments()[name].failing
        for sim in flight.sims:
            sim.clear()
        wait_until("both OK", lambda: all_ok(flight.agent, ["fc1", "fc2"]), 3, POLL_S)


@pytest.mark.parametrize("transport", ["udp", "pty"])
def test_every_autopilot_hears_the_agent_beat(tmp_path: Path, transport: str) -> None:
    """The agent's heartbeat, which an autopilot's companion-computer failsafe watches,
    reaches every link once a second, over UDP and over serial."""
    with flying(["px4", "ardupilot"], tmp_path, transport=transport) as flight:
        sysid = {a.name: a.sysid for a in flight.spec.autopilots}

        def beats() -> dict[str, int]:
            return {
                sim.name: sim.heartbeats_heard.get((sysid[sim.name], AGENT_COMPONENT_ID), 0)
                for sim in flight.sims
            }

        before = beats()
        wait_until(
            "three more heartbeats on every link",
            lambda: all(beats()[name] >= count + 3 for name, count in before.items()),
            10,
            POLL_S,
        )


def test_serial_link_over_a_pseudo_terminal(tmp_path: Path) -> None:
    with flying(["px4", "ardupilot"], tmp_path, transport="pty") as flight:
        assert all(s.connection.startswith("serial://") for s in flight.spec.autopilots)
        injected = time.monotonic()
        flight.sim("fc1").inject(FaultKind.SILENCE)
        wait_until("a failover over serial", flight.agent.failovers, 10, POLL_S)
        assert flight.bridge.selected == 1
        assert_held_then_landed(flight, "fc2", injected)


def test_udpout_link_where_the_agent_sends_first(tmp_path: Path) -> None:
    with flying(["ardupilot", "px4"], tmp_path, transport="udpout") as flight:
        assert all(s.connection.startswith("udpout://") for s in flight.spec.autopilots)
        flight.sim("fc1").inject(FaultKind.SENSOR, "gyro")
        (event,) = wait_until("a failover over udpout", flight.agent.failovers, 10, POLL_S)
        assert event.record.to_autopilot == "fc2" and flight.bridge.selected == 1


def _gcs_set_mode(sim: SimulatedAutopilot, mode: str) -> None:
    """A pilot/ground station switches ``sim`` to ``mode`` over its own UDP port."""
    from pymavlink import mavutil  # noqa: PLC0415 - test-only client

    host, port = sim.link.local_address  # type: ignore[attr-defined]
    gcs = mavutil.mavlink_connection(
        f"udpout:{host}:{port}", source_system=250, source_component=190
    )
    try:
        stack = Stack(sim.stack)
        gcs.mav.command_long_send(
            sim.sysid, 1, MAV_CMD_DO_SET_MODE, 0, *set_mode_params(stack, mode)
        )
        sim.wait_until(lambda s: s.mode == mode, timeout=5)
    finally:
        gcs.close()


def test_pilot_in_manual_mode_gets_the_switch_but_no_safety_routine(tmp_path: Path) -> None:
    with flying(["px4", "px4"], tmp_path) as flight:
        for sim in flight.sims:
            _gcs_set_mode(sim, "POSCTL")
        wait_until(
            "the agent to see both in POSCTL",
            lambda: all(a.mode == "POSCTL" for a in flight.agent.status().autopilots),
            5,
            POLL_S,
        )
        injected = time.monotonic()
        flight.sim("fc1").inject(FaultKind.SILENCE)
        (event,) = wait_until("a failover", flight.agent.failovers, 10, POLL_S)
        assert event.record.safety_routine == "Skipped: pilot in manual mode"
        assert flight.bridge.selected == 1
        time.sleep(HOLD_S + 1.0)  # nothing happens for longer than a hold: no routine
        assert flight.agent_commands("fc2", injected) == []
        assert flight.sim("fc2").snapshot().mode == "POSCTL"


def test_restart_mid_flight_keeps_the_failed_over_autopilot(tmp_path: Path) -> None:
    with flying(["px4", "px4"], tmp_path, final_action=FinalAction.HOLD) as flight:
        flight.sim("fc1").inject(FaultKind.STATE, "EMERGENCY")
        wait_until("a failover", flight.agent.failovers, 10, POLL_S)
        flight.agent.stop()
        flight.sim("fc1").clear()  # the old primary looks perfect again
        bridge = SimulatedBridge([0, 1])
        again = Agent(flight.spec, bridge, state_file=StateFile(flight.state_path))
        again.start()
        try:
            assert bridge.selected == 1  # asserted at start, before any telemetry
            assert again.active == "fc2" and again.latched
            wait_until("both OK after restart", lambda: all_ok(again, ["fc1", "fc2"]), 5, POLL_S)
            time.sleep(CLEAR_S + 1.0)  # nothing happens past T_off: no switch back to fc1
            assert again.failovers() == []
            assert [s.channel for s in bridge.history] == [1]
            status = again.status()
            assert status.active_autopilot == "fc2" and status.latched
            assert status.last_failover is not None and status.last_failover.from_autopilot == "fc1"
        finally:
            again.stop()


def _command(command_id: str, action: str, target: str | None = None) -> AutopilotCommand:
    return AutopilotCommand(
        id=command_id, action=action, target=target, issued_at=datetime.now(UTC)
    )


def test_switch_command_runs_once_per_id_also_after_restart(tmp_path: Path) -> None:
    with flying(["ardupilot", "ardupilot"], tmp_path) as flight:
        first = flight.agent.submit(_command("sw-1", "Switch", "fc2")).result(timeout=5)
        assert first.result == "Executed"
        assert flight.bridge.selected == 1
        assert flight.agent.failovers()[0].record.trigger == "Command"
        again = flight.agent.submit(_command("sw-1", "Switch", "fc1")).result(timeout=5)
        assert again == first and flight.bridge.selected == 1
        back = flight.agent.submit(_command("sw-2", "Switch", "fc1")).result(timeout=5)
        assert back.result == "Executed" and flight.bridge.selected == 0
        flight.agent.stop()
        bridge = SimulatedBridge([0, 1])
        restarted = Agent(flight.spec, bridge, state_file=StateFile(flight.state_path))
        restarted.start()
        try:
            replay = restarted.submit(_command("sw-1", "Switch", "fc2")).result(timeout=5)
            assert replay == first
            assert [s.channel for s in bridge.history] == [0]
        finally:
            restarted.stop()


def test_emergency_stop_force_disarms_every_autopilot(tmp_path: Path) -> None:
    with flying(["px4", "ardupilot"], tmp_path) as flight:
        done = flight.agent.submit(_command("estop-1", "EmergencyStop")).result(timeout=5)
        assert done.result == "Executed"
        for sim in flight.sims:
            sim.wait_until(lambda s: not s.armed, timeout=5)


# -- the console script ---------------------------------------------------------------


def test_console_script_fails_over_and_restarts_from_its_state_dir(tmp_path: Path) -> None:
    sims = start_vehicle_sims(["px4", "px4"], config=SIM_CONFIG)
    state_dir = tmp_path / "state"
    config = tmp_path / "ra.yaml"
    spec = make_spec(sims, FinalAction.HOLD)
    config.write_text(
        yaml.safe_dump(
            {
                "apiVersion": "roost.dev/v1alpha1",
                "kind": "RedundantAutopilot",
                "metadata": {"name": "v1", "generation": 3},
                "spec": spec.to_api(),
            }
        )
    )
    agent = AgentProcess.standalone(tmp_path, extra_args=["--config", str(config)])
    try:
        agent.wait_for(lambda d: d.get("reason") == "AgentStarted", 10)
        take_off(sims)

        def both_ok(doc: dict[str, Any]) -> bool:
            aps = doc.get("status", {}).get("autopilots", [])
            return len(aps) == 2 and all(a["level"] == "OK" for a in aps)

        agent.wait_for(both_ok, 10)
        time.sleep(CLEAR_S + 0.3)  # T_off, a required duration: standbys become targets
        sims[0].inject(FaultKind.SILENCE)
        event = agent.wait_for(lambda d: d.get("event") == "Failover", 10)
        assert event["failover"]["from"] == "fc1" and event["failover"]["to"] == "fc2"
        assert event["latencyMs"] >= 0
        assert agent.stop() == 0
        sims[0].clear()
        saved = json.loads((state_dir / STATE_FILE_NAME).read_text())
        assert saved["active"] == "fc2" and saved["latched"] and saved["generation"] == 3

        restarted = AgentProcess.standalone(tmp_path)  # no config: the saved spec
        try:
            started = restarted.wait_for(lambda d: d.get("reason") == "AgentStarted", 10)
            assert "fc2 (restored from the state file, latched)" in started["message"]
            status = restarted.wait_for(both_ok, 10)["status"]
            assert status["activeAutopilot"] == "fc2" and status["latched"]
            time.sleep(CLEAR_S + 0.5)  # nothing happens past T_off: no switch back to fc1
            restarted.wait_for(lambda d: "status" in d, 5)
            assert not [d for d in restarted.seen if d.get("event") == "Failover"]
        finally:
            assert restarted.stop() == 0
    finally:
        agent.stop()
        stop_sims(sims)
