"""A saved map as a mapping drive with GPS would leave it, made from the simulator's world.

For the relocalization's tests and ``make bench perception``: scans ray-cast from the
simulated world (:class:`~platformd.sim.lidar.LidarWorld`) at known poses, integrated into an
occupancy grid anchored at a latitude and longitude (``geo``: its frame is tied to them, as a
grid built while GPS held the pose is). No I/O; the caller saves it where the platform loads it.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

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
