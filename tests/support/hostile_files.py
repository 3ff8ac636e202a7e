"""Map and route files built to break limits: rings of n vertices, a boundary of them, a KML of
n coordinates and a QGroundControl plan of n items."""

from __future__ import annotations

import json
import math
from typing import Any


def ring(n: int, lat: float = 37.94, lon: float = 23.65, radius: float = 0.001) -> list[Any]:
    points = [
        [round(lon + radius * math.cos(2 * math.pi * i / n), 6),
         round(lat + radius * math.sin(2 * math.pi * i / n), 6)]
        for i in range(n)
    ]  # fmt: skip
    return [*points, points[0]]


def boundary_map(*rings: list[Any]) -> dict[str, Any]:
    return {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {"role": "boundary"},
                "geometry": {"type": "Polygon", "coordinates": list(rings)},
            }
        ],
    }


def kml(coordinates: int) -> str:
    text = " ".join(f"23.{i:06d},37.9,0" for i in range(coordinates))
    return (
        '<?xml version="1.0"?><kml xmlns="http://www.opengis.net/kml/2.2"><Document>'
        f"<Placemark><Polygon><outerBoundaryIs><LinearRing><coordinates>{text}</coordinates>"
        "</LinearRing></outerBoundaryIs></Polygon></Placemark></Document></kml>"
    )


def plan(items: int) -> str:
    mission = [
        {"type": "SimpleItem", "command": 16, "frame": 3,
         "params": [0, 0, 0, None, 37.94 + i * 1e-6, 23.65, 0]}
        for i in range(items)
    ]  # fmt: skip
    return json.dumps(
        {
            "fileType": "Plan",
            "version": 1,
            "groundStation": "QGroundControl",
            "mission": {"version": 2, "items": mission, "plannedHomePosition": [37.94, 23.65, 0]},
            "geoFence": {"version": 2, "polygons": [], "circles": []},
            "rallyPoints": {"version": 2, "points": []},
        },
        separators=(",", ":"),
    )
