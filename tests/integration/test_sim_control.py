"""The simulator's control requests that wait in real time.

A ``fly`` request waits (polling, up to its ``timeout``) for the autopilot to finish
starting up; a refusal must still be an answer that changes nothing. The other refused
requests are a decision table in ``tests/unit/test_sim_autopilot.py``.
"""

from __future__ import annotations

from roost_api.meta import Stack
from roost_sim.autopilot import SimulatedAutopilot
from roost_sim.control import handle_request


def test_a_fly_request_while_starting_up_is_refused_and_changes_nothing() -> None:
    sim = SimulatedAutopilot.udp(Stack.ARDUPILOT, 1)  # not started; realistic 41 s boot
    answer = handle_request(sim, {"op": "fly", "timeout": 0.05})
    assert answer["ok"] is False and "still starting up" in answer["error"]
    assert handle_request(sim, {"op": "status"})["state"]["faults"] == {}
    assert sim.link.impairment.jitter_ms == 0.0
