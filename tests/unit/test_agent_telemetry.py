"""The agent's telemetry samples and the stream's frame, without sockets.

The sampler reads an agent through the small protocol the stream needs; here that is a
plain object (the integration test reads a real ``roost-agent`` over a WebSocket).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime

import pytest

from roost_agent.health import Fix
from roost_agent.telemetry import Sampler, requested_hz
from roost_api.autopilot import FailoverRecord, FailoverTrigger
from roost_api.meta import HealthLevel
from roost_api.telemetry import MAX_HZ, Origin, north_east_m

HOME = Origin(47.397742, 8.545594)


@dataclass(frozen=True)
class Level:
    level: HealthLevel


@dataclass
class Link:
    fix_now: Fix | None = None

    def fix(self) -> Fix | None:
        return self.fix_now


@dataclass
class Vehicle:
    active: str = "fc1"
    latched: bool = False
    vehicle_name: str = "v1"
    last_failover: FailoverRecord | None = None
    links: Mapping[str, Link] = field(default_factory=lambda: {"fc1": Link(), "fc2": Link()})

    def assessments(self) -> dict[str, Level]:
        return {"fc1": Level(HealthLevel.OK), "fc2": Level(HealthLevel.STALE)}


def test_no_position_before_the_first_fix() -> None:
    sample = Sampler(Vehicle(), wall_clock=lambda: 1000.0).sample()
    assert sample["position"] is None and sample["origin"] is None
    assert sample["health"] == {"fc1": "OK", "fc2": "STALE"}
    assert (sample["vehicle"], sample["active"], sample["time"], sample["seq"]) == (
        "v1",
        "fc1",
        1000.0,
        1,
    )


def test_the_first_fix_is_the_origin_unless_one_is_given() -> None:
    vehicle = Vehicle()
    vehicle.links["fc1"].fix_now = Fix(HOME.lat, HOME.lon, 3.0, 270.0, at=10.0)
    sampler = Sampler(vehicle, clock=lambda: 10.5)
    first = sampler.sample()
    assert first["origin"] == {"lat": HOME.lat, "lon": HOME.lon}
    assert first["position"]["north"] == 0 and first["position"]["down"] == -3.0
    assert first["position"]["heading"] == 270.0 and first["position"]["age"] == 0.5
    east_lon = HOME.lon + 0.0001
    vehicle.links["fc1"].fix_now = Fix(HOME.lat, east_lon, 3.0, None, at=10.4)
    moved = sampler.sample()
    assert moved["position"]["east"] == pytest.approx(
        north_east_m(HOME, HOME.lat, east_lon)[1], abs=1e-3
    )
    assert moved["position"]["heading"] is None and moved["seq"] == 2

    given = Origin(HOME.lat - 0.001, HOME.lon)
    north = Sampler(vehicle, given).sample()["position"]["north"]
    assert north == pytest.approx(111.2, abs=0.2)


def test_the_position_is_the_active_autopilots() -> None:
    vehicle = Vehicle(active="fc2")
    vehicle.links["fc1"].fix_now = Fix(HOME.lat, HOME.lon, 3.0, 0.0, at=1.0)
    assert Sampler(vehicle).sample()["position"] is None


def test_the_last_failover_is_dumped_once_per_failover() -> None:
    vehicle = Vehicle(active="fc2", latched=True)
    sampler = Sampler(vehicle)
    vehicle.last_failover = FailoverRecord(
        time=datetime(2026, 5, 1, tzinfo=UTC),
        from_autopilot="fc1",
        to_autopilot="fc2",
        reason="fc1 silent",
        trigger=FailoverTrigger.AUTOMATIC,
        latency_ms=0.4,
    )
    first, second = sampler.sample()["lastFailover"], sampler.sample()["lastFailover"]
    assert first is second  # the same dict: not dumped again
    assert (first["from"], first["to"], first["trigger"]) == ("fc1", "fc2", "Automatic")


@pytest.mark.parametrize(
    ("path", "hz"),
    [("/", MAX_HZ), ("/?hz=2", 2.0), ("/?hz=50", MAX_HZ), ("/?hz=0", MAX_HZ), ("/?hz=x", MAX_HZ)],
)
def test_a_client_may_ask_for_a_lower_rate_only(path: str, hz: float) -> None:
    assert requested_hz(path) == hz


@pytest.mark.parametrize("text", ["47.3", "91,8", "a,b", "47.3,181"])
def test_an_origin_is_latitude_comma_longitude(text: str) -> None:
    with pytest.raises(ValueError, match="LAT,LON"):
        Origin.parse(text)
    assert Origin.parse("47.5,-8.25") == Origin(47.5, -8.25)
