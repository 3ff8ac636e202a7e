"""A saved map as a mapping drive with GPS would leave it, made from the simulator's world.

For the relocalization's tests and ``make bench perception``: scans ray-cast from the
simulated world (:class:`~platformd.sim.lidar.LidarWorld`) at known poses, integrated into an
occupancy grid anchored at a latitude and longitude (``geo``: its frame is tied to them, as a
grid built while GPS held the pose is). No I/O; the caller saves it where the platform loads it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray
from shapely.geometry import box

from brasidas.autonomy.geo import LocalFrame
from brasidas.perception.grid import OccupancyGrid
from brasidas.perception.odometry import Pose2D
from platformd.sim.lidar import LidarWorld

BEAM_STEP_RAD = math.radians(0.8)
"""The LD19's spacing: 450 returns a revolution."""
MAX_RANGE_M = 12.0
RANGE_NOISE_M = 0.01


def cast_scan(
    world: LidarWorld,
    pose: Pose2D,
    rng: np.random.Generator | None = None,
    max_range_m: float = MAX_RANGE_M,
) -> NDArray[np.float64]:
    """The returns at ``pose`` (world frame) as (N, 2) x forward, y left of the robot (metres),
    with the LD19's range noise when ``rng`` is given."""
    bearings = np.arange(0.0, 2 * math.pi, BEAM_STEP_RAD)
    segments, discs = world.near(pose.x_m, pose.y_m, max_range_m)
    ranges, _ = world.cast(pose.x_m, pose.y_m, bearings + pose.yaw_rad, segments, discs)
    seen = ranges < max_range_m
    r, b = ranges[seen], bearings[seen]
    if rng is not None:
        r = r + rng.normal(0.0, RANGE_NOISE_M, len(r))
    return np.column_stack((r * np.cos(b), r * np.sin(b)))


def survey(
    world: LidarWorld,
    poses: list[Pose2D],
    latitude: float,
    longitude: float,
    rng: np.random.Generator | None = None,
) -> OccupancyGrid:
    """The grid of scans taken at ``poses``, anchored at ``latitude``, ``longitude`` (the
    world's origin), the robot's saved pose the last of them."""
    grid = OccupancyGrid(latitude, longitude)
    grid.geo = True
    for pose in poses:
        grid.integrate(pose, cast_scan(world, pose, rng))
    grid.pose = poses[-1] if poses else None
    return grid


ROOM_WALLS = (
    (-11.0, -8.0, 5.0, -7.7),
    (-11.0, 7.7, 5.0, 8.0),
    (-11.0, -8.0, -10.7, 8.0),
    (4.7, -8.0, 5.0, 3.0),  # a doorway in the east wall, north of 3 m
    (-6.0, -7.7, -5.8, -4.0),  # a partition
)
"""A 16 m square room (west, south, east, north edges of each wall, metres from the origin):
its walls alone look the same turned 90°; the doorway, the partition and the posts tell."""
ROOM_POSTS = ((-9.0, 5.0), (3.0, -6.0), (-7.0, -5.5))
POST_RADIUS_M = 0.3


def obstacles_geojson(
    latitude: float,
    longitude: float,
    walls: Sequence[tuple[float, float, float, float]],
    posts: Sequence[tuple[float, float]] = (),
) -> dict[str, Any]:
    """``sim.obstacles_file``'s GeoJSON of these walls and posts (metres east and north of
    ``latitude``, ``longitude``)."""
    frame = LocalFrame(latitude, longitude)

    def feature(geometry: dict[str, Any], **properties: Any) -> dict[str, Any]:
        return {"type": "Feature", "properties": properties, "geometry": geometry}

    def lon_lat(x: float, y: float) -> list[float]:
        lat, lon = frame.to_geo(x, y)
        return [lon, lat]

    features = []
    for x0, y0, x1, y1 in walls:
        ring = [lon_lat(x, y) for x, y in ((x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0))]
        features.append(feature({"type": "Polygon", "coordinates": [ring]}))
    for x, y in posts:
        point = {"type": "Point", "coordinates": lon_lat(x, y)}
        features.append(feature(point, radius_m=POST_RADIUS_M))
    return {"type": "FeatureCollection", "features": features}


def world_of(
    walls: Sequence[tuple[float, float, float, float]], posts: Sequence[tuple[float, float]] = ()
) -> LidarWorld:
    """The simulator's world of these walls and posts, in metres (no globe)."""
    return LidarWorld(
        [(box(*wall), 0.6) for wall in walls], [(x, y, POST_RADIUS_M, 0.5) for x, y in posts]
    )
