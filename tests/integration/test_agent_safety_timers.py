"""The safety routine when something changes while it runs: a hold that fails later, a
cancel while holding.

The scripted autopilot of the routine's decision table (``tests/unit/test_agent_safety.py``)
changes on a timer thread while the routine runs in real time.
"""

from __future__ import annotations

import threading

from roost_agent.safety import Phase
from roost_api.autopilot import SafetyRoutine
from roost_api.meta import Stack
from roost_mavlink import (
    MAV_CMD_DO_SET_MODE,
)
from tests.support.scriptedautopilot import HOLD_PHASES, ScriptedAutopilot, run


def test_a_hold_that_fails_later_escalates_then() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4)
    threading.Timer(0.15, lambda: autopilot.climb_in.update({"AUTO.LOITER": -3.0})).start()
    final, phases = run(autopilot, SafetyRoutine(hold_seconds=2.0))
    assert phases[:3] == HOLD_PHASES and phases[3] == Phase.HOLD_FAILED
    assert final == Phase.LANDED


def test_cancelled_while_holding_sends_nothing_more() -> None:
    autopilot = ScriptedAutopilot(Stack.PX4)
    cancel = threading.Event()
    threading.Timer(0.1, cancel.set).start()
    final, _ = run(autopilot, SafetyRoutine(hold_seconds=5.0), cancel)
    assert final == Phase.CANCELLED and autopilot.commands() == [MAV_CMD_DO_SET_MODE]
