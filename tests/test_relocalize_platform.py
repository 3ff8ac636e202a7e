"""Without GPS, through the running --sim daemon: a robot whose saved map was made with GPS
(its frame tied to latitude and longitude) is started 10 m and 90° away from where it saved
it, is placed in that map by global relocalization, and patrols its route (latitude and
longitude, projected into the map's frame) on that pose. Started in a room that looks the
same turned round, it holds, says why, and never moves by itself; with no saved map at all the
patrol holds, saying why, and hand driving works."""

from __future__ import annotations

import asyncio
import json
import math
from pathlib import Path
from typing import Any, TypeVar

import pytest
from conftest import until_armable, wait_until
from support.patrol import LAT, LON, Robot, at, config

from brasidas import topics
from brasidas.autonomy.geo import LocalFrame
from brasidas.messages import PoseEstimate, Velocity
from brasidas.perception.odometry import Pose2D
from platformd.app import PlatformDaemon
from platformd.lidar_localization import OWN_FRAME_HOLD, Localizer
from platformd.lidar_reader import LidarReader
from platformd.mode import ModeArbiter
from platformd.session_table import Session
from platformd.sim.demo_area import offset
from platformd.sim.lidar import LidarWorld, load_obstacles, world_polygons
from platformd.sim.survey import ROOM_POSTS, ROOM_WALLS, obstacles_geojson, survey

T = TypeVar("T")
pytestmark = pytest.mark.slow  # three daemons, ~20 s of patrol

FRAME = LocalFrame(LAT, LON)
"""The saved map's frame: metres east and north of LAT, LON."""
SAVED = Pose2D(-8.0, -2.0, 0.0)
"""Where the robot was when its map was saved (facing east)."""
START = Pose2D(0.0, 4.0, math.pi / 2)
"""Where it is started: 10 m from there, facing north (90° turned)."""
OPERATOR = Session("operator", "station-1", "127.0.0.1", None, 0.0, 0.0)
BARE = (
    (-11.0, -5.0, 5.0, -4.7),
    (-11.0, 4.7, 5.0, 5.0),
    (-11.0, -5.0, -10.7, 5.0),
    (4.7, -5.0, 5.0, 5.0),
)
"""A bare rectangle: every place in it has a twin, turned half round."""


def obstacles(
    tmp_path: Path,
    walls: tuple[tuple[float, float, float, float], ...],
    posts: tuple[tuple[float, float], ...],
) -> str:
    """The room, known to the simulator only (the area map has no keep-outs)."""
    path = tmp_path / "room.geojson"
    path.write_text(json.dumps(obstacles_geojson(LAT, LON, walls, posts)))
    return str(path)


def area_map() -> dict[str, Any]:
    corners = [(-12.0, -9.0), (6.0, -9.0), (6.0, 9.0), (-12.0, 9.0), (-12.0, -9.0)]
    ring = [[lon, lat] for lat, lon in (offset(LAT, LON, x, y) for x, y in corners)]
    boundary = {
        "type": "Feature",
        "id": "room",
        "properties": {"role": "boundary"},
        "geometry": {"type": "Polygon", "coordinates": [ring]},
    }
    return {"type": "FeatureCollection", "name": "room", "features": [boundary]}


def saved_map(tmp_path: Path, room: str) -> Path:
    """The grid a mapping drive with GPS would have saved: round the room, ending at SAVED."""
    polygons, discs = world_polygons(FRAME, None, load_obstacles(room))
    world = LidarWorld(polygons, discs)
    circle = [
        Pose2D(-2.7 + 2.7 * math.cos(t), 2.7 * math.sin(t), t + math.pi / 2)
        for t in [2 * math.pi * k / 40 for k in range(41)]
    ]
    sweep = [Pose2D(-9.0 + 0.6 * k, -1.0 + (k % 3), 0.0) for k in range(20)]
    grid = survey(world, [*circle, *sweep, SAVED], LAT, LON)
    path = tmp_path / "grid.npz"
    grid.save(path)
    return path


async def start(tmp_path: Path, room: str, *overrides: str) -> tuple[PlatformDaemon, Robot]:
    latitude, longitude = FRAME.to_geo(START.x_m, START.y_m)
    daemon = PlatformDaemon(
        config(
            tmp_path,
            "gps.enabled=false",
            "lidar.enabled=true",
            "lidar.map_obstacles=false",
            "autonomy.autostart=false",
            "autonomy.cruise_speed_kmh=7",
            "autonomy.lookahead_m=2",
            "autonomy.clearance_m=1.5",
            f"lidar.grid_file={tmp_path / 'grid.npz'}",
            f"sim.obstacles_file={room}",
            f"sim.latitude={latitude:.9f}",
            f"sim.longitude={longitude:.9f}",
            f"sim.heading_deg={(90.0 - math.degrees(START.yaw_rad)) % 360.0:.3f}",
            *overrides,
        ),
        None,
    )
    await daemon.start()
    robot = Robot(daemon)
    await robot.call("load_map", map=area_map())
    await robot.call("set_waypoints", waypoints=[at(-4.0, 4.0), at(-4.0, -3.0)])
    return daemon, robot


def actor(daemon: PlatformDaemon, kind: type[T]) -> T:
    return next(a for a in daemon.supervisor.actors if isinstance(a, kind))


def truth(robot: Robot) -> Pose2D:
    pose = robot.vehicle.pose()
    east, north = FRAME.to_local(pose.latitude, pose.longitude)
    return Pose2D(east, north, math.radians(90.0 - pose.heading_deg))


def pose_error_m(pose: PoseEstimate, robot: Robot) -> float:
    actual = truth(robot)
    return math.dist(FRAME.to_local(pose.latitude, pose.longitude), (actual.x_m, actual.y_m))


def moved_m(robot: Robot) -> float:
    here = truth(robot)
    return math.hypot(here.x_m - START.x_m, here.y_m - START.y_m)


SAVED_MAP_HOLDS = ("holding, not placed", "holding: a place", "lost:")
"""The saved map's own holds on the way (a starved machine's odometry can drift off the map:
the robot holds and is placed again)."""


async def test_without_gps_a_robot_carried_10_m_is_placed_in_its_saved_map_and_patrols(
    tmp_path: Path,
) -> None:
    room = obstacles(tmp_path, ROOM_WALLS, ROOM_POSTS)
    saved_map(tmp_path, room)
    daemon, robot = await start(tmp_path, room)
    try:
        localizer = actor(daemon, Localizer)
        await wait_until(lambda: daemon.ctx.bus.last(topics.POSE) is not None, 20)  # placed
        placer = localizer.placer
        assert placer is not None and placer.placed and localizer.geo_anchored
        fused = localizer.fused
        assert fused is not None
        actual = truth(robot)  # standing still: where it was placed is where it is
        assert math.hypot(fused.x_m - actual.x_m, fused.y_m - actual.y_m) < 0.3, (fused, actual)
        assert abs(math.remainder(fused.yaw_rad - actual.yaw_rad, 2 * math.pi)) < math.radians(3)
        section = actor(daemon, LidarReader).section()
        assert section.map_place.startswith("placed in the saved map"), section.map_place
        assert section.localization in ("map+lidar", "lidar", "prior"), section.localization

        errors: list[float] = []
        robot.watchers.append(lambda pose, _here: errors.append(pose_error_m(pose, robot)))
        await robot.call("patrol_start")
        await robot.drive_laps(1, 120.0, also_transient=SAVED_MAP_HOLDS)
        assert len(errors) > 50
        # The patrol's pose against the truth: a wrong place (10 m, 90° off) or a drift left
        # uncorrected would be metres. The worst is a pose late on a loaded machine: it is
        # stamped when published, and at 2 m/s a scan processed 0.3 s late is 0.6 m behind
        # (1.23 m seen in a whole-suite run, 0.4 m alone), so the mean is the tight bound.
        mean = sum(errors) / len(errors)
        assert mean < 0.3, (mean, max(errors))
        assert max(errors) < 2.0, (mean, max(errors))
        assert placer.placements == placer.losses + 1  # each loss searched and placed again
        assert localizer.fusion.map_accepted > 0  # registered to the saved map as it went
        assert localizer.fusion.accepted == 0  # no GPS at all: the saved map did it
    finally:
        robot.close()
        await daemon.stop()


async def test_a_start_the_saved_map_cannot_tell_apart_holds_and_says_why(tmp_path: Path) -> None:
    room = obstacles(tmp_path, BARE, ())
    saved_map(tmp_path, room)
    daemon, robot = await start(tmp_path, room)
    try:
        localizer = actor(daemon, Localizer)
        placer = localizer.placer
        assert placer is not None
        await wait_until(lambda: placer.searches >= 2, 20)
        await robot.call("patrol_start")
        await wait_until(lambda: "ambiguous" in robot.status.reason, 10)
        assert robot.status.state == "holding"
        assert robot.status.reason.startswith("holding, not placed in the saved map")
        assert "ambiguous" in actor(daemon, LidarReader).section().map_place
        assert localizer.fused is None  # no pose at all, so nothing drives on one
        assert daemon.ctx.bus.last(topics.POSE) is None
        await asyncio.sleep(1.0)  # a second of scans: it stays where it is
        assert moved_m(robot) < 0.05
        assert not any(v.linear or v.angular for v in robot.cmd_vel)
    finally:
        robot.close()
        await daemon.stop()


async def test_with_no_saved_map_and_no_gps_the_patrol_holds_and_hand_driving_works(
    tmp_path: Path,
) -> None:
    room = obstacles(tmp_path, ROOM_WALLS, ROOM_POSTS)
    daemon, robot = await start(tmp_path, room)
    try:
        localizer = actor(daemon, Localizer)
        await wait_until(lambda: localizer.fused is not None, 20)
        assert localizer.map_frame and not localizer.geo_anchored
        await robot.call("patrol_start")
        await wait_until(lambda: robot.status.reason == OWN_FRAME_HOLD, 10)
        assert robot.status.state == "holding"
        assert daemon.ctx.bus.last(topics.POSE) is None
        assert actor(daemon, LidarReader).section().map_place == OWN_FRAME_HOLD
        # The hand drives it all the same.
        await until_armable(robot.ctx)
        mode = actor(daemon, ModeArbiter)
        assert mode.request(True, OPERATOR).accepted
        for _ in range(15):
            robot.ctx.bus.publish(topics.TELEOP_VELOCITY, Velocity(0.2, 0.0))
            await asyncio.sleep(0.1)
        robot.ctx.bus.publish(topics.TELEOP_VELOCITY, Velocity(0.0, 0.0))
        assert mode.request(False, OPERATOR).accepted
        assert moved_m(robot) > 0.5
        assert robot.status.state == "holding"
    finally:
        robot.close()
        await daemon.stop()
