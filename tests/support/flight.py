"""Simulated autopilots in the air under an agent, for the failover tests and benchmarks.

:func:`take_off` gets sims airborne and :func:`land` brings one down; :func:`make_spec`
is the RedundantAutopilot spec the agent tests fly them with; :class:`Flight` is one
such vehicle (sims, in-process agent, simulated bridge) with what the tests ask of it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from roost_agent import Agent
from roost_agent.bridge import SimulatedBridge
from roost_api.autopilot import (
    AutopilotSpec,
    FailoverPolicy,
    FinalAction,
    HubSpec,
    RedundantAutopilotSpec,
    SafetyRoutine,
    Thresholds,
)
from roost_mavlink import (
    AGENT_COMPONENT_ID,
    MAV_CMD_NAV_LAND,
    MAV_CMD_REQUEST_MESSAGE,
    MAV_CMD_SET_MESSAGE_INTERVAL,
)
from roost_sim import SimulatedAutopilot, autopilot_specs

BOOT_TIMEOUT_S = 5.0
TAKEOFF_TIMEOUT_S = 15.0
AIRBORNE_M = 2.0


def take_off(sims: Sequence[SimulatedAutopilot]) -> None:
    """Wait for every sim to finish start-up (booted, position estimate, armable), order
    all to fly, wait until all are airborne (in the air and above :data:`AIRBORNE_M`).

    The sims should run with ``SimConfig.fast()``: a realistic ArduCopter waits ~40 s for
    its position estimate before it arms.
    """
    for sim in sims:
        sim.wait_ready(timeout=BOOT_TIMEOUT_S)
    for sim in sims:
        sim.fly()
    for sim in sims:
        sim.wait_until(
            lambda s: s.landed_state == "InAir" and s.altitude_m > AIRBORNE_M,
            timeout=TAKEOFF_TIMEOUT_S,
        )


def land(sim: SimulatedAutopilot) -> None:
    """NAV_LAND, as a ground station on another link would send it (the firmware
    disarms after the touchdown)."""
    sim.local_command(MAV_CMD_NAV_LAND, (0, 0, 0, math.nan, math.nan, math.nan, math.nan))


# The silence thresholds of tests whose subject is not the silence detector: fixed at the
# 200 ms ceiling (floor = ceiling), not learnt. Why: simulated autopilots in a test share
# the test's process and two CI cores with the agent; under load they stall for tens of
# milliseconds, which a threshold learnt from their steady stream (60 ms floor, late at
# 30 ms) would call late or silent. Firmware on its own MCU does not stall with the
# companion computer. The detector's own tests (test_agent_silence, the unit tables) and
# the benchmarks keep the defaults.
SIM_THRESHOLDS = Thresholds(message_error_min_ms=Thresholds().message_error_ms)
HOLD_S = 1.0  # the safety routine's hold in the agent tests
CLEAR_S = 1.0  # Thresholds.clear_ms default: a standby must be OK this long
POLL_S = 0.02  # failovers take tens of milliseconds: look often


@dataclass
class Flight:
    """One airborne vehicle: its sims, the agent watching them and the simulated bridge."""

    sims: list[SimulatedAutopilot]
    agent: Agent
    bridge: SimulatedBridge
    spec: RedundantAutopilotSpec
    state_path: Path

    def sim(self, name: str) -> SimulatedAutopilot:
        return next(s for s in self.sims if s.name == name)

    def agent_commands(self, name: str, since: float = 0.0) -> list[Any]:
        """Commands the agent (component 191) sent to autopilot ``name``, except its
        requests for data, which it sends to every autopilot: telemetry rates
        (SET_MESSAGE_INTERVAL) and AUTOPILOT_VERSION (REQUEST_MESSAGE, again after a
        reboot)."""
        return [
            c
            for c in self.sim(name).commands
            if c.source[1] == AGENT_COMPONENT_ID
            and c.at >= since
            and c.command not in (MAV_CMD_SET_MESSAGE_INTERVAL, MAV_CMD_REQUEST_MESSAGE)
        ]


def make_spec(
    sims: list[SimulatedAutopilot],
    final_action: FinalAction = FinalAction.LAND,
    thresholds: Thresholds | None = None,
) -> RedundantAutopilotSpec:
    """Vehicle ``v1`` over ``sims`` (the first is primary), holding :data:`HOLD_S`
    (:data:`SIM_THRESHOLDS` unless given)."""
    return RedundantAutopilotSpec(
        vehicle_name="v1",
        autopilots=autopilot_specs(sims),
        primary=sims[0].name,
        failover_policy=FailoverPolicy(
            thresholds=thresholds if thresholds is not None else SIM_THRESHOLDS,
            safety_routine=SafetyRoutine(hold_seconds=HOLD_S, final_action=final_action),
        ),
    )


def px4_pair_on_udp(
    vehicle: str,
    ports: Sequence[int],
    hub: HubSpec,
    failover_policy: FailoverPolicy | None = None,
) -> RedundantAutopilotSpec:
    """Vehicle ``vehicle`` with PX4 autopilots fc1, fc2 (system ids 1, 2, bridge channels
    0, 1) listened for on 127.0.0.1 ``ports``, and ``hub``: for tests and benches whose
    autopilots are plain sockets rather than simulators."""
    return RedundantAutopilotSpec(
        vehicle_name=vehicle,
        primary="fc1",
        autopilots=[
            AutopilotSpec(
                name=f"fc{i + 1}",
                stack="px4",
                connection=f"udp://127.0.0.1:{port}",
                sysid=i + 1,
                bridge_channel=i,
            )
            for i, port in enumerate(ports)
        ],
        failover_policy=failover_policy or FailoverPolicy(),
        hub=hub,
    )
