"""How far a standby autopilot drifts from the active one, with and without the hub's
mirroring: ``hub.standby_divergence_m_mirrored`` and ``hub.standby_divergence_m_unmirrored``.

Two simulated PX4 autopilots (real UDP MAVLink) behind an in-process agent serving the
hub, both airborne; a ground-station client on the hub switches the vehicle to OFFBOARD
and streams position setpoints at 20 Hz along a 20 m circle at 2 m/s for 60 s. With
mirroring the standby receives the same mode change and setpoints and flies the same
path; without it, it keeps hovering where it was. The figure is the 3D distance between
where the two autopilots put the vehicle after the 60 s (the max over the run is in the
note). In the simulator each autopilot flies its own copy of the vehicle, so the distance
is how far the standby's plan is from the active's: what it would fly if it took over.
"""

from __future__ import annotations

from bench.core import Figure
from tests.support.hubclient import fly_setpoint_circle, hub_vehicle

COMMAND = "python -m bench standby"
FLIGHT_S = 60.0


def _divergence(mirror: bool) -> list[float]:
    with hub_vehicle(["px4", "px4"], mirror=mirror) as v:
        return fly_setpoint_circle(v, FLIGHT_S)


def run() -> list[Figure]:
    figures = []
    for mirror, name in ((True, "mirrored"), (False, "unmirrored")):
        samples = _divergence(mirror)
        figures.append(
            Figure(
                f"hub.standby_divergence_m_{name}",
                round(samples[-1], 2),
                "m",
                "informational",
                COMMAND,
                f"active/standby distance after {FLIGHT_S:.0f} s of 20 Hz OFFBOARD setpoints "
                f"along a 20 m circle at 2 m/s through the hub (two PX4 sims); max over the "
                f"run {max(samples):.2f} m, {len(samples)} samples",
            )
        )
    return figures
