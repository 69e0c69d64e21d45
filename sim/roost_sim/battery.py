"""The battery a simulated autopilot measures: one shared by the vehicle or one per autopilot.

Why a separate object: a vehicle with redundant autopilots has either one flight battery
that powers everything (every autopilot measures the same pack) or a separate supply per
autopilot. The difference decides what a battery failsafe should do, so the simulator
models both: :func:`roost_sim.vehicle.start_vehicle_sims` hands every autopilot the same
:class:`Battery` (``battery="shared"``) or one each (``battery="per-autopilot"``).

What a battery failsafe should do in each case (for whoever acts on it, e.g. an agent):

- **Shared battery**: every autopilot reports the same falling charge. Switching to
  another autopilot does not help -- it is powered by the same empty pack and will
  raise the same failsafe moments later. The only useful action is to get the vehicle
  down: land now (or let the active autopilot's own battery failsafe land it).
- **One battery per autopilot**: the failing autopilot's supply is what is running out;
  an autopilot on a healthy battery can take over, and should then bring the vehicle
  down (hold, then land), because a vehicle that has lost a power source is degraded.

Calibration (PX4 v1.16 SIH, ``battery empty`` injected in flight): the voltage drops at
once (15.7 V -> 14.4 V), the filtered remaining charge falls to 0 % within about 4-5 s, the
SYS_STATUS battery health bit clears about 2 s after the fault, BATTERY_STATUS
charge_state turns EMERGENCY and the heartbeat CRITICAL after about 3.5 s, and PX4 holds
5 s before switching itself to AUTO.LAND. ArduCopter's default critical-battery action
(``BATT_FS_CRT_ACT`` = 0) only reports: CRITICAL in the heartbeat, no mode change.

Thread safety: a shared battery is read by several autopilots (from the tick scheduler
and control requests); one lock.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum

Clock = Callable[[], float]

FULL_VOLTAGE_V = 16.2  # 4S pack, as the PX4 SITL reports it
EMPTY_VOLTAGE_V = 14.4
LOW_FRACTION = 0.15  # PX4 BAT_LOW_THR; the health bit clears below it
CRITICAL_FRACTION = 0.07  # PX4 BAT_CRIT_THR
EMERGENCY_FRACTION = 0.05  # PX4 BAT_EMERGEN_THR
FLIGHT_DRAIN_PER_S = 1.0 / 1200.0  # a 20-minute pack at hover current
FAULT_DRAIN_S = 3.7  # a failed pack reads empty this long after the fault (EMERGENCY at 3.5 s)


class ChargeState(IntEnum):
    """MAV_BATTERY_CHARGE_STATE."""

    UNDEFINED = 0
    OK = 1
    LOW = 2
    CRITICAL = 3
    EMERGENCY = 4
    FAILED = 5


@dataclass(frozen=True)
class BatteryReading:
    """What an autopilot measures at one instant."""

    voltage_mv: int
    remaining_percent: int
    current_ca: int
    charge_state: ChargeState
    healthy: bool


class Battery:
    """A flight battery: drains while the vehicle flies, faster after an injected fault."""

    def __init__(self, *, clock: Clock = time.monotonic, fraction: float = 1.0) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._fraction = fraction
        self._fault_at: float | None = None
        self._fault_start_fraction = fraction
        self._last = clock()

    def drain(self, *, flying: bool) -> None:
        """Advance the charge to now (called by each autopilot's step)."""
        with self._lock:
            now = self._clock()
            dt = max(0.0, now - self._last)
            self._last = now
            if self._fault_at is not None:
                spent = (now - self._fault_at) / FAULT_DRAIN_S
                self._fraction = max(0.0, self._fault_start_fraction * (1.0 - spent))
            elif flying:
                self._fraction = max(0.0, self._fraction - FLIGHT_DRAIN_PER_S * dt)

    def fail(self) -> None:
        """A pack failure (a dead cell, a connector): the charge reads empty within seconds."""
        with self._lock:
            if self._fault_at is None:
                self._fault_at = self._clock()
                self._fault_start_fraction = self._fraction

    def replace(self) -> None:
        """A fresh pack: full and without a fault (``clear battery``)."""
        with self._lock:
            self._fault_at = None
            self._fraction = 1.0
            self._last = self._clock()

    @property
    def failed(self) -> bool:
        """A fault was injected and not cleared."""
        with self._lock:
            return self._fault_at is not None

    def reading(self, *, flying: bool) -> BatteryReading:
        """Voltage, charge and state as the autopilot measures them now."""
        with self._lock:
            fraction, failed = self._fraction, self._fault_at is not None
        voltage = EMPTY_VOLTAGE_V if failed else (
            EMPTY_VOLTAGE_V + (FULL_VOLTAGE_V - EMPTY_VOLTAGE_V) * fraction
        )  # fmt: skip
        if fraction <= EMERGENCY_FRACTION:
            state = ChargeState.EMERGENCY
        elif fraction <= CRITICAL_FRACTION:
            state = ChargeState.CRITICAL
        elif fraction <= LOW_FRACTION:
            state = ChargeState.LOW
        else:
            state = ChargeState.OK
        return BatteryReading(
            voltage_mv=round(voltage * 1000),
            remaining_percent=round(fraction * 100),
            current_ca=1500 if flying else 50,
            charge_state=state,
            healthy=fraction > LOW_FRACTION,
        )
