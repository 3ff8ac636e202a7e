"""The patrol steered by the lidar localization on a --sim platform: a spoofed GPS is refused
and never followed, and a map reloaded mid-patrol leaves the robot localized.

The area map's keep-outs are buildings along a street; the simulated lidar sees them (the
simulator's world is the map's keep-outs), the simulated NEO-6M has its slow error, and the
whole platform runs: GPS reader, IMU, AX3500, lidar reader, localizer, patrol.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
from typing import Any

from conftest import until_armable, wait_until
from test_patrol_platform import LAT, LON, Robot, at
from test_patrol_platform import robot_factory as robot_factory  # the fixture

from brasidas import topics
from brasidas.messages import GpsFix
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
        buildings.append(zone("keepout", f"south-{i}", (x0, -11.0, x1, -5.0)))
        buildings.append(zone("keepout", f"north-{i}", (x0 + 3, 5.0, x1 + 3, 11.0)))
    return {
        "type": "FeatureCollection",
        "name": "street",
        "features": [zone("boundary", "field", (-15.0, -15.0, 55.0, 15.0)), *buildings],
    }


LIDAR = (
    "lidar.enabled=true",
    "lidar.map_obstacles=false",
    "autonomy.cruise_speed_kmh=7",
    "autonomy.lookahead_m=2",
)


def localizer_of(robot: Robot) -> Localizer:
    return next(a for a in robot.daemon.supervisor.actors if isinstance(a, Localizer))


async def start_on_the_street(robot: Robot) -> Localizer:
    await robot.call("load_map", map=street_map())
    await robot.call("set_waypoints", waypoints=[at(0, 0), at(40, 0)])
    await until_armable(robot.ctx)
    await robot.call("patrol_start")
    localizer = localizer_of(robot)

    def on_the_lidar() -> bool:
        pose = robot.ctx.bus.last(topics.POSE)
        return pose is not None and pose.source.endswith("+lidar") and robot.status.waypoint == 1

    await wait_until(on_the_lidar, 40)
    return localizer


def error_m(robot: Robot) -> float:
    """From the pose the patrol follows to the true vehicle's position."""
    pose, truth = robot.poses[-1]
    return math.dist(robot.local(pose.latitude, pose.longitude), truth)


async def test_a_spoofed_gps_jump_is_refused_and_the_robot_keeps_its_route(
    robot_factory: Any,
) -> None:
    robot: Robot = await robot_factory(*LIDAR)
    trace = []
    def on_lidar(p):
        att = robot.ctx.bus.last(topics.ATTITUDE)
        loc = localizer_of(robot)
        trace.append((p.time, p.source, round(math.degrees(p.yaw_rad)), round(att.yaw_deg) if att else None, round(math.degrees(robot.vehicle.pose().yaw_rad)), loc.last.source if loc.last else None, loc.last.reason if loc.last else None, loc.map_refusal))
    robot.ctx.bus.subscribe(topics.LIDAR_POSE, on_lidar)
    localizer = await start_on_the_street(robot)
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
    # The robot drives on along the street to the far waypoint, then back, on the lidar.
    try:
        await wait_until(lambda: robot.status.waypoint == 0, 60)
    except TimeoutError:
        for pose, truth in robot.poses[::5]:
            print(f"{pose.time:.1f} {pose.source} est {robot.local(pose.latitude, pose.longitude)} truth {truth} sig {pose.sigma_xy_m:.2f} yaw {math.degrees(pose.yaw_rad):.0f} age {pose.fix_age_s}")
        print(robot.history())
        for t in trace: print("TR", t)
        raise
    for t in trace: print("TR", t)
    for pose, truth in robot.poses[::5]:
        print(f"{pose.time:.1f} {pose.source} est {robot.local(pose.latitude, pose.longitude)} truth {truth} sig {pose.sigma_xy_m:.2f} yaw {math.degrees(pose.yaw_rad):.0f} age {pose.fix_age_s}")
    after = robot.poses[spoofed_at:]
    assert after
    assert max(abs(truth[1]) for _pose, truth in after) < 3.0  # never left the street
    errors = [math.dist(robot.local(pose.latitude, pose.longitude), truth) for pose, truth in after]
    assert max(errors) < 4.0, max(errors)  # a followed spoof would be 30 m
    sources = [pose.source for pose, _ in after]
    assert "gps+imu" not in sources and sources.count("map+lidar") > len(sources) / 2
    assert all(robot.local(fix.latitude, fix.longitude)[1] < 15 for fix in followed)
    holds = {r.reason for r in robot.reports[reported_at:] if r.state == "holding"}
    assert all(reason.startswith("planning the path") for reason in holds), holds
