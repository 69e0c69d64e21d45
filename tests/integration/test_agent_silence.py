"""The learnt silence threshold in the running agent, against two simulated PX4s.

The agent runs as its own process (``roost-agent --cluster off``, simulated bridge: the
one stand-in, no GPIO here) on two simulated PX4s streaming their onboard rates over
real UDP, at the default thresholds but the floor (60 ms, learning on; the default floor
equals the ceiling, a fixed threshold). A silent active autopilot fails over on the
threshold learnt from its stream (the floor, far under the fixed ceiling); the agent
itself stopped (SIGSTOP, a starved CPU at its worst) while both autopilots keep
streaming is never judged as their silence: no ERROR, no failover. About 25 s.
"""

from __future__ import annotations

import os
import re
import signal
import time
from pathlib import Path

import pytest

from roost_api.autopilot import (
    FailoverPolicy,
    FinalAction,
    RedundantAutopilotSpec,
    SafetyRoutine,
    Thresholds,
)
from roost_sim import FaultKind, SimConfig, autopilot_specs, start_vehicle_sims, stop_sims
from tests.support.agent import AgentProcess
from tests.support.flight import take_off

# serial: silence thresholds judged in real time
pytestmark = [pytest.mark.slow, pytest.mark.serial]

LEARN_S = 3.0  # two complete one-second windows, and a margin
STOPS = 5
STOPPED_S = 0.3  # longer than the ceiling (200 ms) of the silence threshold


def test_silence_fails_over_on_the_learnt_threshold_and_a_stopped_agent_is_not_silence(
    tmp_path: Path,
) -> None:
    sims = start_vehicle_sims(["px4", "px4"], config=SimConfig.fast())
    by_name = {s.name: s for s in sims}
    th = Thresholds()  # the defaults: this is the detector's test
    spec = RedundantAutopilotSpec(
        vehicle_name="silence",
        autopilots=autopilot_specs(sims),
        primary="fc1",
        failover_policy=FailoverPolicy(
            thresholds=th,
            safety_routine=SafetyRoutine(hold_seconds=0, final_action=FinalAction.HOLD),
        ),
    )
    agent = AgentProcess.standalone(tmp_path, spec, log_level="WARNING")
    try:
        take_off(sims)
        agent.wait_ok(["fc1", "fc2"])
        time.sleep(LEARN_S)

        by_name["fc1"].inject(FaultKind.SILENCE)
        event = agent.wait_for(lambda d: d.get("event") == "Failover", 10)
        assert event["failover"]["to"] == "fc2"
        # the threshold learnt from the stream: the floor on a quiet machine, higher when
        # the simulators' own scheduling leaves longer gaps (never above the ceiling)
        limit = re.search(r"silent for \d+ ms \(limit (\d+) ms\)", event["failover"]["reason"])
        assert limit is not None, event["failover"]["reason"]
        assert th.message_error_min_ms <= int(limit[1]) <= th.message_error_ms

        by_name["fc1"].clear()
        assert agent.command("ClearLatch")["result"] == "Executed"
        agent.wait_ok(["fc1", "fc2"])
        time.sleep(LEARN_S)
        agent.read()
        for _ in range(STOPS):
            os.kill(agent.pid, signal.SIGSTOP)
            time.sleep(STOPPED_S)
            os.kill(agent.pid, signal.SIGCONT)
            time.sleep(0.5)
        agent.wait_ok(["fc1", "fc2"])
        seen = agent.read()
        assert not [d for d in seen if d.get("event") == "Failover"]
        judged = [
            (d["autopilot"], d["health"]["level"], d["health"]["reasons"])
            for d in seen
            if d.get("event") == "HealthChanged"
        ]
        assert not [j for j in judged if j[1] in ("ERROR", "STALE")], judged
    finally:
        agent.stop()
        stop_sims(sims)
