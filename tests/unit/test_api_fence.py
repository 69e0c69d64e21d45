"""Fence geometry validation (roost_api.fence): what a Mission's fence may be."""

from __future__ import annotations

import pytest

from roost_api.fence import (
    Area,
    LatLon,
    fence_problems,
    held_id,
    held_message,
    inside_polygon,
    polygon_problem,
)

LAT, LON = 47.397742, 8.545594
D = 0.001  # about 111 m of latitude


def poly(*offsets: tuple[float, float]) -> tuple[LatLon, ...]:
    return tuple(LatLon(LAT + a * D, LON + b * D) for a, b in offsets)


SQUARE = poly((0, 0), (0, 1), (1, 1), (1, 0))


@pytest.mark.parametrize(
    ("vertices", "problem"),
    [
        (SQUARE, None),
        (poly((0, 0), (0, 1), (1, 1), (1, 0), (0, 0)), None),  # closed GeoJSON-style ring
        (poly((0, 0), (0, 1), (1, 0.5)), None),  # a triangle
        (poly((0, 0), (0, 1), (1, 2), (1.5, 0.5), (1, -1)), None),  # concave
        (poly((0, 0), (0, 1)), "an open polygon: it needs at least three distinct vertices"),
        (poly((0, 0), (0, 1), (0, 0)), "an open polygon: it needs at least three distinct"),
        (poly((0, 0), (0, 1), (0, 2)), "an open polygon: its vertices enclose no area"),
        (poly((0, 0), (1, 1), (0, 1), (1, 0)), "the polygon intersects itself: edge 0-1"),
        (poly((0, 0), (0, 1), (0, 1), (1, 0)), "vertices 1 and 2 are the same point"),
        (
            poly((0, 0), (0, 2), (1, 2), (1, 1), (-1, 1), (-1, 0)),
            "the polygon intersects itself",
        ),
    ],
)
def test_polygon_problems(vertices: tuple[LatLon, ...], problem: str | None) -> None:
    found = polygon_problem(vertices)
    if problem is None:
        assert found is None
    else:
        assert found is not None and found.startswith(problem)


@pytest.mark.parametrize(
    ("point", "inside"),
    [((0.5, 0.5), True), ((1.5, 0.5), False), ((0.5, -0.1), False), ((0.01, 0.99), True)],
)
def test_inside_the_polygon(point: tuple[float, float], inside: bool) -> None:
    assert inside_polygon(SQUARE, poly(point)[0]) is inside


CIRCLE = Area(centre=LatLon(LAT, LON), radius_m=50)


@pytest.mark.parametrize(
    ("area", "max_alt", "flying", "positions", "problems"),
    [
        (Area(polygon=SQUARE), 50, 30, [("v1", poly((0.5, 0.5))[0])], []),
        (CIRCLE, 50, None, [("v1", LatLon(LAT, LON))], []),
        (
            CIRCLE,
            20,
            30,
            [],
            ["fence maxAltitudeM 20 m is below the Mission's flying altitude 30 m"],
        ),
        (
            CIRCLE,
            50,
            None,
            [("v1", LatLon(LAT, LON)), ("v2", LatLon(LAT + D, LON))],
            ["vehicle(s) outside the fence: v2 at 47.398742,8.545594"],
        ),
        (Area(centre=LatLon(LAT, LON), radius_m=0), 50, None, [], ["fence circle: the radius"]),
        (Area(polygon=poly((0, 0), (0, 1))), 50, None, [], ["fence polygon: an open polygon"]),
    ],
)
def test_fence_problems(
    area: Area,
    max_alt: float,
    flying: float | None,
    positions: list[tuple[str, LatLon]],
    problems: list[str],
) -> None:
    found = fence_problems(area, max_alt, flying_altitude_m=flying, positions=positions)
    assert len(found) == len(problems)
    assert all(f.startswith(p) for f, p in zip(found, problems, strict=True))


def test_the_held_message_names_the_id() -> None:
    assert held_id(held_message("0123456789ab", "circle of 50 m")) == "0123456789ab"
    assert held_id("uploading the fence") is None
