"""The simulated platform's demo map and route, around where the simulated vehicle starts.

A 60 m x 50 m field (the start 10 m in from its south-west corner) with a 10 m x 10 m shed
in the middle, named points at the four corners of a 40 m x 30 m loop around the shed, and
that loop as the route. ``--sim`` loads them when no map or route is stored.
"""

from __future__ import annotations

import math
from typing import Any

LOOP = {"sw": (0.0, 0.0), "se": (40.0, 0.0), "ne": (40.0, 30.0), "nw": (0.0, 30.0)}
"""Corners of the demo loop, metres east and north of the start."""


def offset(latitude: float, longitude: float, east: float, north: float) -> tuple[float, float]:
    """A position ``east``/``north`` metres from another (small distances)."""
    return (
        latitude + north / 110_574.0,
        longitude + east / (111_320.0 * math.cos(math.radians(latitude))),
    )


def demo_map(latitude: float, longitude: float) -> dict[str, Any]:
    """The demo map as GeoJSON."""

    def ring(x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
        corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]
        points = (offset(latitude, longitude, x, y) for x, y in corners)
        return [[lon, lat] for lat, lon in points]

    def point(name: str, east: float, north: float) -> dict[str, Any]:
        lat, lon = offset(latitude, longitude, east, north)
        return {
            "type": "Feature",
            "properties": {"name": name},
            "geometry": {"type": "Point", "coordinates": [lon, lat]},
        }

    return {
        "type": "FeatureCollection",
        "name": "demo field",
        "features": [
            {
                "type": "Feature",
                "properties": {"role": "boundary"},
                "geometry": {"type": "Polygon", "coordinates": [ring(-10, -10, 50, 40)]},
            },
            {
                "type": "Feature",
                "id": "shed",
                "properties": {"role": "keepout"},
                "geometry": {"type": "Polygon", "coordinates": [ring(15, 10, 25, 20)]},
            },
            *(point(name, east, north) for name, (east, north) in LOOP.items()),
        ],
    }


def demo_route() -> list[str]:
    """The demo route: the loop's named points, closed."""
    return [*LOOP, "sw"]
