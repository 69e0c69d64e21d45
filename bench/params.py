"""Declared autopilot parameters: ``params.apply_100_s`` and ``params.drift_detect_s``.

Two simulated PX4 autopilots (real UDP MAVLink, the parameter protocol with PX4's names,
types and bytewise integers) behind an in-process agent, on the ground.

- ``params.apply_100_s``: 100 parameters (RC calibration of 18 channels, the channel
  map, takeoff, landing and geofence parameters; FLOAT and INT32), every one different
  from what the autopilots hold, are declared by a new spec; the figure is the time from
  ``apply_spec`` until both autopilots report ``ParametersInSync`` True: each parameter
  read, written, and its echo read back as declared, on both.
- ``params.drift_detect_s``: with 10 declared parameters in sync, one is changed on an
  autopilot the way a ground station on another radio would (the agent's link gets no
  echo: it must read it back); the figure is the slowest of 10 trials from the change
  to the agent reporting ``Drifted``.
"""

from __future__ import annotations

import statistics
import time

from bench.core import Figure
from roost_api.autopilot import ParametersSpec, ParameterValue
from tests.support.hubclient import HubVehicle, hub_vehicle

COMMAND = "python -m bench params"
TRIALS = 10
POLL_S = 0.005


def hundred() -> dict[str, float]:
    """100 real PX4 parameters, each set away from its default."""
    values: dict[str, float] = {}
    for n in range(1, 19):
        values |= {
            f"RC{n}_MIN": 990 + n,
            f"RC{n}_TRIM": 1490 + n,
            f"RC{n}_MAX": 2010 - n,
            f"RC{n}_REV": -1,
            f"RC{n}_DZ": 5 + n / 10,
        }
    values |= {"RC_CHAN_CNT": 8, "RC_MAP_ROLL": 1, "RC_MAP_PITCH": 2, "RC_MAP_YAW": 4}
    values |= {"RC_MAP_THROTTLE": 3, "MIS_TAKEOFF_ALT": 6.2, "MPC_LAND_SPEED": 0.9}
    values |= {"GF_ACTION": 3, "GF_MAX_HOR_DIST": 150, "GF_MAX_VER_DIST": 60}
    assert len(values) == 100, len(values)
    return values


def spec_of(values: dict[str, float]) -> ParametersSpec:
    return ParametersSpec(px4=[ParameterValue(name=n, value=v) for n, v in values.items()])


def reasons(v: HubVehicle) -> list[str]:
    return [
        c.reason
        for h in v.agent.status().autopilots
        for c in h.conditions
        if c.type == "ParametersInSync"
    ]


def wait_for(predicate: object, timeout: float) -> float:
    """Seconds until ``predicate()`` holds (polled every POLL_S)."""
    start = time.monotonic()
    while not predicate():  # type: ignore[operator]
        if time.monotonic() - start > timeout:
            raise TimeoutError("the condition did not come")
        time.sleep(POLL_S)
    return time.monotonic() - start


def apply_100() -> float:
    with hub_vehicle(["px4", "px4"]) as v:
        start = time.monotonic()
        assert v.agent.apply_spec(v.spec_with(parameters=spec_of(hundred()))) is None
        wait_for(lambda: reasons(v) == ["InSync", "InSync"], 60)
        return time.monotonic() - start


def drift_trials() -> list[float]:
    ten = dict(list(hundred().items())[:10])
    samples = []
    with hub_vehicle(["px4", "px4"], parameters=spec_of(ten)) as v:
        wait_for(lambda: reasons(v) == ["InSync", "InSync"], 30)
        names = list(ten)
        for trial in range(TRIALS):
            name = names[trial % len(names)]
            sim = v.sims[trial % 2]
            sim.params.set(name, ten[name] + 1)
            samples.append(wait_for(lambda: "Drifted" in reasons(v), 30))
            sim.params.set(name, ten[name])
            wait_for(lambda: reasons(v) == ["InSync", "InSync"], 30)
    return samples


def run() -> list[Figure]:
    applied = apply_100()
    drift = drift_trials()
    return [
        Figure(
            "params.apply_100_s",
            round(applied, 2),
            "s",
            "informational",
            COMMAND,
            "100 declared PX4 parameters (FLOAT and INT32, all changed) read, written and "
            "confirmed by their echoes on two simulated PX4 autopilots over UDP: apply_spec "
            "to ParametersInSync True on both (16 requests in flight per autopilot)",
        ),
        Figure(
            "params.drift_detect_s",
            round(max(drift), 2),
            "s",
            "<= 2",
            COMMAND,
            f"slowest of {TRIALS}: a declared parameter changed on an autopilot by another "
            f"link (no echo to the agent) to the Drifted condition, 10 declared parameters "
            f"read back once a second; median {statistics.median(drift):.2f} s. With N "
            f"declared the read-back cycle is max(1, N/20) s",
        ),
    ]
