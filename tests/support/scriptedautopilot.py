"""A scripted autopilot for the safety routine: answers as a stack would, with the climb
rates and modes a test sets, and records what it was sent; and running a routine on it."""

from __future__ import annotations

import threading
import time

from roost_agent.health import Motion
from roost_agent.safety import Phase, SafetyRunner, Timing
from roost_api.autopilot import SafetyRoutine
from roost_api.meta import Stack
from roost_mavlink import (
    MAV_CMD_COMPONENT_ARM_DISARM,
    MAV_CMD_DO_SET_MODE,
    MAV_CMD_NAV_LAND,
    MAV_CMD_NAV_RETURN_TO_LAUNCH,
    MavLandedState,
    MavResult,
    MavState,
    custom_mode,
    mode_name,
)
from roost_mavlink.modes import custom_mode_from_set_mode

FAST = Timing(
    ack_timeout_s=0.01,
    retry_gap_s=0.01,
    mode_confirm_s=0.05,
    hold_confirm_s=0.05,
    hold_violation_s=0.01,
    telemetry_max_age_s=0.05,
    land_timeout_s=0.3,
    poll_s=0.002,
)


HOLD_PHASES = [Phase.STARTED, Phase.CONFIRMING_HOLD, Phase.HOLDING]

ACCEPTED = MavResult.ACCEPTED


class ScriptedAutopilot:
    """Answers each command from a per-command script (then ACCEPTED), applies accepted
    commands to its mode like an autopilot, and reports that mode in its heartbeat.

    Its altitude moves at ``climb_in[mode]`` m/s (0 when absent), integrated on every
    telemetry read, like a GLOBAL_POSITION_INT stream; ``telemetry=False`` sends none.
    """

    def __init__(
        self,
        stack: Stack,
        script: dict[int, list[int | None]] | None = None,
        *,
        mode: str | None = None,
        ignores_modes: bool = False,
        climb_in: dict[str, float] | None = None,
        telemetry: bool = True,
        touches_down: bool = True,
    ) -> None:
        self.name = "fc2"
        self.stack = stack
        self.script = {k: list(v) for k, v in (script or {}).items()}
        self.mode = custom_mode(stack, mode or ("POSCTL" if stack == Stack.PX4 else "GUIDED"))
        self.armed = True
        self.landed = MavLandedState.IN_AIR
        self.ignores_modes = ignores_modes
        self.climb_in = climb_in or {}
        self.telemetry = telemetry
        self.touches_down = touches_down
        self.status: int = MavState.ACTIVE
        self.altitude = 10.0
        self.moved_at = time.monotonic()
        self.lowest = self.altitude
        self.beat_at = 0.0
        self.sent: list[tuple[int, tuple[float, ...], int]] = []

    def command(
        self, command: int, params: tuple[float, ...], *, confirmation: int, timeout_s: float
    ) -> int | None:
        self.sent.append((command, params, confirmation))
        queue = self.script.get(command, [])
        answer = queue.pop(0) if queue else ACCEPTED
        if answer == ACCEPTED:
            self._apply(command, params)
        self.beat_at = time.monotonic()
        return answer

    def _apply(self, command: int, params: tuple[float, ...]) -> None:
        if self.ignores_modes:
            return
        self._move()
        if command == MAV_CMD_DO_SET_MODE:
            self.mode = custom_mode_from_set_mode(self.stack, *params[:3])
        elif command == MAV_CMD_NAV_LAND:
            self.mode = custom_mode(self.stack, "AUTO.LAND" if self.stack == Stack.PX4 else "LAND")
            if self.touches_down:
                self.landed = MavLandedState.ON_GROUND
        elif command == MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self.mode = custom_mode(self.stack, "AUTO.RTL" if self.stack == Stack.PX4 else "RTL")
        elif command == MAV_CMD_COMPONENT_ARM_DISARM:
            self.armed = False

    def _move(self) -> None:
        now = time.monotonic()
        rate = self.climb_in.get(mode_name(self.stack, self.mode), 0.0)
        self.altitude += rate * (now - self.moved_at)
        self.lowest = min(self.lowest, self.altitude)
        self.moved_at = now

    def heartbeat(self) -> tuple[int, int, float] | None:
        return self.mode, 1 | (128 if self.armed else 0), self.beat_at

    def landed_state(self) -> int | None:
        return self.landed

    def system_status(self) -> int | None:
        return self.status

    def motion(self) -> Motion | None:
        if not self.telemetry:
            return None
        self._move()
        rate = self.climb_in.get(mode_name(self.stack, self.mode), 0.0)
        return Motion(self.altitude, rate, time.monotonic())

    def commands(self) -> list[int]:
        return [c for c, _, _ in self.sent]

    def modes_requested(self) -> list[int]:
        return [
            custom_mode_from_set_mode(self.stack, *p[:3])
            for c, p, _ in self.sent
            if c == MAV_CMD_DO_SET_MODE
        ]


def run(
    autopilot: ScriptedAutopilot,
    routine: SafetyRoutine | None = None,
    cancel: threading.Event | None = None,
    **kwargs: object,
) -> tuple[Phase, list[Phase]]:
    phases: list[Phase] = []
    runner = SafetyRunner(
        autopilot,
        cancel or threading.Event(),
        lambda p, _: phases.append(p),
        FAST,
        **kwargs,  # type: ignore[arg-type]
    )
    # The API's model has the fields of the plain class the agent loads from its spec.
    chosen = routine or SafetyRoutine(hold_seconds=0.05)
    return runner.run(chosen), phases  # type: ignore[arg-type]
