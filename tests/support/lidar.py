"""Lidar test helpers: obstacles the simulator alone knows, and the true clearance to one."""

from __future__ import annotations

import json
import math
from pathlib import Path

from platformd.sim.demo_area import offset
from support.patrol import LAT, LON, Robot


def obstacles_file(tmp_path: Path, *discs: tuple[float, float, float]) -> str:
    features = []
    for east, north, radius in discs:
        lat, lon = offset(LAT, LON, east, north)
        features.append(
            {
                "type": "Feature",
                "properties": {"radius_m": radius},
                "geometry": {"type": "Point", "coordinates": [lon, lat]},
            }
        )
    path = tmp_path / "obstacles.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    return str(path)


def clearance(robot: Robot, east: float, north: float, radius: float) -> float:
    """From the true vehicle's centre to the obstacle's edge."""
    pose = robot.vehicle.pose()
    return math.dist(robot.local(pose.latitude, pose.longitude), (east, north)) - radius
