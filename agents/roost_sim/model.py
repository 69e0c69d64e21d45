"""The flight-controller behaviour of one simulated autopilot: pure state, no I/O, no threads.

Why separate from the wire: every decision that arms, disarms, switches mode or lands
lives here and is unit-tested as a decision table with a fake clock, while
:mod:`roost_sim.autopilot` only turns MAVLink bytes into these calls and this state back
into messages.

What is modelled, per stack (the facts and their sources are in ``docs/health-model.md``):

- Modes and their vertical behaviour. Climb while a takeoff target is set, hold
  otherwise; descend in land and return modes. The vehicle never moves horizontally, so
  return-to-launch is "descend and land here" (it is always at home).
- Takeoff: PX4 accepts NAV_TAKEOFF on the ground armed or not (switches to AUTO.TAKEOFF,
  climbs once armed, then AUTO.LOITER); param7 is an AMSL altitude, NaN means the default
  takeoff altitude. ArduCopter needs to be armed and in a mode with user takeoff (GUIDED,
  LOITER, ALT_HOLD, POSHOLD); param7 is relative; it stays in that mode afterwards.
- Arming is refused while booting, with any counted sensor unhealthy (preflight checks),
  under an injected MAV_STATE other than STANDBY/ACTIVE, and on ArduCopter in a mode that
  cannot be armed (LAND, RTL, AUTO...). Disarming is refused in the air. The force magic
  21196 overrides both. Refusals use each stack's code: PX4 answers
  TEMPORARILY_REJECTED (DENIED for an unknown mode), ArduPilot FAILED.
- Modes that need a position estimate (hold, RTL, takeoff, guided) are refused while the
  GPS sensor is failed; land always works, as on the real stacks.
- After landing the vehicle disarms itself after ``auto_disarm_after_land_s``; armed and
  idle on the ground it disarms after ``idle_disarm_s`` (COM_DISARM_PRFLT / DISARM_DELAY).
- MAV_STATE: BOOT for ``boot_s`` after (re)boot; PX4 STANDBY when disarmed, ACTIVE when
  armed; ArduCopter STANDBY on the ground even when armed, ACTIVE in the air. Armed with a
  critical sensor failed both report CRITICAL (a failsafe is active). An injected
  MAV_STATE overrides all of that.
- SYS_STATUS: the stack's sensor set present and enabled; healthy except the stack's
  normally-unhealthy bits and injected failures; PREARM_CHECK is unhealthy while
  disarmed and a pre-arm check fails (booting, or a counted sensor failed).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from roost_api.meta import Stack
from roost_mavlink import FORCE_DISARM_MAGIC, MavResult
from roost_mavlink.modes import ModeIntent, custom_mode, default_mode, intent_mode, mode_name
from roost_mavlink.status import (
    CRITICAL_SENSORS,
    IGNORED_SENSORS,
    LandedState,
    MavState,
    SensorBit,
    stack_normally_unhealthy,
    stack_sensors,
)

Clock = Callable[[], float]

# Modes in which the vehicle goes down and lands where it is.
_DESCEND_MODES: dict[Stack, frozenset[str]] = {
    Stack.PX4: frozenset({"AUTO.LAND", "AUTO.RTL", "AUTO.PRECLAND"}),
    Stack.ARDUPILOT: frozenset({"LAND", "RTL", "SMART_RTL", "AUTO_RTL"}),
}
# Modes that need a position estimate to be entered (refused with GPS failed).
_POSITION_MODES: dict[Stack, frozenset[str]] = {
    Stack.PX4: frozenset(
        {"POSCTL", "AUTO.LOITER", "AUTO.RTL", "AUTO.TAKEOFF", "AUTO.MISSION", "OFFBOARD"}
    ),
    Stack.ARDUPILOT: frozenset(
        {"LOITER", "BRAKE", "RTL", "SMART_RTL", "AUTO", "GUIDED", "POSHOLD", "CIRCLE"}
    ),
}
_ARDUPILOT_UNARMABLE = frozenset({"LAND", "RTL", "SMART_RTL", "AUTO_RTL", "AUTO", "BRAKE"})
_ARDUPILOT_USER_TAKEOFF = frozenset({"GUIDED", "LOITER", "ALT_HOLD", "POSHOLD"})
_FALL_RATE_MPS = 8.0  # a disarmed vehicle in the air drops


@dataclass
class SimConfig:
    """Tunable behaviour of a simulated autopilot (defaults keep tests quick)."""

    climb_rate_mps: float = 2.5
    descent_rate_mps: float = 1.5
    takeoff_alt_m: float = 2.5
    auto_disarm_after_land_s: float = 1.0
    idle_disarm_s: float = 10.0
    boot_s: float = 0.5
    home_lat_deg: float = 47.397742
    home_lon_deg: float = 8.545594
    home_amsl_m: float = 488.0


@dataclass(frozen=True)
class ModeChange:
    """The autopilot entered ``mode`` at monotonic time ``at``."""

    at: float
    mode: str


@dataclass(frozen=True)
class Sensors:
    """SYS_STATUS onboard_control_sensors_* masks."""

    present: int
    enabled: int
    health: int


@dataclass
class AutopilotModel:
    """State and rules of one flight controller; call :meth:`step` regularly."""

    stack: Stack
    config: SimConfig = field(default_factory=SimConfig)
    clock: Clock = time.monotonic
    armed: bool = field(init=False, default=False)
    custom_mode: int = field(init=False, default=0)
    altitude_m: float = field(init=False, default=0.0)
    climb_mps: float = field(init=False, default=0.0)
    landed_state: LandedState = field(init=False, default=LandedState.ON_GROUND)
    takeoff_target_m: float | None = field(init=False, default=None)
    sensor_faults: SensorBit = field(init=False, default=SensorBit(0))
    state_override: MavState | None = field(init=False, default=None)
    boot_at: float = field(init=False, default=0.0)
    mode_history: list[ModeChange] = field(init=False, default_factory=list)
    _last_step: float = field(init=False, default=0.0)
    _on_ground_armed_since: float | None = field(init=False, default=None)
    _landed_at: float | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        self.stack = Stack(self.stack)
        self.reboot()

    # ---- lifecycle -------------------------------------------------------------------

    def reboot(self) -> None:
        """Power-cycle: time restarts, disarmed on the ground in the default mode."""
        now = self.clock()
        self.boot_at = now
        self._last_step = now
        self.armed = False
        self.altitude_m = 0.0
        self.climb_mps = 0.0
        self.landed_state = LandedState.ON_GROUND
        self.takeoff_target_m = None
        self.state_override = None
        self._on_ground_armed_since = None
        self._landed_at = None
        self._enter_mode(custom_mode(self.stack, default_mode(self.stack)))

    def time_boot_ms(self) -> int:
        """Milliseconds since (re)boot, as in every timestamped message."""
        return int((self.clock() - self.boot_at) * 1000)

    @property
    def booting(self) -> bool:
        """True during the BOOT phase right after (re)boot."""
        return self.clock() - self.boot_at < self.config.boot_s

    @property
    def mode(self) -> str:
        """Current mode name in the stack's spelling."""
        return mode_name(self.stack, self.custom_mode)

    @property
    def on_ground(self) -> bool:
        """The vehicle rests on the ground."""
        return self.landed_state is LandedState.ON_GROUND

    # ---- derived state ---------------------------------------------------------------

    def _counted_failures(self) -> SensorBit:
        return self.sensor_faults & ~IGNORED_SENSORS

    def _critical_failure(self) -> bool:
        return bool(self.sensor_faults & CRITICAL_SENSORS)

    def sensors(self) -> Sensors:
        """SYS_STATUS masks as this stack would report them now."""
        enabled = stack_sensors(self.stack) | self.sensor_faults
        health = enabled & ~stack_normally_unhealthy(self.stack) & ~self.sensor_faults
        if not self.armed and (self._counted_failures() or self.booting):
            health &= ~SensorBit.PREARM_CHECK  # the pre-arm checks do not pass
        return Sensors(present=int(enabled), enabled=int(enabled), health=int(health))

    def system_status(self) -> MavState:
        """The heartbeat's MAV_STATE."""
        if self.booting:
            return MavState.BOOT
        if self.state_override is not None:
            return self.state_override
        if self.armed and self._critical_failure():
            return MavState.CRITICAL
        if self.stack is Stack.ARDUPILOT:
            return MavState.ACTIVE if self.armed and not self.on_ground else MavState.STANDBY
        return MavState.ACTIVE if self.armed else MavState.STANDBY

    # ---- commands (each returns a MAV_RESULT) ----------------------------------------

    def refused_result(self) -> int:
        """What this stack answers to a request that is valid but not possible now."""
        return MavResult.TEMPORARILY_REJECTED if self.stack is Stack.PX4 else MavResult.FAILED

    def invalid_result(self) -> int:
        """What this stack answers to a malformed request (unknown mode)."""
        return MavResult.DENIED if self.stack is Stack.PX4 else MavResult.FAILED

    def arm(self, *, arm: bool, magic: float = 0.0) -> int:
        """COMPONENT_ARM_DISARM: param1 = arm, param2 = 21196 to force."""
        force = math.isfinite(magic) and int(magic) == FORCE_DISARM_MAGIC
        if arm == self.armed:
            return MavResult.ACCEPTED
        if arm:
            if not force and not self._may_arm():
                return self.refused_result()
            self.armed = True
            self._landed_at = None
            self._on_ground_armed_since = self.clock() if self.on_ground else None
            return MavResult.ACCEPTED
        if not force and not self.on_ground:
            return self.refused_result()
        self._disarm()
        return MavResult.ACCEPTED

    def _may_arm(self) -> bool:
        if self.booting or self._counted_failures():
            return False
        if self.state_override not in (None, MavState.STANDBY, MavState.ACTIVE):
            return False
        return not (self.stack is Stack.ARDUPILOT and self.mode in _ARDUPILOT_UNARMABLE)

    def _disarm(self) -> None:
        self.armed = False
        self.takeoff_target_m = None
        self._on_ground_armed_since = None
        self._landed_at = None

    def set_mode(self, value: int) -> int:
        """DO_SET_MODE with an already decoded ``custom_mode``."""
        if mode_name(self.stack, value).startswith("UNKNOWN"):
            return self.invalid_result()
        name = mode_name(self.stack, value)
        if name in _POSITION_MODES[self.stack] and self.sensor_faults & SensorBit.GPS:
            return self.refused_result()
        # Any mode change ends a climb where it is; PX4's takeoff mode starts one.
        self.takeoff_target_m = None
        if self.stack is Stack.PX4 and name == "AUTO.TAKEOFF":
            self.takeoff_target_m = max(self.config.takeoff_alt_m, self.altitude_m)
        self._enter_mode(value)
        return MavResult.ACCEPTED

    def takeoff(self, altitude_param: float) -> int:
        """NAV_TAKEOFF; ``altitude_param`` is param7 (PX4: AMSL, ArduPilot: relative)."""
        if self.sensor_faults & SensorBit.GPS:
            return self.refused_result()
        if self.stack is Stack.PX4:
            if math.isfinite(altitude_param):
                target = altitude_param - self.config.home_amsl_m
            else:
                target = self.config.takeoff_alt_m
            if target <= 0:
                return MavResult.DENIED
            self.takeoff_target_m = max(target, self.altitude_m)
            self._enter_mode(custom_mode(self.stack, "AUTO.TAKEOFF"))
            return MavResult.ACCEPTED
        if not self.armed or not self.on_ground or self.mode not in _ARDUPILOT_USER_TAKEOFF:
            return MavResult.FAILED
        target = altitude_param if math.isfinite(altitude_param) and altitude_param > 0 else 0.0
        self.takeoff_target_m = target or self.config.takeoff_alt_m
        return MavResult.ACCEPTED

    def land(self) -> int:
        """NAV_LAND: always switches to the land mode (it needs no position estimate)."""
        self.takeoff_target_m = None
        self._enter_mode(custom_mode(self.stack, intent_mode(self.stack, ModeIntent.LAND)))
        return MavResult.ACCEPTED

    def return_to_launch(self) -> int:
        """NAV_RETURN_TO_LAUNCH: the RTL mode (needs a position estimate)."""
        return self.set_mode(
            custom_mode(self.stack, intent_mode(self.stack, ModeIntent.RETURN_TO_LAUNCH))
        )

    def _enter_mode(self, value: int) -> None:
        changed = value != self.custom_mode or not self.mode_history
        self.custom_mode = value
        if changed:
            self.mode_history.append(ModeChange(at=self.clock(), mode=self.mode))

    # ---- kinematics ------------------------------------------------------------------

    def step(self) -> None:
        """Advance the simple vertical kinematics and the automatic disarms to now."""
        now = self.clock()
        dt = max(0.0, now - self._last_step)
        self._last_step = now
        if not self.armed:
            self.takeoff_target_m = None if self.stack is Stack.ARDUPILOT else self.takeoff_target_m
            self._fall(dt)
            return
        if self.mode in _DESCEND_MODES[self.stack]:
            self._descend(dt, now)
        elif self.takeoff_target_m is not None:
            self._climb(dt)
        else:
            self.climb_mps = 0.0
            if not self.on_ground:
                self.landed_state = LandedState.IN_AIR
        self._auto_disarm(now)

    def _fall(self, dt: float) -> None:
        if self.altitude_m <= 0.0:
            self.climb_mps = 0.0
            self.landed_state = LandedState.ON_GROUND
            return
        self.climb_mps = -_FALL_RATE_MPS
        self.altitude_m = max(0.0, self.altitude_m - _FALL_RATE_MPS * dt)
        self.landed_state = LandedState.IN_AIR if self.altitude_m > 0 else LandedState.ON_GROUND

    def _climb(self, dt: float) -> None:
        target = self.takeoff_target_m
        assert target is not None
        self._on_ground_armed_since = None
        self.altitude_m = min(target, self.altitude_m + self.config.climb_rate_mps * dt)
        self.climb_mps = self.config.climb_rate_mps
        self.landed_state = LandedState.TAKEOFF
        if self.altitude_m >= target:
            self.takeoff_target_m = None
            self.climb_mps = 0.0
            self.landed_state = LandedState.IN_AIR
            if self.stack is Stack.PX4:
                self._enter_mode(custom_mode(self.stack, intent_mode(self.stack, ModeIntent.HOLD)))

    def _descend(self, dt: float, now: float) -> None:
        self.takeoff_target_m = None
        if self.on_ground:
            self.climb_mps = 0.0
            if self._landed_at is None:
                self._landed_at = now
            return
        self.altitude_m = max(0.0, self.altitude_m - self.config.descent_rate_mps * dt)
        self.climb_mps = -self.config.descent_rate_mps
        self.landed_state = LandedState.LANDING
        if self.altitude_m <= 0.0:
            self.climb_mps = 0.0
            self.landed_state = LandedState.ON_GROUND
            self._landed_at = now

    def _auto_disarm(self, now: float) -> None:
        if not self.on_ground:
            self._on_ground_armed_since = None
            return
        if self._landed_at is not None:
            if now - self._landed_at >= self.config.auto_disarm_after_land_s:
                self._disarm()
            return
        if self._on_ground_armed_since is None:
            self._on_ground_armed_since = now
        if now - self._on_ground_armed_since >= self.config.idle_disarm_s:
            self._disarm()
