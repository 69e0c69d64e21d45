"""The flight-controller behaviour of one simulated autopilot: pure state, no I/O, no threads.

Why separate from the wire: every decision that arms, disarms, switches mode or lands
lives here and is unit-tested as a decision table with a fake clock, while
:mod:`roost_sim.autopilot` only turns MAVLink bytes into these calls and this state back
into messages.

Calibrated against recordings of the real firmware (PX4 v1.16 SIH and ArduCopter 4.7
SITL, two instances each); the numbers below are measured there.

- **Boot.** PX4 reports MAV_STATE UNINIT (not BOOT) until STANDBY 4.0 s after launch;
  its estimator reports ``ESTIMATOR_STATUS`` flags 0x400 (nothing estimated yet) from
  1 s, 0xe5 from 2 s and a full solution (0x3ff on the ground) from 3 s; arming is
  refused (TEMPORARILY_REJECTED) until STANDBY. ArduCopter reports BOOT for 2 s, then
  STANDBY while its EKF initialises (3.4 s), sets its origin from GPS (19 s) and uses
  GPS (40.6 s); arming is refused (FAILED) with ArduPilot's texts ("Arm: AHRS: waiting
  for home", "Arm: Need Position Estimate") until then. A mode set during ArduCopter's
  BOOT is overwritten with STABILIZE when it finishes. :class:`SimConfig` makes both
  phases short for tests (:meth:`SimConfig.fast`, ``roost-sim run --fast-boot``).
- **Modes and vertical behaviour.** Climb while a takeoff target is set; descend in land
  and return modes. PX4 switches itself to AUTO.LOITER after a takeoff and holds there.
  ArduCopter stays in GUIDED after a takeoff; GUIDED and BRAKE (17) hold position, while
  LOITER, ALT_HOLD, POSHOLD and the manual modes follow the throttle stick: centred it
  holds, low it descends at PILOT_SPEED_DN (0 = PILOT_SPEED_UP, 2.5 m/s) with
  PILOT_ACCEL_Z (2.5 m/s^2). Without RC the stick rests low, so LOITER without a pilot
  flies into the ground at ~2.45 m/s without flaring -- the recorded crash
  (``throttle`` sets a stick; RC_CHANNELS_OVERRIDE channel 3 does it over MAVLink).
- **Landing.** Land modes descend at PX4 0.7 m/s, ArduCopter 0.5 m/s. A touchdown
  records its vertical speed (:attr:`AutopilotModel.touchdowns`; ArduPilot SITL says "SIM
  Hit ground at X m/s"). The landing detector reports ON_GROUND ``land_detect_s`` after
  contact (PX4 ~7 s, ArduCopter ~2 s); in a land mode the vehicle then disarms after
  ``auto_disarm_after_land_s`` (PX4 2 s, ArduCopter 0.5 s), elsewhere after
  DISARM_DELAY (10 s). :meth:`SimConfig.fast` lands at 1.5 m/s, detects in 0.3 s.
- **Takeoff.** PX4 accepts NAV_TAKEOFF on the ground armed or not (AUTO.TAKEOFF, climbs
  once armed, then AUTO.LOITER); param7 is AMSL, NaN means MIS_TAKEOFF_ALT. ArduCopter
  needs to be armed in a mode with user takeoff (GUIDED, LOITER, ALT_HOLD, POSHOLD);
  param7 is relative.
- **Arming** is refused while booting or waiting for a position, with any counted
  sensor unhealthy, under an injected MAV_STATE other than STANDBY/ACTIVE, and on
  ArduCopter in a mode that cannot be armed. Disarming is refused in the air. The force
  magic 21196 overrides both.
- Modes that need a position estimate are refused while the GPS sensor is failed; land
  always works.
- **MAV_STATE**: see :meth:`AutopilotModel.system_status`. A failsafe (critical sensor
  failed while armed, battery at its emergency level) reports CRITICAL.
- **Battery** (:mod:`roost_sim.battery`): PX4 answers an emergency-level battery by
  holding 5 s, then AUTO.LAND; ArduCopter's default only reports it.
- **Horizontal flight** (:mod:`roost_sim.kinematics`, local NED metres from home).
  Position setpoints (SET_POSITION_TARGET_LOCAL_NED / _GLOBAL_INT: position and yaw)
  are flown in PX4 OFFBOARD and ArduCopter GUIDED. PX4 refuses OFFBOARD unless
  setpoints arrived within the last ``offboard_loss_s`` (its COM_OF_LOSS_T, 1 s) and,
  in OFFBOARD, falls back to AUTO.LOITER when they stop for that long; ArduCopter
  takes setpoints only in GUIDED and keeps flying to the last one. Every other mode
  holds the position it was entered at; RTL modes fly home at the current altitude and
  descend once over it. Setpoints that give no position (velocity, acceleration only)
  are not modelled and are ignored.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

from roost_api.meta import Stack
from roost_mavlink import FORCE_DISARM_MAGIC, MavResult
from roost_mavlink.modes import ModeIntent, custom_mode, default_mode, intent_mode, mode_name
from roost_mavlink.status import (
    CRITICAL_SENSORS,
    IGNORED_SENSORS,
    MavLandedState,
    MavState,
    SensorBit,
    stack_normally_unhealthy,
    stack_sensors,
)
from roost_sim.battery import Battery, BatteryReading, ChargeState
from roost_sim.kinematics import Horizontal

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
# ArduCopter modes whose climb rate comes from the pilot's throttle stick.
_ARDUPILOT_STICK_MODES = frozenset(
    {"STABILIZE", "ACRO", "ALT_HOLD", "LOITER", "POSHOLD", "SPORT", "DRIFT", "FLOWHOLD"}
)
# Modes in which a vehicle flies to position setpoints.
_SETPOINT_MODES: dict[Stack, str] = {Stack.PX4: "OFFBOARD", Stack.ARDUPILOT: "GUIDED"}
_RTL_MODES = frozenset({"AUTO.RTL", "RTL", "SMART_RTL", "AUTO_RTL"})
_OVER_HOME_M = 0.5  # an RTL descends once this close to home
_SETPOINT_CLIMB_GAIN = 1.0  # m/s of climb per metre of altitude error, within the rates
_FALL_RATE_MPS = 8.0  # a disarmed vehicle in the air drops
_THROTTLE_DEADZONE = 0.1  # THR_DZ 100 of 1000, each side of centre
_PX4_BATTERY_HOLD_S = 5.0  # "Hold for 5 seconds", then land

SEVERITY_CRITICAL = 2
SEVERITY_INFO = 6


@dataclass(frozen=True)
class BootTimes:
    """Seconds after (re)boot at which each start-up step completes."""

    first_heartbeat_s: float  # PX4: nothing but raw sensors before its first heartbeat
    attitude_s: float  # the estimator has an attitude
    standby_s: float  # MAV_STATE leaves UNINIT/BOOT
    origin_s: float  # ArduCopter: EKF origin and home set from GPS
    position_s: float  # a position estimate: arming possible (ArduCopter), GLOBAL_POSITION


# Measured on the real firmware (seconds after launch).
_REALISTIC_BOOT: dict[Stack, BootTimes] = {
    Stack.PX4: BootTimes(
        first_heartbeat_s=1.0, attitude_s=2.0, standby_s=4.0, origin_s=1.1, position_s=3.0
    ),
    Stack.ARDUPILOT: BootTimes(
        first_heartbeat_s=0.0, attitude_s=3.4, standby_s=2.0, origin_s=19.0, position_s=40.6
    ),
}


@dataclass(frozen=True)
class Landing:
    """How a stack lands: descent rate in its land mode, how long its landing detector
    takes after ground contact, and how long it stays armed once landed there."""

    descent_mps: float
    detect_s: float
    disarm_s: float


# Measured: PX4 descends at MPC_LAND_SPEED (0.7 m/s), its land detector reports ON_GROUND
# ~7 s after contact (SIH), COM_DISARM_LAND 2 s. ArduCopter: LAND_SPEED 0.5 m/s, landed
# 1.6 s (LAND) to 2.3 s (LOITER) after contact, disarms ~0.5 s after landing in LAND.
_REALISTIC_LANDING: dict[Stack, Landing] = {
    Stack.PX4: Landing(descent_mps=0.7, detect_s=7.0, disarm_s=2.0),
    Stack.ARDUPILOT: Landing(descent_mps=0.5, detect_s=2.0, disarm_s=0.5),
}
_FAST_LANDING: dict[Stack, Landing] = {
    stack: Landing(descent_mps=1.5, detect_s=0.3, disarm_s=1.0) for stack in Stack
}

# ``SimConfig.fast()``: the same order of steps in well under a second.
_FAST_BOOT: dict[Stack, BootTimes] = {
    Stack.PX4: replace(_REALISTIC_BOOT[Stack.PX4], standby_s=0.4, position_s=0.3),
    Stack.ARDUPILOT: replace(_REALISTIC_BOOT[Stack.ARDUPILOT], standby_s=0.3, position_s=0.6),
}


@dataclass
class SimConfig:
    """Tunable behaviour of a simulated autopilot; defaults follow the real firmware.

    ``boot_s`` (time to STANDBY) and ``position_wait_s`` (time to a position estimate)
    default to the stack's measured values (PX4 4.0 s and 3.0 s, ArduCopter 2.0 s and
    40.6 s); the other start-up steps scale with them. ``fast_boot`` (:meth:`fast`)
    gives sub-second boots for tests. ``throttle`` is the pilot's stick (0 low .. 1
    high); None means no RC, which ArduCopter reads as a low stick.
    ``battery_failsafe_land`` None is each stack's default (PX4 lands, ArduCopter only
    reports). ``preset_streams``: ArduCopter streams the usual set from boot, as with
    its SRn_* stream-rate parameters set (the real default streams only on request).
    ``gcs_heartbeat``: ArduCopter routes the 1 Hz HEARTBEAT of a ground station on
    another of its ports (sysid 255) onto this link. ``max_speed_mps`` and
    ``max_accel_mps2`` limit horizontal flight (:mod:`roost_sim.kinematics`);
    ``offboard_loss_s`` is PX4's COM_OF_LOSS_T.
    """

    climb_rate_mps: float = 2.5
    descent_rate_mps: float | None = None
    takeoff_alt_m: float = 2.5
    auto_disarm_after_land_s: float | None = None
    idle_disarm_s: float = 10.0
    boot_s: float | None = None
    position_wait_s: float | None = None
    land_detect_s: float | None = None
    pilot_speed_up_mps: float = 2.5
    pilot_speed_dn_mps: float = 0.0  # 0: PILOT_SPEED_UP, as ArduCopter does
    pilot_accel_mps2: float = 2.5
    throttle: float | None = None
    battery_failsafe_land: bool | None = None
    preset_streams: bool = False
    gcs_heartbeat: bool = False
    home_lat_deg: float = 47.397742
    home_lon_deg: float = 8.545594
    home_amsl_m: float = 488.0
    max_speed_mps: float = 5.0
    max_accel_mps2: float = 3.0
    offboard_loss_s: float = 1.0

    fast_boot: bool = False

    @classmethod
    def fast(cls, **overrides: object) -> SimConfig:
        """A config that boots in well under a second (tests, benchmarks, the sandbox)."""
        values: dict[str, object] = {"fast_boot": True}
        values.update(overrides)
        return cls(**values)  # type: ignore[arg-type]

    def landing(self, stack: Stack) -> Landing:
        """Descent rate, landing detection and disarm delay in effect for ``stack``."""
        base = (_FAST_LANDING if self.fast_boot else _REALISTIC_LANDING)[Stack(stack)]
        return Landing(
            descent_mps=base.descent_mps
            if self.descent_rate_mps is None
            else self.descent_rate_mps,
            detect_s=base.detect_s if self.land_detect_s is None else self.land_detect_s,
            disarm_s=(
                base.disarm_s
                if self.auto_disarm_after_land_s is None
                else self.auto_disarm_after_land_s
            ),
        )

    def boot_times(self, stack: Stack) -> BootTimes:
        """This config's start-up timeline for ``stack``."""
        real = _REALISTIC_BOOT[Stack(stack)]
        quick = _FAST_BOOT[Stack(stack)] if self.fast_boot else real
        standby = quick.standby_s if self.boot_s is None else self.boot_s
        position = quick.position_s if self.position_wait_s is None else self.position_wait_s
        boot_scale = standby / real.standby_s
        position_scale = position / real.position_s
        if Stack(stack) is Stack.PX4:
            return replace(
                real,
                first_heartbeat_s=real.first_heartbeat_s * boot_scale,
                attitude_s=real.attitude_s * boot_scale,
                standby_s=standby,
                origin_s=real.origin_s * boot_scale,
                position_s=position,
            )
        return replace(
            real,
            attitude_s=max(standby, real.attitude_s * position_scale),
            standby_s=standby,
            origin_s=real.origin_s * position_scale,
            position_s=position,
        )


@dataclass(frozen=True)
class ModeChange:
    """The autopilot entered ``mode`` at monotonic time ``at``."""

    at: float
    mode: str


@dataclass(frozen=True)
class Touchdown:
    """The vehicle met the ground at ``at`` with ``speed_mps`` downwards in ``mode``."""

    at: float
    speed_mps: float
    mode: str


@dataclass(frozen=True)
class Sensors:
    """SYS_STATUS onboard_control_sensors_* masks."""

    present: int
    enabled: int
    health: int


@dataclass(frozen=True)
class PositionSetpoint:
    """The last position target a client sent (local NED, altitude up), at ``at``."""

    north_m: float
    east_m: float
    altitude_m: float
    yaw_rad: float | None
    at: float


@dataclass
class AutopilotModel:
    """State and rules of one flight controller; call :meth:`step` regularly."""

    stack: Stack
    config: SimConfig = field(default_factory=SimConfig)
    clock: Clock = time.monotonic
    battery: Battery | None = None
    armed: bool = field(init=False, default=False)
    custom_mode: int = field(init=False, default=0)
    altitude_m: float = field(init=False, default=0.0)
    climb_mps: float = field(init=False, default=0.0)
    landed_state: MavLandedState = field(init=False, default=MavLandedState.ON_GROUND)
    takeoff_target_m: float | None = field(init=False, default=None)
    horizontal: Horizontal = field(init=False, default_factory=Horizontal)
    setpoint: PositionSetpoint | None = field(init=False, default=None)
    hold_point: tuple[float, float] = field(init=False, default=(0.0, 0.0))
    speed_scale: float = field(init=False, default=1.0)
    sensor_faults: SensorBit = field(init=False, default=SensorBit(0))
    state_override: MavState | None = field(init=False, default=None)
    boot_at: float = field(init=False, default=0.0)
    mode_history: list[ModeChange] = field(init=False, default_factory=list)
    touchdowns: list[Touchdown] = field(init=False, default_factory=list)
    texts: list[tuple[int, str]] = field(init=False, default_factory=list)
    _last_step: float = field(init=False, default=0.0)
    _on_ground_armed_since: float | None = field(init=False, default=None)
    _landed_at: float | None = field(init=False, default=None)
    _contact_at: float | None = field(init=False, default=None)
    _battery_emergency_at: float | None = field(init=False, default=None)
    _announced: set[str] = field(init=False, default_factory=set)
    _boot_times: tuple[tuple[object, ...], BootTimes] | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        self.stack = Stack(self.stack)
        if self.battery is None:
            self.battery = Battery(clock=self.clock)
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
        self.landed_state = MavLandedState.ON_GROUND
        self.takeoff_target_m = None
        self.horizontal = Horizontal()
        self.setpoint = None
        self.hold_point = (0.0, 0.0)
        self.state_override = None
        self._on_ground_armed_since = None
        self._landed_at = None
        self._contact_at = None
        self._battery_emergency_at = None
        self._announced = set()
        self._enter_mode(custom_mode(self.stack, default_mode(self.stack)))

    def time_boot_ms(self) -> int:
        """Milliseconds since (re)boot, as in every timestamped message."""
        return int(self.uptime() * 1000)

    def uptime(self) -> float:
        """Seconds since (re)boot."""
        return self.clock() - self.boot_at

    @property
    def boot_times(self) -> BootTimes:
        """The start-up timeline in effect (worked out again only when the config's
        timing changes: it is read for every stream in every round)."""
        config = self.config
        key = (config.fast_boot, config.boot_s, config.position_wait_s)
        if self._boot_times is None or self._boot_times[0] != key:
            self._boot_times = (key, config.boot_times(self.stack))
        return self._boot_times[1]

    @property
    def booting(self) -> bool:
        """True until STANDBY: PX4 reports UNINIT, ArduCopter BOOT."""
        return self.uptime() < self.boot_times.standby_s

    @property
    def has_position(self) -> bool:
        """The estimator has a position (GLOBAL_POSITION_INT and LOCAL_POSITION_NED flow)."""
        return self.uptime() >= self.boot_times.position_s

    @property
    def has_attitude(self) -> bool:
        """The estimator has an attitude (PX4 sends ATTITUDE from then on)."""
        return self.uptime() >= self.boot_times.attitude_s

    @property
    def ready_to_arm(self) -> bool:
        """The start-up checks have passed: booted and (ArduCopter) a position estimate."""
        if self.booting:
            return False
        return self.stack is Stack.PX4 or self.has_position

    @property
    def mode(self) -> str:
        """Current mode name in the stack's spelling."""
        return mode_name(self.stack, self.custom_mode)

    @property
    def detecting_landing(self) -> bool:
        """On the ground, but the landing detector has not said so yet."""
        return self._contact_at is not None and not self.on_ground

    @property
    def on_ground(self) -> bool:
        """The vehicle rests on the ground (as its landing detector reports it)."""
        return self.landed_state is MavLandedState.ON_GROUND

    # ---- derived state ---------------------------------------------------------------

    def _counted_failures(self) -> SensorBit:
        return self.sensor_faults & ~IGNORED_SENSORS

    def _critical_failure(self) -> bool:
        return bool(self.sensor_faults & CRITICAL_SENSORS)

    def battery_reading(self) -> BatteryReading:
        """The battery as this autopilot measures it now."""
        assert self.battery is not None
        return self.battery.reading(flying=not self.on_ground)

    def battery_emergency(self) -> bool:
        """The battery is at its emergency level: the stack's failsafe is on."""
        return self.battery_reading().charge_state >= ChargeState.EMERGENCY

    def sensors(self) -> Sensors:
        """SYS_STATUS masks as this stack would report them now."""
        enabled = stack_sensors(self.stack) | self.sensor_faults
        health = enabled & ~stack_normally_unhealthy(self.stack) & ~self.sensor_faults
        if not self.battery_reading().healthy:
            health &= ~SensorBit.BATTERY
        if not self.armed and (self._counted_failures() or not self.ready_to_arm):
            health &= ~SensorBit.PREARM_CHECK  # the pre-arm checks do not pass
        return Sensors(present=int(enabled), enabled=int(enabled), health=int(health))

    def system_status(self) -> MavState:
        """The heartbeat's MAV_STATE."""
        if self.booting:
            return MavState.UNINIT if self.stack is Stack.PX4 else MavState.BOOT
        if self.state_override is not None:
            return self.state_override
        if self.armed and (self._critical_failure() or self.battery_emergency()):
            return MavState.CRITICAL
        if self.stack is Stack.ARDUPILOT:
            return MavState.ACTIVE if self.armed and not self.on_ground else MavState.STANDBY
        return MavState.ACTIVE if self.armed else MavState.STANDBY

    def estimator_flags(self) -> int:
        """PX4 ESTIMATOR_STATUS / ArduPilot EKF_STATUS_REPORT flags, as measured.

        Both stacks send 0x400 while their estimator has not started (PX4: "GPS glitch"
        bit, ArduPilot: EKF_UNINITIALIZED) -- a start-up state, not a lost attitude.
        """
        if not self.has_attitude:
            return 0x400
        if not self.has_position:
            return 0xE5 if self.stack is Stack.PX4 else 0xA7
        if self.stack is Stack.ARDUPILOT:
            return 0x33F
        return 0x3FF if self.on_ground else 0x37F  # 0x80: constant-position mode on the ground

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
            reasons = [] if force else self.arming_refusals()
            if reasons:
                if self.stack is Stack.ARDUPILOT:
                    self.texts.extend((SEVERITY_CRITICAL, f"Arm: {r}") for r in reasons)
                return self.refused_result()
            self.armed = True
            self._landed_at = None
            self._on_ground_armed_since = self.clock() if self.on_ground else None
            if self.stack is Stack.ARDUPILOT:
                self.texts.append((SEVERITY_INFO, "Arming motors"))
            return MavResult.ACCEPTED
        if not force and not self.on_ground:
            return self.refused_result()
        self._disarm()
        return MavResult.ACCEPTED

    def arming_refusals(self) -> list[str]:
        """Why arming is refused now, in ArduPilot's words (empty: it may arm)."""
        uptime, times = self.uptime(), self.boot_times
        if self.booting:
            return ["System not initialised"]
        reasons: list[str] = []
        if self.stack is Stack.ARDUPILOT and not self.has_position:
            reasons.append(
                "AHRS: waiting for home" if uptime < times.origin_s else "Need Position Estimate"
            )
        if self._counted_failures():
            reasons.append("Check sensors")
        if self.state_override not in (None, MavState.STANDBY, MavState.ACTIVE):
            reasons.append("System not healthy")
        if self.stack is Stack.ARDUPILOT and self.mode in _ARDUPILOT_UNARMABLE:
            reasons.append("Mode not armable")
        return reasons

    def _disarm(self) -> None:
        was_armed = self.armed
        self.armed = False
        self.takeoff_target_m = None
        self._on_ground_armed_since = None
        self._landed_at = None
        if was_armed and self.stack is Stack.ARDUPILOT:
            self.texts.append((SEVERITY_INFO, "Disarming motors"))

    def set_mode(self, value: int) -> int:
        """DO_SET_MODE with an already decoded ``custom_mode``."""
        if mode_name(self.stack, value).startswith("UNKNOWN"):
            return self.invalid_result()
        name = mode_name(self.stack, value)
        if name in _POSITION_MODES[self.stack] and self.sensor_faults & SensorBit.GPS:
            return self.refused_result()
        if name == "OFFBOARD" and not self._setpoints_flowing():
            return self.refused_result()  # PX4: "Switching to Offboard requires setpoints"
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
            self.hold_point = (self.horizontal.north_m, self.horizontal.east_m)
            if self.mode == "GUIDED":
                self.setpoint = None  # ArduCopter's GUIDED starts by holding

    # ---- position setpoints ----------------------------------------------------------

    def position_setpoint(
        self, north_m: float, east_m: float, altitude_m: float, yaw_rad: float | None
    ) -> None:
        """A SET_POSITION_TARGET_* with a position: flown in the stack's setpoint mode.

        PX4 keeps every setpoint (it needs the stream before OFFBOARD); ArduCopter reads
        them only in GUIDED.
        """
        values = (north_m, east_m, altitude_m)
        if not all(math.isfinite(v) for v in values):
            return
        if self.stack is Stack.ARDUPILOT and self.mode != "GUIDED":
            return
        yaw = yaw_rad if yaw_rad is not None and math.isfinite(yaw_rad) else None
        self.setpoint = PositionSetpoint(north_m, east_m, altitude_m, yaw, self.clock())

    def _setpoints_flowing(self) -> bool:
        return (
            self.setpoint is not None
            and self.clock() - self.setpoint.at <= self.config.offboard_loss_s
        )

    def _flying_setpoint(self) -> PositionSetpoint | None:
        """The setpoint the vehicle flies now, if its mode flies setpoints."""
        if self.mode != _SETPOINT_MODES[self.stack] or self.setpoint is None:
            return None
        return self.setpoint

    def _offboard_failsafe(self) -> None:
        """PX4 without setpoints for COM_OF_LOSS_T in OFFBOARD: hold where it is."""
        if self.stack is Stack.PX4 and self.mode == "OFFBOARD" and not self._setpoints_flowing():
            self.texts.append((SEVERITY_CRITICAL, "Failsafe activated: offboard signal lost"))
            self._enter_mode(custom_mode(self.stack, intent_mode(self.stack, ModeIntent.HOLD)))

    # ---- kinematics ------------------------------------------------------------------

    def step(self) -> None:
        """Advance start-up, the vertical kinematics, failsafes and auto-disarms to now."""
        now = self.clock()
        dt = max(0.0, now - self._last_step)
        self._last_step = now
        self._start_up()
        assert self.battery is not None
        self.battery.drain(flying=not self.on_ground)
        if not self.armed:
            self.takeoff_target_m = None if self.stack is Stack.ARDUPILOT else self.takeoff_target_m
            self._fall(dt, now)
            return
        self._battery_failsafe(now)
        self._offboard_failsafe()
        self._fly_horizontally(dt)
        if self.mode in _DESCEND_MODES[self.stack] and not self._returning():
            self._descend(dt, now)
        elif self.takeoff_target_m is not None:
            self._climb(dt)
        else:
            self._track(self._commanded_climb(), dt, now)
        self._auto_disarm(now)

    def _returning(self) -> bool:
        """In an RTL mode, in the air and not yet over home (flying back, then descend)."""
        return (
            self.mode in _RTL_MODES
            and not self.on_ground
            and self.horizontal.distance_to(0.0, 0.0) > _OVER_HOME_M
        )

    def _fly_horizontally(self, dt: float) -> None:
        """Towards the setpoint, home (RTL) or the hold point; nothing on the ground."""
        if self.on_ground and self.altitude_m <= 0.0:
            self.horizontal.stop()
            return
        flying = self._flying_setpoint()
        if flying is not None:
            target = (flying.north_m, flying.east_m)
            if flying.yaw_rad is not None:
                self.horizontal.yaw_rad = flying.yaw_rad
        elif self.mode in _RTL_MODES:
            target = (0.0, 0.0)
        else:
            target = self.hold_point
        self.horizontal.step(
            dt,
            target,
            max_speed_mps=self.config.max_speed_mps,
            max_accel_mps2=self.config.max_accel_mps2,
            speed_scale=self.speed_scale,
        )

    def _start_up(self) -> None:
        """ArduPilot's start-up announcements; a mode set during BOOT is overwritten."""
        if self.stack is not Stack.ARDUPILOT:
            return
        uptime, times = self.uptime(), self.boot_times
        steps = [
            (times.standby_s, "ArduPilot Ready"),
            (times.attitude_s, "EKF3 IMU0 initialised"),
            (times.origin_s, "EKF3 IMU0 origin set"),
            (times.position_s, "EKF3 IMU0 is using GPS"),
        ]
        for at, text in steps:
            if uptime >= at and text not in self._announced:
                self._announced.add(text)
                self.texts.append((SEVERITY_INFO, text))
                if text == "ArduPilot Ready" and not self.armed:
                    self._enter_mode(custom_mode(self.stack, default_mode(self.stack)))

    def _commanded_climb(self) -> float:
        """Vertical speed the current mode asks for (m/s, up positive)."""
        flying = self._flying_setpoint()
        if flying is not None:
            error = flying.altitude_m - self.altitude_m
            up = self.config.climb_rate_mps * self.speed_scale
            down = self.config.landing(self.stack).descent_mps * 2
            return max(-down, min(up, _SETPOINT_CLIMB_GAIN * error))
        if self.stack is not Stack.ARDUPILOT or self.mode not in _ARDUPILOT_STICK_MODES:
            return 0.0  # position and altitude holds (GUIDED, BRAKE, PX4 AUTO.LOITER..)
        stick = self.config.throttle if self.config.throttle is not None else 0.0
        stick = min(1.0, max(0.0, stick))
        offset = stick - 0.5
        if abs(offset) <= _THROTTLE_DEADZONE:
            return 0.0
        share = (abs(offset) - _THROTTLE_DEADZONE) / (0.5 - _THROTTLE_DEADZONE)
        if offset > 0:
            return share * self.config.pilot_speed_up_mps
        down = self.config.pilot_speed_dn_mps or self.config.pilot_speed_up_mps
        return -share * down

    def _track(self, target_mps: float, dt: float, now: float) -> None:
        """Approach ``target_mps`` at the pilot acceleration limit; meet the ground."""
        limit = self.config.pilot_accel_mps2 * dt
        self.climb_mps += max(-limit, min(limit, target_mps - self.climb_mps))
        if self.altitude_m <= 0.0 and self.climb_mps <= 0.0:
            self.climb_mps = 0.0
            self._settle(now)
            return
        self.altitude_m += self.climb_mps * dt
        if self.altitude_m <= 0.0:
            self._touch_down(now, -self.climb_mps)
            self.climb_mps = 0.0
            self._settle(now)
        else:
            self._contact_at = None
            self._on_ground_armed_since = None
            self.landed_state = MavLandedState.IN_AIR

    def _settle(self, now: float) -> None:
        """On the ground outside a land mode: the landing detector needs its time."""
        if self.on_ground:
            return
        if self._contact_at is None:
            self._contact_at = now
        if now - self._contact_at >= self.config.landing(self.stack).detect_s:
            self.landed_state = MavLandedState.ON_GROUND
            self._contact_at = None

    def _touch_down(self, now: float, speed: float) -> None:
        self.altitude_m = 0.0
        self.touchdowns.append(Touchdown(at=now, speed_mps=round(speed, 3), mode=self.mode))
        if self.stack is Stack.ARDUPILOT:
            self.texts.append((SEVERITY_INFO, f"SIM Hit ground at {speed:.6f} m/s"))

    def _fall(self, dt: float, now: float) -> None:
        self.horizontal.stop()
        if self.altitude_m <= 0.0:
            self.climb_mps = 0.0
            self.landed_state = MavLandedState.ON_GROUND
            return
        self.climb_mps = -_FALL_RATE_MPS
        self.altitude_m = max(0.0, self.altitude_m - _FALL_RATE_MPS * dt)
        if self.altitude_m <= 0.0:
            self._touch_down(now, _FALL_RATE_MPS)
            self.climb_mps = 0.0
            self.landed_state = MavLandedState.ON_GROUND
        else:
            self.landed_state = MavLandedState.IN_AIR

    def _climb(self, dt: float) -> None:
        target = self.takeoff_target_m
        assert target is not None
        self._on_ground_armed_since = None
        self._contact_at = None
        self.altitude_m = min(target, self.altitude_m + self.config.climb_rate_mps * dt)
        self.climb_mps = self.config.climb_rate_mps
        self.landed_state = MavLandedState.TAKEOFF
        if self.altitude_m >= target:
            self.takeoff_target_m = None
            self.climb_mps = 0.0
            self.landed_state = MavLandedState.IN_AIR
            if self.stack is Stack.PX4:
                self._enter_mode(custom_mode(self.stack, intent_mode(self.stack, ModeIntent.HOLD)))

    def _descend(self, dt: float, now: float) -> None:
        self.takeoff_target_m = None
        if self.on_ground:
            self.climb_mps = 0.0
            if self._landed_at is None:
                self._landed_at = now
            return
        if self.altitude_m > 0.0:
            rate = self.config.landing(self.stack).descent_mps
            self.altitude_m = max(0.0, self.altitude_m - rate * dt)
            self.climb_mps = -rate
            self.landed_state = MavLandedState.LANDING
            if self.altitude_m <= 0.0:
                self._touch_down(now, rate)
        if self.altitude_m <= 0.0:
            self.climb_mps = 0.0
            self._settle(now)  # LANDING until the landing detector is sure
            if self.on_ground:
                self._landed_at = now

    def _battery_failsafe(self, now: float) -> None:
        """PX4: hold 5 s at the emergency level, then land; ArduCopter: report only."""
        if not self.battery_emergency():
            self._battery_emergency_at = None
            return
        if self._battery_emergency_at is None:
            self._battery_emergency_at = now
        lands = self.config.battery_failsafe_land
        if lands is None:
            lands = self.stack is Stack.PX4
        land_mode = intent_mode(self.stack, ModeIntent.LAND)
        due = now - self._battery_emergency_at >= _PX4_BATTERY_HOLD_S
        if lands and due and not self.on_ground and self.mode != land_mode:
            self.land()

    def _auto_disarm(self, now: float) -> None:
        if not self.on_ground:
            self._on_ground_armed_since = None
            return
        if self._landed_at is not None:
            if now - self._landed_at >= self.config.landing(self.stack).disarm_s:
                self._disarm()
            return
        if self._on_ground_armed_since is None:
            self._on_ground_armed_since = now
        if now - self._on_ground_armed_since >= self.config.idle_disarm_s:
            self._disarm()
