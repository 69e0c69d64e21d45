"""The agents' telemetry stream as both ends read it: the local frame and its origin.

The agent (:mod:`roost_agent.telemetry`) sends metres north and east of an origin with
the latitude and longitude they came from; the dashboard puts every vehicle into its own
frame with the same projection, so a vehicle is drawn where its agent says it is, even
when agents measure from different origins.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

EARTH_RADIUS_M = 6_371_000.0
MAX_HZ = 10.0
"""The stream's highest rate: what a person can follow, and cheap for the agent."""


@dataclass(frozen=True)
class Origin:
    """Where north = east = 0 (degrees)."""

    lat: float
    lon: float

    @classmethod
    def parse(cls, text: str) -> Origin:
        """``LAT,LON`` in degrees."""
        lat_text, sep, lon_text = text.partition(",")
        try:
            lat, lon = float(lat_text), float(lon_text)
        except ValueError:
            lat = lon = math.nan
        if not sep or not (-90 <= lat <= 90 and -180 <= lon <= 180):
            raise ValueError(f"expected LAT,LON in degrees, not {text!r}")
        return cls(lat, lon)


def north_east_m(origin: Origin, lat: float, lon: float) -> tuple[float, float]:
    """Metres north and east of ``origin`` (equirectangular: exact enough over a field)."""
    k = math.pi / 180
    north = (lat - origin.lat) * k * EARTH_RADIUS_M
    east = (lon - origin.lon) * k * math.cos((lat + origin.lat) / 2 * k) * EARTH_RADIUS_M
    return north, east
