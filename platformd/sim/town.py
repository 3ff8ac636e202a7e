"""A generated town map with the statistics of an OpenStreetMap building export.

Real maps are what users have: an OSM export of a town's buildings, hundreds to thousands of
them. This builds one anywhere on Earth, reproducibly (``seed``), for tests and ``make bench``:

- blocks of 60-140 m between 12 m streets, on a street grid turned by a random angle;
- buildings along each block's edges, 3-6 m back from the street, 1.5-8 m apart; footprints
  log-normal around 110 m² (OSM's European median is ~100-150 m²), 5 positions for a plain
  rectangle (most), 7 for an L-shaped one (one in four), coordinates rounded to 1e-7° as OSM
  stores them;
- ``properties`` as an export has them (``building``, an ``@id``) and names that repeat: most
  buildings have none, many have the same few (``" "``, ``"Garage"``), so names never make ids;
- an irregular boundary (~40 vertices) around the blocks.
"""

from __future__ import annotations

import math
import random
from typing import Any

from brasidas.autonomy.geo import LocalFrame

STREET_M = 12.0
NAMES = (" ", "Garage", "Shed", "Church", "School")


def town_map(
    latitude: float, longitude: float, buildings: int = 1000, seed: int = 1
) -> dict[str, Any]:
    """A map (GeoJSON with roles) of ``buildings`` keep-outs centred on a position."""
    rng = random.Random(seed)
    frame = LocalFrame(latitude, longitude)
    turn = rng.uniform(0.0, math.pi / 2)
    footprints: list[list[tuple[float, float]]] = []
    side = 200.0
    while len(footprints) < buildings:
        footprints = _buildings(rng, side, buildings)
        side *= 1.25
    extent = max(max(abs(x), abs(y)) for ring in footprints for x, y in ring) + 25.0

    def geo(points: list[tuple[float, float]]) -> list[list[float]]:
        out = []
        for x, y in points:
            rx = x * math.cos(turn) - y * math.sin(turn)
            ry = x * math.sin(turn) + y * math.cos(turn)
            lat, lon = frame.to_geo(rx, ry)
            out.append([round(lon, 7), round(lat, 7)])
        return out

    boundary = _boundary(rng, extent * math.sqrt(2.0))
    features: list[dict[str, Any]] = [
        {
            "type": "Feature",
            "properties": {"role": "boundary", "name": "town"},
            "geometry": {"type": "Polygon", "coordinates": [geo(boundary)]},
        }
    ]
    for index, ring in enumerate(footprints):
        properties: dict[str, Any] = {"role": "keepout", "building": "yes"}
        properties["@id"] = f"way/{100_000_000 + index * 7}"
        roll = rng.random()
        if roll < 0.25:
            properties["name"] = rng.choice(NAMES)
        features.append(
            {
                "type": "Feature",
                "properties": properties,
                "geometry": {"type": "Polygon", "coordinates": [geo(ring)]},
            }
        )
    return {"type": "FeatureCollection", "name": f"town of {buildings}", "features": features}


def _buildings(rng: random.Random, side: float, wanted: int) -> list[list[tuple[float, float]]]:
    """Footprints (closed rings, metres) in blocks filling a square of ``side`` metres."""
    found: list[list[tuple[float, float]]] = []
    y = -side / 2
    while y < side / 2 and len(found) < wanted:
        depth = rng.uniform(60.0, 140.0)
        x = -side / 2
        while x < side / 2 and len(found) < wanted:
            width = rng.uniform(60.0, 140.0)
            found.extend(_block(rng, x, y, width, depth)[: wanted - len(found)])
            x += width + STREET_M
        y += depth + STREET_M
    return found


def _block(
    rng: random.Random, x0: float, y0: float, width: float, depth: float
) -> list[list[tuple[float, float]]]:
    """Buildings along the south and north edges of one block."""
    out = []
    for north in (False, True):
        x = x0 + rng.uniform(1.5, 6.0)
        while True:
            area = min(max(rng.lognormvariate(math.log(110.0), 0.6), 25.0), 900.0)
            aspect = rng.uniform(1.0, 2.2)
            w = math.sqrt(area * aspect)
            d = min(area / w, depth / 2 - 8.0)
            if x + w > x0 + width - 1.5:
                break
            setback = rng.uniform(3.0, 6.0)
            yb = y0 + depth - setback - d if north else y0 + setback
            if rng.random() < 0.25:  # an L: a corner cut out
                cx, cy = w * rng.uniform(0.3, 0.6), d * rng.uniform(0.3, 0.6)
                ring = [(x, yb), (x + w, yb), (x + w, yb + d - cy), (x + w - cx, yb + d - cy),
                        (x + w - cx, yb + d), (x, yb + d)]  # fmt: skip
            else:
                ring = [(x, yb), (x + w, yb), (x + w, yb + d), (x, yb + d)]
            out.append([*ring, ring[0]])
            x += w + rng.uniform(1.5, 8.0)
    return out


def _boundary(rng: random.Random, radius: float) -> list[tuple[float, float]]:
    """An irregular ring of ~40 vertices, 1.0-1.1 times ``radius`` from the centre."""
    count = 40
    ring = []
    for index in range(count):
        angle = 2 * math.pi * index / count
        r = radius * rng.uniform(1.0, 1.1)
        ring.append((r * math.cos(angle), r * math.sin(angle)))
    return [*ring, ring[0]]


def clear_around(
    town: dict[str, Any], latitude: float, longitude: float, metres: float = 10.0
) -> dict[str, Any]:
    """The map without the keep-outs nearer than ``metres`` to a position (a robot's start
    in a street), and without names (ids from the export's order)."""
    from shapely import Point

    from brasidas.autonomy.areamap import parse_map

    stripped = [town["features"][0]]
    for feature in town["features"][1:]:
        properties = {k: v for k, v in feature["properties"].items() if k != "name"}
        stripped.append(feature | {"properties": properties})
    area = parse_map(town | {"features": stripped})
    here = Point(area.local(latitude, longitude))
    kept = [stripped[0]]
    for feature, zone in zip(stripped[1:], area.keepouts.values(), strict=True):
        if zone.distance(here) > metres:
            kept.append(feature)
    return town | {"features": kept}
