"""A Mission's geofence without pydantic: the breach actions, the geometry checks and the
form in which an autopilot's condition names the fence it holds, shared by the operator
(admission of a Mission's fence, preflight) and the node agent (which uploads it and must
import neither pydantic, see :mod:`roost_api.core`, nor hashlib: the fence's content id
is computed by the operator, ``roost_operator.missions.fence``).

The geometry is checked on a local flat-earth projection around the fence's first point
(metres north and east). A Mission's flying area spans at most a few kilometres, where
the projection's error (well under a metre) is far below any fence margin; the
autopilots themselves test the fence on their own projections.

What is refused and why:

- fewer than three distinct vertices, or a polygon of (nearly) zero area: an open
  polygon encloses nothing, and PX4 and ArduPilot reject or ignore it;
- two edges that cross (self-intersecting): "inside" is ambiguous and the stacks decide
  it differently (ArduPilot rejects such a polygon on upload, PX4 accepts it);
- a vehicle position outside the area: the vehicle would breach on arming;
- a maximum altitude below the Mission's flying altitude: the Mission could not fly as
  declared without a breach.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

EARTH_RADIUS_M = 6_371_000.0
MIN_AREA_M2 = 1.0
"""A polygon enclosing less than this is taken as open (its vertices are on a line)."""
MAX_VERTICES = 100
"""Polygon vertices a fence may have (PX4 stores 256 fence items, ArduPilot's default
storage about 80 on a small board; 100 fits a real board's EEPROM budget and CEL's)."""


class FenceAction(StrEnum):
    """What the autopilot does on a breach (mapped to GF_ACTION / FENCE_ACTION)."""

    HOLD = "Hold"
    RETURN = "Return"
    LAND = "Land"
    REPORT = "Report"


@dataclass(frozen=True)
class LatLon:
    """A point in degrees (WGS84)."""

    latitude: float
    longitude: float


def local_m(origin: LatLon, point: LatLon) -> tuple[float, float]:
    """``point`` as metres (north, east) of ``origin`` on a local flat-earth projection."""
    north = math.radians(point.latitude - origin.latitude) * EARTH_RADIUS_M
    east = (
        math.radians(point.longitude - origin.longitude)
        * EARTH_RADIUS_M
        * math.cos(math.radians(origin.latitude))
    )
    return north, east


def _cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _segments_cross(
    p1: tuple[float, float],
    p2: tuple[float, float],
    q1: tuple[float, float],
    q2: tuple[float, float],
) -> bool:
    """Whether segments p1p2 and q1q2 share a point (touching counts)."""
    d1, d2 = _cross(q1, q2, p1), _cross(q1, q2, p2)
    d3, d4 = _cross(p1, p2, q1), _cross(p1, p2, q2)
    if ((d1 > 0 > d2) or (d1 < 0 < d2)) and ((d3 > 0 > d4) or (d3 < 0 < d4)):
        return True

    def on(a: tuple[float, float], b: tuple[float, float], c: tuple[float, float]) -> bool:
        return min(a[0], b[0]) <= c[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= c[1] <= max(
            a[1], b[1]
        )

    return (
        (d1 == 0 and on(q1, q2, p1))
        or (d2 == 0 and on(q1, q2, p2))
        or (d3 == 0 and on(p1, p2, q1))
        or (d4 == 0 and on(p1, p2, q2))
    )


def polygon_problem(vertices: Sequence[LatLon]) -> str | None:
    """Why ``vertices`` is not a usable inclusion polygon (None: it is). The polygon is
    closed implicitly (last vertex to first); a repeated first vertex at the end is
    allowed, as GeoJSON writes a ring."""
    points = list(vertices)
    if len(points) > 1 and points[0] == points[-1]:
        points = points[:-1]
    if len({(p.latitude, p.longitude) for p in points}) < 3:
        return "an open polygon: it needs at least three distinct vertices"
    origin = points[0]
    xy = [local_m(origin, p) for p in points]
    n = len(xy)
    for i in range(n):
        if xy[i] == xy[(i + 1) % n]:
            return f"vertices {i} and {(i + 1) % n} are the same point"
    for i in range(n):
        for j in range(i + 1, n):
            if j == i + 1 or (i == 0 and j == n - 1):
                continue  # neighbouring edges share a vertex
            if _segments_cross(xy[i], xy[(i + 1) % n], xy[j], xy[(j + 1) % n]):
                return (
                    f"the polygon intersects itself: edge {i}-{(i + 1) % n} crosses "
                    f"edge {j}-{(j + 1) % n}"
                )
    # After the crossing test: a figure-of-eight's two lobes cancel out in the sum.
    area = abs(sum(_cross((0.0, 0.0), xy[i], xy[(i + 1) % n]) for i in range(n))) / 2
    if area < MIN_AREA_M2:
        return "an open polygon: its vertices enclose no area (they lie on one line)"
    return None


def inside_polygon(vertices: Sequence[LatLon], point: LatLon) -> bool:
    """Whether ``point`` is inside the polygon (ray casting on the local projection)."""
    origin = vertices[0]
    xy = [local_m(origin, p) for p in vertices]
    px, py = local_m(origin, point)
    inside = False
    n = len(xy)
    for i in range(n):
        (x1, y1), (x2, y2) = xy[i], xy[(i + 1) % n]
        if (y1 > py) != (y2 > py) and px < x1 + (py - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
    return inside


def inside_circle(centre: LatLon, radius_m: float, point: LatLon) -> bool:
    """Whether ``point`` is within ``radius_m`` of ``centre``."""
    north, east = local_m(centre, point)
    return math.hypot(north, east) <= radius_m


@dataclass(frozen=True)
class Area:
    """A fence's horizontal area: an inclusion polygon or an inclusion circle."""

    polygon: tuple[LatLon, ...] = ()
    centre: LatLon | None = None
    radius_m: float = 0.0

    def contains(self, point: LatLon) -> bool:
        if self.centre is not None:
            return inside_circle(self.centre, self.radius_m, point)
        return inside_polygon(self.polygon, point)


def fence_problems(
    area: Area,
    max_altitude_m: float,
    *,
    flying_altitude_m: float | None = None,
    positions: Sequence[tuple[str, LatLon]] = (),
) -> list[str]:
    """Every reason the fence cannot be used, in a fixed order (empty: it can).
    ``positions``: the claimed vehicles' known positions, by vehicle name."""
    problems: list[str] = []
    if area.centre is None:
        problem = polygon_problem(area.polygon)
        if problem is not None:
            return [f"fence polygon: {problem}"]
    elif area.radius_m <= 0:
        return ["fence circle: the radius must be positive"]
    if max_altitude_m <= 0:
        problems.append("fence maxAltitudeM must be positive")
    if flying_altitude_m is not None and max_altitude_m < flying_altitude_m:
        problems.append(
            f"fence maxAltitudeM {max_altitude_m:g} m is below the Mission's flying "
            f"altitude {flying_altitude_m:g} m"
        )
    outside = [name for name, at in positions if not area.contains(at)]
    if outside:
        problems.append(
            "vehicle(s) outside the fence: "
            + ", ".join(
                f"{name} at {p.latitude:.6f},{p.longitude:.6f}"
                for name, p in positions
                if name in outside
            )
        )
    return problems


HELD_PREFIX = "holds fence "


def held_message(fid: str, detail: str) -> str:
    """The FenceInSync message of an autopilot that holds fence ``fid``."""
    return f"{HELD_PREFIX}{fid}: {detail}"


def held_id(message: str) -> str | None:
    """The fence id a FenceInSync message says is held (None: it says none is)."""
    if not message.startswith(HELD_PREFIX):
        return None
    return message[len(HELD_PREFIX) :].split(":", 1)[0]


__all__ = [
    "Area",
    "FenceAction",
    "LatLon",
    "fence_problems",
    "held_id",
    "held_message",
    "inside_circle",
    "inside_polygon",
    "local_m",
    "polygon_problem",
]
