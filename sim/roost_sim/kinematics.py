"""Horizontal flight of a simulated multicopter: position, velocity and heading in a local
NED frame (metres from home), pure and stepped with an explicit ``dt``.

Why a point mass with speed and acceleration limits: what Roost's users test against the
simulator — timed waypoints, position setpoint streams, holds, return to home, delays
when a vehicle is slowed — depends on *when* the vehicle gets where, which a vehicle
that accelerates at a bounded rate up to a bounded speed and brakes in time reproduces;
attitude dynamics would add nothing those tests can see. The vertical axis stays in
:mod:`roost_sim.model` (take-off, landing, the pilot's stick, falling when disarmed).

The controller flies straight at its target: the wanted velocity points at it with the
speed that still lets the vehicle stop on it (``sqrt(2·a·d)``, capped by the speed
limit), and the velocity approaches the wanted one at most ``accel`` per second. A
``speed_scale`` below 1 is the ``lag`` fault: wind or a weak battery make the vehicle
slower than planned.

Limits by default follow the stacks' position controllers: PX4 ``MPC_XY_CRUISE`` 5 m/s
and ``MPC_ACC_HOR`` 3 m/s²; ArduCopter ``WPNAV_SPEED`` 10 m/s and ``WPNAV_ACCEL``
2.5 m/s² (:class:`roost_sim.model.SimConfig` takes one pair for both stacks).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

EARTH_RADIUS_M = 6_378_137.0
"""WGS-84 equatorial radius, for the flat-earth conversion between NED and lat/lon."""

ARRIVED_M = 0.05
"""Closer than this to the target with no speed left counts as on it."""

MAX_STEP_S = 0.02
"""Longest stretch integrated in one go. The simulator steps on its own clock, so a busy
machine can hand :meth:`Horizontal.step` half a second at once; flown as one step, the
braking curve near the target overshoots and rings (a discrete controller whose gain is
too high for its period). Cutting ``dt`` into slices no longer than this makes where the
vehicle ends up independent of how often it was stepped."""


@dataclass
class Horizontal:
    """Where the vehicle is over the ground and how it moves (NED: north, east)."""

    north_m: float = 0.0
    east_m: float = 0.0
    vn_mps: float = 0.0
    ve_mps: float = 0.0
    yaw_rad: float = math.pi / 2  # heading, clockwise from north (east at rest)

    @property
    def speed_mps(self) -> float:
        return math.hypot(self.vn_mps, self.ve_mps)

    def distance_to(self, north_m: float, east_m: float) -> float:
        return math.hypot(north_m - self.north_m, east_m - self.east_m)

    def stop(self) -> None:
        """On the ground (or falling): no horizontal motion."""
        self.vn_mps = self.ve_mps = 0.0

    def step(
        self,
        dt: float,
        target: tuple[float, float],
        *,
        max_speed_mps: float,
        max_accel_mps2: float,
        speed_scale: float = 1.0,
    ) -> None:
        """Fly towards ``target`` (north, east) for ``dt`` seconds within the limits."""
        if dt <= 0.0:
            return
        slices = math.ceil(dt / MAX_STEP_S)
        for _ in range(slices):
            self._slice(dt / slices, target, max_speed_mps, max_accel_mps2, speed_scale)

    def _slice(
        self,
        dt: float,
        target: tuple[float, float],
        max_speed_mps: float,
        max_accel_mps2: float,
        speed_scale: float,
    ) -> None:
        """One integration step, short enough for the braking curve to be flown exactly."""
        speed_limit = max(0.0, max_speed_mps * speed_scale)
        accel = max_accel_mps2 * max(speed_scale, 0.1)
        dn, de = target[0] - self.north_m, target[1] - self.east_m
        distance = math.hypot(dn, de)
        if distance < ARRIVED_M and self.speed_mps < accel * dt:
            self.north_m, self.east_m = target
            self.stop()
            return
        wanted = min(speed_limit, math.sqrt(2.0 * accel * distance))
        want_n = dn / distance * wanted if distance > 0 else 0.0
        want_e = de / distance * wanted if distance > 0 else 0.0
        change_n, change_e = want_n - self.vn_mps, want_e - self.ve_mps
        change = math.hypot(change_n, change_e)
        most = accel * dt
        if change > most:
            change_n, change_e = change_n / change * most, change_e / change * most
        self.vn_mps += change_n
        self.ve_mps += change_e
        self.north_m += self.vn_mps * dt
        self.east_m += self.ve_mps * dt


def ned_from_global(
    lat_deg: float, lon_deg: float, home_lat_deg: float, home_lon_deg: float
) -> tuple[float, float]:
    """(north, east) in metres of a latitude/longitude from home (flat earth, fine for
    the few kilometres a lab flies)."""
    north = math.radians(lat_deg - home_lat_deg) * EARTH_RADIUS_M
    east = (
        math.radians(lon_deg - home_lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(home_lat_deg))
    )
    return north, east


def global_from_ned(
    north_m: float, east_m: float, home_lat_deg: float, home_lon_deg: float
) -> tuple[float, float]:
    """The latitude/longitude (degrees) ``north_m``/``east_m`` from home."""
    lat = home_lat_deg + math.degrees(north_m / EARTH_RADIUS_M)
    lon = home_lon_deg + math.degrees(
        east_m / (EARTH_RADIUS_M * math.cos(math.radians(home_lat_deg)))
    )
    return lat, lon
