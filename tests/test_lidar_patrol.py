"""The patrol steered by the lidar localization on a --sim platform: a spoofed GPS is refused
and never followed, and a map reloaded mid-patrol leaves the robot localized.

The area map's keep-outs are buildings along a street; the simulated lidar sees them (the
simulator's world is the map's keep-outs), the simulated NEO-6M has its slow error, and the
whole platform runs: GPS reader, IMU, AX3500, lidar reader, localizer, patrol.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import itertools
import math
from typing import Any

from conftest import until_armable, wait_until
from support.patrol import LAT, LON, Robot, at

from brasidas import topics
from brasidas.messages import GpsFix, PoseEstimate
from platformd.lidar_localization import Localizer
from platformd.sim.demo_area import offset
from platformd.sim.vehicle import Pose

STREET = [(-6.0, 8.0), (12.0, 26.0), (30.0, 46.0)]
"""Buildings' spans east (metres) on both sides of the street along y = 0."""


def street_map() -> dict[str, Any]:
    def ring(x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
        corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]
        return [[lon, lat] for lat, lon in (offset(LAT, LON, x, y) for x, y in corners)]

    def zone(role: str, name: str, corners: tuple[float, float, float, float]) -> dict[str, Any]:
        return {
            "type": "Feature",
            "id": name,
            "properties": {"role": role},
            "geometry": {"type": "Polygon", "coordinates": [ring(*corners)]},
        }

    buildings = []
    for i, (x0, x1) in enumerate(STREET):
        buildings.append(zone("keepout", f"south-{i}", (x0, -13.0, x1, -7.0)))
        buildings.append(zone("keepout", f"north-{i}", (x0 + 3, 7.0, x1 + 3, 13.0)))
    return {
        "type": "FeatureCollection",
        "name": "street",
        "features": [zone("boundary", "field", (-15.0, -17.0, 55.0, 17.0)), *buildings],
    }


LIDAR = (
    "lidar.enabled=true",
    "lidar.map_obstacles=false",
    "autonomy.cruise_speed_kmh=7",
    "autonomy.lookahead_m=2",
    # The street is 14 m wide: at the default 4.5 m a NEO-6M start 2.5 m off sideways (before
    # the lidar's fusion starts, on the GPS+IMU pose) puts the robot inside the buildings'
    # margin, and the patrol holds before it ever drives.
    "autonomy.clearance_m=2",
    "sim.heading_deg=90",  # facing along the street
)


def localizer_of(robot: Robot) -> Localizer:
    return next(a for a in robot.daemon.supervisor.actors if isinstance(a, Localizer))


async def start_on_the_street(robot: Robot, far_end_m: float = 40.0) -> Localizer:
    await robot.call("load_map", map=street_map())
    await robot.call("set_waypoints", waypoints=[at(0, 0), at(far_end_m, 0)])
    await until_armable(robot.ctx)
    await robot.call("patrol_start")
    localizer = localizer_of(robot)
    settled: list[str] = []

    def on_the_map(pose: PoseEstimate) -> None:
        settled.append(pose.source)

    unsubscribe = robot.ctx.bus.subscribe(topics.POSE, on_the_map)
    try:  # on the lidar's pose for a second (ten poses)
        await wait_until(
            lambda: len(settled) > 10 and all(s.endswith("+lidar") for s in settled[-10:]), 60
        )
    finally:
        unsubscribe()
    return localizer


def error_m(robot: Robot) -> float:
    """From the pose the patrol follows to the true vehicle's position."""
    pose, truth = robot.poses[-1]
    return math.dist(robot.local(pose.latitude, pose.longitude), truth)


async def test_a_spoofed_gps_jump_is_refused_and_the_robot_keeps_its_route(
    robot_factory: Any,
) -> None:
    robot: Robot = await robot_factory(*LIDAR)
    # To the second buildings' far end (x 12-26 south, 15-29 north), not the street's (46 m):
    # the robot still drives ~10 s (20 m) after the spoof between walls on both sides, where the
    # map's walls fix it, and the test waits 10 s less on it.
    localizer = await start_on_the_street(robot, far_end_m=24.0)
    gps = robot.ctx.sim.gps
    assert gps is not None
    honest = gps.generator.epoch

    def spoofed(pose: Pose, utc: dt.datetime) -> bytes:  # 30 m north of the truth
        return honest(dataclasses.replace(pose, latitude=pose.latitude + 30 / 110_574.0), utc)

    followed: list[GpsFix] = []
    robot.ctx.bus.subscribe(topics.GPS_ACCEPTED, followed.append)
    gps.generator.epoch = spoofed
    await wait_until(lambda: localizer.gps_refusal.startswith("jump"), 5)
    spoofed_at, reported_at = len(robot.poses), len(robot.reports)
    # The robot drives on along the street to the next end of it, on the lidar.
    target = robot.status.waypoint
    # ... and, on a loaded machine the map matching's process answers late, until a scan has
    # fit the map's walls since.
    await wait_until(
        lambda: (
            robot.status.waypoint != target
            and len(robot.poses) > spoofed_at + 50
            and any(pose.source == "map+lidar" for pose, _ in robot.poses[spoofed_at:])
        ),
        60,
    )
    after = robot.poses[spoofed_at:]
    assert after
    assert max(abs(truth[1]) for _pose, truth in after) < 5.0  # never left the street
    errors = [math.dist(robot.local(pose.latitude, pose.longitude), truth) for pose, truth in after]
    # A followed spoof would be 30 m off. The pose's own error is the honest GPS's along the
    # street before the spoof (the walls on both sides fix the pose across the street, not
    # along it) until a scan fits the street's ends: 1.3 m in one run, 4.1-5.3 m in others
    # (a stalled scan under load adds to it); make bench perception measures the lidar's.
    assert max(errors) < 10.0, max(errors)
    sources = [pose.source for pose, _ in after]
    assert "gps+imu" not in sources
    assert "map+lidar" in sources
    assert all(robot.local(fix.latitude, fix.longitude)[1] < 15 for fix in followed)
    holds = {r.reason for r in robot.reports[reported_at:] if r.state == "holding"}
    assert all(reason.startswith("planning the path") for reason in holds), holds


async def test_reloading_the_map_mid_patrol_keeps_the_robot_localized(robot_factory: Any) -> None:
    """R-5.3.2: a map reloaded while the robot drives changes what the scans are matched to,
    not where the robot is: the pose carries on, and the next scans fit the new map."""
    robot: Robot = await robot_factory(*LIDAR)
    localizer = await start_on_the_street(robot)
    before = localizer.walls_set
    reloaded_at = len(robot.poses)
    changed = street_map()
    changed["name"] = "street, resurveyed"
    moved = changed["features"][-1]["geometry"]  # the survey put one building 0.2 m north
    moved["coordinates"] = [[[lon, lat + 0.2 / 110_574.0] for lon, lat in moved["coordinates"][0]]]
    await robot.call("load_map", map=changed)
    assert robot.status.state == "stopped"  # a reload clears the route (the operator's rule)
    await wait_until(lambda: localizer.walls_set > before, 5)
    swapped_at = len(robot.poses)
    assert localizer.has_walls  # the scans are matched to the new map's keep-outs
    await wait_until(lambda: localizer.map_answers >= 3, 10)
    await wait_until(lambda: len(robot.poses) > reloaded_at + 30, 10)
    around = robot.poses[reloaded_at - 10 :]
    errors = [
        math.dist(robot.local(pose.latitude, pose.longitude), truth) for pose, truth in around
    ]
    # As localized after the reload as before it (the street's along-street error is the
    # GPS's where the walls do not fix it: make bench perception measures the accuracy).
    assert max(errors[10:]) < max(errors[:10]) + 0.5, errors
    assert "gps+imu" not in {pose.source for pose, _ in around}
    across = robot.poses[reloaded_at - 10 : swapped_at + 1]  # before the new map is matched
    jumps = [
        math.dist(robot.local(a.latitude, a.longitude), robot.local(b.latitude, b.longitude))
        for (a, _), (b, _) in itertools.pairwise(across)
    ]
    # No reset at the reload: the pose carried on (a map match of the old map just before it
    # may still correct it by a metre; a restart from the GPS would move it by the GPS's error).
    assert max(jumps) < 2.0, max(jumps)
    assert localizer.fusion.started
    # And the patrol starts again on it.
    await robot.call("set_waypoints", waypoints=[at(0, 0), at(40, 0)])
    await robot.call("patrol_start")
    await wait_until(lambda: robot.status.state == "patrolling", 20)
