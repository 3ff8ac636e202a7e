"""The occupancy grid: beams mark free and hit cells in the world frame; saved and loaded."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from brasidas.perception.grid import GridError, OccupancyGrid
from brasidas.perception.odometry import Pose2D

WALL = np.column_stack((np.full(41, 5.0), np.linspace(-2.0, 2.0, 41)))
"""A wall 5 m ahead of the robot, 4 m wide (robot frame)."""


def test_a_wall_ahead_is_occupied_the_way_to_it_free_behind_unknown() -> None:
    grid = OccupancyGrid(37.9, 23.6)
    for _ in range(3):
        grid.integrate(Pose2D(10.0, 20.0, 0.0), WALL)
    assert grid.occupied(15.02, 20.0) > 0.9
    assert grid.occupied(12.5, 20.0) < 0.1
    assert grid.occupied(5.0, 20.0) == 0.5  # behind the robot: never seen


def test_the_robots_heading_turns_the_scan_into_the_world() -> None:
    grid = OccupancyGrid(37.9, 23.6)
    grid.integrate(Pose2D(0.0, 0.0, math.pi / 2), WALL)  # facing north: the wall is north
    assert grid.occupied(0.0, 5.02) > 0.6
    assert grid.occupied(5.02, 0.0) == 0.5


def test_saved_and_loaded_with_its_anchor(tmp_path: Path) -> None:
    grid = OccupancyGrid(37.9, 23.6)
    grid.integrate(Pose2D(-30.0, 40.0, 0.3), WALL)  # grows the grid away from its start
    grid.integrate(Pose2D(0.0, 0.0, 0.0), WALL)
    path = tmp_path / "grid.npz"
    grid.save(path)
    loaded = OccupancyGrid.load(path)
    assert (loaded.latitude, loaded.longitude, loaded.scans) == (37.9, 23.6, 2)
    assert np.array_equal(loaded.log_odds, grid.log_odds)
    assert loaded.occupied(5.02, 0.0) == grid.occupied(5.02, 0.0) > 0.6


@pytest.mark.parametrize(
    "content",
    [b"", b"not a zip", b"PK\x03\x04broken", b"\x93NUMPY\x01\x00v\x00{'descr': '<f8'}"],
    ids=["empty", "text", "torn", "npy"],
)
def test_a_file_that_is_not_a_grid_is_refused_with_the_reason(
    tmp_path: Path, content: bytes
) -> None:
    path = tmp_path / "grid.npz"
    path.write_bytes(content)
    with pytest.raises(GridError, match="not a saved grid"):
        OccupancyGrid.load(path)


def test_the_robots_pose_is_saved_with_the_grid_and_a_rebuild_keeps_it(tmp_path: Path) -> None:
    grid = OccupancyGrid(37.9, 23.6)
    grid.integrate(Pose2D(0.0, 0.0, 0.0), WALL)
    path = tmp_path / "grid.npz"
    grid.save(path)
    assert OccupancyGrid.load(path).pose is None  # not known: a robot with GPS finds itself
    grid.pose = Pose2D(1.5, -2.0, 0.3)
    rebuilt = grid.rebuilt([(Pose2D(0.0, 0.0, math.pi / 2), WALL.astype(np.float32))])
    assert rebuilt.pose == grid.pose
    assert rebuilt.occupied(0.0, 5.02) > 0.6  # the keyframe's wall, north
    assert rebuilt.occupied(5.02, 0.0) > 0.6  # and the grid's own, east
    rebuilt.save(path)
    assert OccupancyGrid.load(path).pose == Pose2D(1.5, -2.0, 0.3)
