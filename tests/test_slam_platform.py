"""SLAM through the running --sim daemon without GPS: the robot localizes in its own map's
frame, driving round a loop closes it (the pose graph's keyframes, scan registration) and the
drift of its pose is taken out, and the map it saved at stop (grid, keyframes, its pose) is
loaded at the next start, where it goes on in the same frame and closes loops against the old
keyframes."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from support.patrol import LAT, LON, Robot, config

from brasidas import topics
from brasidas.messages import Velocity
from brasidas.perception.grid import OccupancyGrid
from brasidas.perception.messages import LidarPose, RobotScan
from brasidas.perception.odometry import LidarOdometry, OdometryStep, Pose2D
from brasidas.perception.pose_graph import load_keyframes
from platformd.app import PlatformDaemon
from platformd.lidar_localization import Localizer, keyframes_path
from platformd.mode import ModeArbiter
from platformd.session_table import Session
from platformd.sim.demo_area import offset

pytestmark = pytest.mark.slow  # two daemons, 22 s of driving

START = Pose2D(0.0, 0.0, math.pi / 2)
"""The simulated vehicle's start (metres east, north of LAT, LON; facing north): the new map's
frame starts here, facing its x axis."""
OPERATOR = Session("operator", "station-1", "127.0.0.1", None, 0.0, 0.0)
CIRCLE = Velocity(0.2, 0.25)
"""1 m/s and 21.5°/s at 18 km/h: a circle of 2.7 m round (-2.7, 0), 17 s a lap (faster, a
loaded machine's odometry fell back on its prior for a third of the scans)."""
YAW_DRIFT_PER_M = math.radians(1.0)
"""Put on each odometry step: a drift the scans of this small room would not have on their own
(a long featureless stretch, a starved machine), so that the loop is visibly open."""


@pytest.fixture
def drifting_odometry(monkeypatch: pytest.MonkeyPatch) -> None:
    real = LidarOdometry.update

    def update(self: LidarOdometry, *args: Any) -> OdometryStep:
        step = real(self, *args)
        d = step.delta
        drift = YAW_DRIFT_PER_M * math.hypot(d.x_m, d.y_m)
        return dataclasses.replace(step, delta=Pose2D(d.x_m, d.y_m, d.yaw_rad + drift))

    monkeypatch.setattr(LidarOdometry, "update", update)


class ErrorLog:
    """The map-frame pose of each scan against the truth at that scan's time, and how many
    loops had closed by then."""

    def __init__(self, robot: Robot, localizer: Localizer) -> None:
        self.robot, self.localizer = robot, localizer
        self.truth_at: dict[float, Pose2D] = {}
        self.errors: list[tuple[int, float]] = []
        bus = robot.ctx.bus
        self._unsubscribe = [
            bus.subscribe(topics.LIDAR_SCAN, self._on_scan),
            bus.subscribe(topics.LIDAR_POSE, self._on_pose),
        ]

    def _on_scan(self, scan: RobotScan) -> None:
        self.truth_at[scan.time] = truth(self.robot)

    def _on_pose(self, pose: LidarPose) -> None:
        actual, frame = self.truth_at.pop(pose.time, None), self.localizer.frame
        if actual is None or frame is None:
            return
        x, y = frame.to_local(pose.latitude, pose.longitude)
        here = START.compose(Pose2D(x, y, pose.yaw_rad))
        closed = len(self.localizer.loop_corrections)
        self.errors.append((closed, math.hypot(here.x_m - actual.x_m, here.y_m - actual.y_m)))

    def close(self) -> None:
        for unsubscribe in self._unsubscribe:
            unsubscribe()


def room(tmp_path: Path) -> str:
    """Walls round the circle and a few posts (the simulated lidar's alone: the area map has
    none of them), so the scans have something to register."""

    def polygon(corners: list[tuple[float, float]]) -> dict[str, object]:
        ring = [offset(LAT, LON, east, north) for east, north in [*corners, corners[0]]]
        return {
            "type": "Feature",
            "properties": {},
            "geometry": {"type": "Polygon", "coordinates": [[[lon, lat] for lat, lon in ring]]},
        }

    def wall(x0: float, y0: float, x1: float, y1: float) -> dict[str, object]:
        return polygon([(x0, y0), (x1, y0), (x1, y1), (x0, y1)])

    def post(east: float, north: float) -> dict[str, object]:
        lat, lon = offset(LAT, LON, east, north)
        return {
            "type": "Feature",
            "properties": {"radius_m": 0.3},
            "geometry": {"type": "Point", "coordinates": [lon, lat]},
        }

    features = [
        wall(-11.0, -8.0, 5.0, -7.7),
        wall(-11.0, 7.7, 5.0, 8.0),
        wall(-11.0, -8.0, -10.7, 8.0),
        wall(4.7, -8.0, 5.0, 3.0),  # a doorway in the east wall, north of 3 m
        post(-9.0, 5.0),
        post(3.0, -6.0),
        post(-7.0, -5.5),
    ]
    path = tmp_path / "room.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    return str(path)


async def start(tmp_path: Path, at: Pose2D, *overrides: str) -> tuple[PlatformDaemon, Robot]:
    latitude, longitude = offset(LAT, LON, at.x_m, at.y_m)
    daemon = PlatformDaemon(
        config(
            tmp_path,
            "gps.enabled=false",
            "lidar.enabled=true",
            "autonomy.autostart=false",
            f"lidar.grid_file={tmp_path / 'grid.npz'}",
            f"sim.obstacles_file={room(tmp_path)}",
            f"sim.latitude={latitude:.9f}",
            f"sim.longitude={longitude:.9f}",
            f"sim.heading_deg={(90.0 - math.degrees(at.yaw_rad)) % 360.0:.3f}",
            *overrides,
        ),
        None,
    )
    await daemon.start()
    return daemon, Robot(daemon)


def localizer_of(daemon: PlatformDaemon) -> Localizer:
    return next(a for a in daemon.supervisor.actors if isinstance(a, Localizer))


def truth(robot: Robot) -> Pose2D:
    pose = robot.vehicle.pose()
    east, north = robot.local(pose.latitude, pose.longitude)
    return Pose2D(east, north, math.radians(90.0 - pose.heading_deg))


def error_m(localizer: Localizer, robot: Robot) -> float:
    """The map-frame pose against the truth (the map's frame is the first start's pose)."""
    fused = localizer.fused
    assert fused is not None
    here = START.compose(Pose2D(fused.x_m, fused.y_m, fused.yaw_rad))
    actual = truth(robot)
    return math.hypot(here.x_m - actual.x_m, here.y_m - actual.y_m)


async def drive(robot: Robot, seconds: float, until: Callable[[], bool] | None = None) -> None:
    """Round the circle for ``seconds``, or until ``until()`` holds (failing if it never
    does), then to rest."""
    mode = next(a for a in robot.daemon.supervisor.actors if isinstance(a, ModeArbiter))
    assert mode.request(True, OPERATOR).accepted
    for _ in range(round(seconds * 10)):  # a joystick held
        robot.ctx.bus.publish(topics.TELEOP_VELOCITY, CIRCLE)
        await asyncio.sleep(0.1)
        if until is not None and until():
            break
    else:
        assert until is None, f"not within {seconds} s of driving"
    robot.ctx.bus.publish(topics.TELEOP_VELOCITY, Velocity(0.0, 0.0))
    assert mode.request(False, OPERATOR).accepted
    await wait_until(lambda: abs(robot.vehicle.pose().speed_mps) < 0.02, 5)


async def test_without_gps_a_driven_loop_closes_and_the_saved_map_loads_at_the_next_start(
    tmp_path: Path, drifting_odometry: None
) -> None:
    daemon, robot = await start(tmp_path, START)
    try:
        localizer = localizer_of(daemon)
        await wait_until(lambda: localizer.fused is not None, 10)
        assert localizer.map_frame and not localizer.geo_anchored
        log = ErrorLog(robot, localizer)
        await drive(robot, 21.0)  # a lap and a quarter
        log.close()
        graph = localizer.graph
        assert graph is not None
        assert graph.closures > 0, len(graph.poses)
        # The loop was open (the drift), and closing it took the drift out; driving on with
        # the same drift (5 m more) the later closures keep it under what it was open.
        open_error = max(error for closed, error in log.errors if closed == 0)
        closed_errors = [error for closed, error in log.errors if closed > 0]
        assert open_error > 0.5, open_error
        assert closed_errors[0] < open_error / 2, (open_error, closed_errors)
        assert closed_errors[-1] < open_error, (open_error, closed_errors)
        assert localizer.grid_rebuilds >= 1  # the grid, redrawn from the corrected keyframes
        stopped_at = truth(robot)
        fused = localizer.fused
        assert fused is not None
        assert fused.source == "lidar"
        error = error_m(localizer, robot)
        keyframes = len(graph.poses)
    finally:
        robot.close()
        await daemon.stop()
    grid_file = tmp_path / "grid.npz"
    saved = OccupancyGrid.load(grid_file)
    assert saved.pose is not None
    assert not saved.geo
    assert len(load_keyframes(keyframes_path(grid_file))) >= keyframes - 2

    # The next start, where it stopped: the saved map is its frame, its saved pose the start.
    daemon, robot = await start(tmp_path, stopped_at)
    try:
        localizer = localizer_of(daemon)
        await wait_until(lambda: localizer.fused is not None, 10)
        assert localizer.map_frame and not localizer.geo_anchored  # still its own frame
        # It starts where it stopped in the saved map's frame: off the truth as it was then.
        assert abs(error_m(localizer, robot) - error) < 0.1
        await wait_until(lambda: localizer.graph is not None, 5)
        graph = localizer.graph
        assert graph is not None
        assert graph.first_live >= keyframes - 2

        # Driving on: a loop closes against the loaded map's keyframes.
        def closed_against_the_loaded_map() -> bool:
            closure = graph.last_closure
            return closure is not None and closure.j < graph.first_live

        await drive(robot, 10.0, until=closed_against_the_loaded_map)
    finally:
        robot.close()
        await daemon.stop()
