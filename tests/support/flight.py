"""Getting simulated autopilots airborne, for the failover tests and the benchmarks."""

from __future__ import annotations

from collections.abc import Sequence

from roost_sim import SimulatedAutopilot

BOOT_TIMEOUT_S = 5.0
TAKEOFF_TIMEOUT_S = 15.0
AIRBORNE_M = 2.0


def take_off(sims: Sequence[SimulatedAutopilot]) -> None:
    """Wait for every sim to finish booting, order all to fly, wait until all are airborne
    (in the air and above :data:`AIRBORNE_M`)."""
    for sim in sims:
        sim.wait_until(lambda s: s.system_status != "BOOT", timeout=BOOT_TIMEOUT_S)
    for sim in sims:
        sim.fly()
    for sim in sims:
        sim.wait_until(
            lambda s: s.landed_state == "InAir" and s.altitude_m > AIRBORNE_M,
            timeout=TAKEOFF_TIMEOUT_S,
        )
