"""A Mission's geofence on a vehicle: ``fence.upload_confirm_s``.

Two simulated PX4 autopilots (real UDP MAVLink: the fence part of the mission protocol
and PX4's fence parameters) behind an in-process agent, on the ground. A 20-vertex
inclusion polygon (a circle of about 100 m round home) with a 40 m altitude limit is
put into the agent's spec as the operator writes a Mission's fence; the figure is the
time from ``apply_spec`` until both autopilots report ``FenceInSync`` True naming the
fence: on each, the fence it held read (for the restore), every vertex uploaded
(MISSION_COUNT, 20 MISSION_REQUEST_INT / MISSION_ITEM_INT, MISSION_ACK), read back and
compared, and GF_ACTION and GF_MAX_VER_DIST written and confirmed. Median of
:data:`TRIALS` (each trial a new fence id, so the upload, read-back and parameters run
again; only the first also reads the fence held before, which the agent keeps for the
restore).
"""

from __future__ import annotations

import math
import statistics
import time

from bench.core import Figure
from roost_api.autopilot import AssignedFence, Fence, FencePoint
from roost_api.fence import FenceAction, held_id
from roost_sim.model import SimConfig
from tests.support.hubclient import HubVehicle, hub_vehicle

COMMAND = "python -m bench fence"
TRIALS = 5
VERTICES = 20
POLL_S = 0.005


def polygon(vertices: int = VERTICES, radius_deg: float = 0.0009) -> list[FencePoint]:
    """A regular polygon round the simulator's home."""
    home = SimConfig()
    return [
        FencePoint(
            latitude=home.home_lat_deg + radius_deg * math.cos(2 * math.pi * k / vertices),
            longitude=home.home_lon_deg + radius_deg * math.sin(2 * math.pi * k / vertices),
        )
        for k in range(vertices)
    ]


def held_everywhere(v: HubVehicle, fid: str) -> bool:
    held = [
        c.status == "True" and held_id(c.message) == fid
        for h in v.agent.status().autopilots
        for c in h.conditions
        if c.type == "FenceInSync"
    ]
    return len(held) == len(v.sims) and all(held)


def upload_trials() -> list[float]:
    fence = Fence(polygon=polygon(), max_altitude_m=40, action=FenceAction.RETURN)
    samples = []
    with hub_vehicle(["px4", "px4"]) as v:
        for trial in range(TRIALS):
            fid = f"bench{trial}"
            assigned = AssignedFence(mission="bench/fence", id=fid, fence=fence)
            start = time.monotonic()
            assert v.agent.apply_spec(v.spec_with(fence=assigned)) is None
            while not held_everywhere(v, fid):
                if time.monotonic() - start > 60:
                    raise TimeoutError("the fence was not confirmed")
                time.sleep(POLL_S)
            samples.append(time.monotonic() - start)
        assert all(len(s.fence.items) == VERTICES for s in v.sims)
    return samples


def run() -> list[Figure]:
    samples = upload_trials()
    return [
        Figure(
            "fence.upload_confirm_s",
            round(statistics.median(samples), 3),
            "s",
            "informational",
            COMMAND,
            f"median of {TRIALS}: a {VERTICES}-vertex inclusion polygon and a 40 m altitude "
            "limit uploaded (mission protocol, fence type), read back and compared, and "
            "GF_ACTION/GF_MAX_VER_DIST written and confirmed, on two simulated PX4 "
            "autopilots over UDP: apply_spec to FenceInSync True on both; all (the first "
            "also reads the fence held before) "
            f"{[round(s, 3) for s in samples]}",
        )
    ]
