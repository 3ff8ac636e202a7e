"""Reading map and route files at the station (issues 21, 22): the time to turn a file into the
platform's canonical map or waypoints, for files at the size limits.

- an Overpass export of 2 000 buildings (10 000 vertices: half the map's vertex limit) with
  ``--boundary-bbox``, then checked as the platform will (``parse_map``);
- a ``QGC WPL 110`` mission of 999 waypoints (the route's limit, with home);
- a 4 MiB file (the size limit) of route text: refused at its 1001st waypoint.
"""

from __future__ import annotations

import json
import time
from typing import Any

from bench.support import percentiles
from brasidas.autonomy.areamap import parse_map
from brasidas.mapfiles import FileRefused
from brasidas.mapfiles.files import MapOptions, read_map, read_route

RUNS = 5


def _overpass(buildings: int) -> str:
    elements: list[dict[str, Any]] = []
    side = 50
    for k in range(buildings):
        lon, lat = 23.640 + (k % side) * 4e-4, 37.930 + (k // side) * 3e-4
        base = 10 * k
        ring = [(lon, lat), (lon + 1e-4, lat), (lon + 1e-4, lat + 1e-4), (lon, lat + 1e-4)]
        elements += [
            {"type": "node", "id": base + i, "lat": y, "lon": x} for i, (x, y) in enumerate(ring)
        ]
        nodes = [base, base + 1, base + 2, base + 3, base]
        elements.append({"type": "way", "id": k, "nodes": nodes, "tags": {"building": "yes"}})
    bounds = {"minlat": 37.929, "minlon": 23.639, "maxlat": 37.943, "maxlon": 23.661}
    return json.dumps({"elements": elements, "bounds": bounds})


def _mission(waypoints: int) -> str:
    rows = ["QGC WPL 110", "0\t1\t0\t16\t0\t0\t0\t0\t37.9415\t23.653\t0\t1"]
    for i in range(1, waypoints + 1):
        lat, lon = 37.9410 + (i % 40) * 2e-5, 23.6524 + (i // 40) * 4e-5
        rows.append(f"{i}\t0\t3\t16\t0\t0\t0\t0\t{lat:.7f}\t{lon:.7f}\t0\t1")
    return "\n".join(rows) + "\n"


def _timed(work: Any) -> list[float]:
    samples = []
    for _ in range(RUNS):
        start = time.perf_counter()
        work()
        samples.append((time.perf_counter() - start) * 1000)
    return samples


def _refused(text: str) -> None:
    try:
        read_route(text)
    except FileRefused:
        return
    raise AssertionError("a route of 262 144 waypoints was read")


async def run() -> dict[str, Any]:
    osm = _overpass(2000)
    mission = _mission(999)
    text = "37.9414,23.6526\n" * (4 * 1024 * 1024 // 16)

    def osm_map() -> None:
        found = read_map(osm, "export.json", MapOptions(boundary_bbox=True))
        parse_map(found.geojson)

    return {
        "overpass_2000_buildings_ms": percentiles(_timed(osm_map)),
        "overpass_2000_buildings_bytes": len(osm),
        "wpl_999_waypoints_ms": percentiles(_timed(lambda: read_route(mission))),
        "route_text_4mib_refused_ms": percentiles(_timed(lambda: _refused(text))),
    }
