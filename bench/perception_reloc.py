"""The relocalization rows of ``make bench perception``: a robot without GPS placed in its
saved map, and patrolling on it.

- **relocalization** (:func:`relocalization_rows`, no I/O): a saved grid surveyed from the
  simulator's world (:mod:`platformd.sim.survey`: a mapping drive's scans at known poses),
  then ``BENCH_PERCEPTION_RELOC_STARTS`` (default 30) seeded starts anywhere in its free space
  at any heading, each one LD19 scan (range noise, a tenth of the returns dropped)
  searched for in the whole grid (:mod:`brasidas.perception.relocalize`). Counted: placed
  within 0.3 m and 3° (right), placed further off (wrong: must be 0), refused (ambiguous or
  no fit, the robot holds); the error of the right ones; the search's thread CPU. In the
  16 m room of the platform's tests, and in the street grid of look-alike buildings (where
  refusing is the right answer for most starts).
- **GPS-less patrol** (:func:`gpsless_patrol_rows`, real time, the whole --sim daemon): the
  room's saved map, the robot started 10 m and 90° from its saved pose with GPS off; the
  time until it is placed, then ``BENCH_PERCEPTION_GPSLESS_LAPS`` (default 3) laps of a
  4-waypoint route in latitude and longitude: waypoints reached, the patrol's pose against
  the simulator's truth (mean, max).
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.support import percentiles
from brasidas.perception.odometry import Pose2D
from brasidas.perception.relocalize import GridRelocalizer
from platformd.sim.drive import street_grid
from platformd.sim.lidar import LidarWorld
from platformd.sim.survey import ROOM_POSTS, ROOM_WALLS, cast_scan, survey, world_of

STARTS = int(os.environ.get("BENCH_PERCEPTION_RELOC_STARTS", "30"))
LAPS = int(os.environ.get("BENCH_PERCEPTION_GPSLESS_LAPS", "3"))
LAT, LON = 37.9415, 23.6530
RIGHT_M = 0.3
RIGHT_RAD = math.radians(3.0)
DROPOUT = 0.1
SAVED = Pose2D(-8.0, -2.0, 0.0)
START = Pose2D(0.0, 4.0, math.pi / 2)
ROUTE = ((-4.0, 4.0), (-4.0, -3.0), (1.0, -3.0), (1.0, 2.0))


def room_survey() -> list[Pose2D]:
    """A circle and a sweep through the room, ending at the saved pose."""
    circle = [
        Pose2D(-2.7 + 2.7 * math.cos(t), 2.7 * math.sin(t), t + math.pi / 2)
        for t in np.linspace(0.0, 2 * math.pi, 41)
    ]
    sweep = [Pose2D(-9.0 + 0.6 * k, -1.0 + (k % 3), 0.0) for k in range(20)]
    return [*circle, *sweep, SAVED]


def street_survey() -> list[Pose2D]:
    """Along the streets of the 40 m loop and the cross streets beside it, every 0.5 m."""
    poses = []
    for y in (0.0, 20.0, 40.0):
        poses += [Pose2D(x, y, 0.0) for x in np.arange(-20.0, 60.0, 0.5)]
    for x in (0.0, 20.0, 40.0):
        poses += [Pose2D(x, y, math.pi / 2) for y in np.arange(-20.0, 60.0, 0.5)]
    return poses


def _starts(world: LidarWorld, poses: list[Pose2D], seed: int, spread_m: float) -> dict[str, Any]:
    grid = survey(world, poses, LAT, LON)
    relocalizer = GridRelocalizer(grid)
    rng = np.random.default_rng(seed)
    right: list[float] = []
    wrong: list[float] = []
    refused: dict[str, int] = {}
    cpu: list[float] = []
    wall: list[float] = []
    for _ in range(STARTS):
        base = poses[int(rng.integers(len(poses)))]
        truth = Pose2D(
            base.x_m + rng.uniform(-spread_m, spread_m),
            base.y_m + rng.uniform(-spread_m, spread_m),
            rng.uniform(-math.pi, math.pi),
        )
        scan = cast_scan(world, truth, rng)
        scan = scan[rng.random(len(scan)) >= DROPOUT]
        started = time.perf_counter()
        answer = relocalizer.locate(scan)
        wall.append(time.perf_counter() - started)
        cpu.append(answer.seconds)
        if answer.pose is None:
            kind = answer.reason.split(":")[0].split(" (")[0]
            refused[kind] = refused.get(kind, 0) + 1
            continue
        error = math.hypot(answer.pose.x_m - truth.x_m, answer.pose.y_m - truth.y_m)
        turn = abs(math.remainder(answer.pose.yaw_rad - truth.yaw_rad, 2 * math.pi))
        (right if error <= RIGHT_M and turn <= RIGHT_RAD else wrong).append(error)
    return {
        "starts": STARTS,
        "placed_right": len(right),
        "placed_wrong": len(wrong),
        "refused": refused,
        "error_m_mean": round(float(np.mean(right)), 3) if right else None,
        "error_m_max": round(max(right), 3) if right else None,
        "search_cpu_s": percentiles(cpu),
        "search_wall_s": percentiles(wall),
        "candidate_positions": len(relocalizer.positions()),
        "loadavg_1m": round(os.getloadavg()[0], 2),
    }


def relocalization_rows() -> dict[str, Any]:
    return {
        "relocalization_room": _starts(world_of(ROOM_WALLS, ROOM_POSTS), room_survey(), 11, 4.0),
        "relocalization_street_grid": _starts(street_grid(), street_survey(), 12, 1.5),
    }


async def gpsless_patrol_rows() -> dict[str, Any]:
    """The room, its saved map, the --sim daemon without GPS: placed, then patrolling."""
    from brasidas import topics
    from brasidas.autonomy.geo import LocalFrame
    from brasidas.config import PlatformConfig, load_config
    from brasidas.messages import PoseEstimate
    from platformd.app import PlatformDaemon
    from platformd.lidar_localization import Localizer
    from platformd.sim.lidar import load_obstacles, world_polygons
    from platformd.sim.survey import obstacles_geojson

    frame = LocalFrame(LAT, LON)
    folder = Path(tempfile.mkdtemp(prefix="bench-gpsless-"))
    room = folder / "room.geojson"
    room.write_text(json.dumps(obstacles_geojson(LAT, LON, ROOM_WALLS, ROOM_POSTS)))
    polygons, discs = world_polygons(frame, None, load_obstacles(str(room)))
    survey(LidarWorld(polygons, discs), room_survey(), LAT, LON).save(folder / "grid.npz")

    def geo(x: float, y: float) -> list[float]:
        lat, lon = frame.to_geo(x, y)
        return [lon, lat]

    corners = [(-12.0, -9.0), (6.0, -9.0), (6.0, 9.0), (-12.0, 9.0), (-12.0, -9.0)]
    area = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "id": "room",
                "properties": {"role": "boundary"},
                "geometry": {"type": "Polygon", "coordinates": [[geo(*c) for c in corners]]},
            }
        ],
    }
    latitude, longitude = frame.to_geo(START.x_m, START.y_m)
    config = load_config(
        PlatformConfig,
        None,
        [
            "signaling.port=0", "velocity.port=0", "beacon.enabled=false",
            "navcam.enabled=false", "audio.enabled=false", "sim.enabled=true",
            "motor.enabled=true", "gps.enabled=false", "imu.enabled=true",
            "lidar.enabled=true", "lidar.map_obstacles=false", "autonomy.autostart=false",
            "autonomy.cruise_speed_kmh=7", "autonomy.lookahead_m=2", "autonomy.clearance_m=1.5",
            f"lidar.grid_file={folder / 'grid.npz'}", f"sim.obstacles_file={room}",
            f"sim.latitude={latitude:.9f}", f"sim.longitude={longitude:.9f}",
            "sim.heading_deg=0", f"map.file={folder / 'map.geojson'}",
            f"autonomy.route_file={folder / 'route.json'}",
        ],
    )  # fmt: skip
    daemon = PlatformDaemon(config, None)
    started = time.monotonic()
    await daemon.start()
    errors: list[float] = []
    arrivals = 0
    try:
        ctx = daemon.ctx
        vehicle = ctx.sim.vehicle
        assert vehicle is not None
        localizer = next(a for a in daemon.supervisor.actors if isinstance(a, Localizer))

        def on_pose(pose: PoseEstimate) -> None:
            truth = vehicle.pose()
            here = frame.to_local(truth.latitude, truth.longitude)
            errors.append(math.dist(frame.to_local(pose.latitude, pose.longitude), here))

        await _until(lambda: localizer.fused is not None, 60)
        placed_s = time.monotonic() - started
        fused = localizer.fused
        assert fused is not None
        truth = vehicle.pose()
        placed_error = math.dist(
            (fused.x_m, fused.y_m), frame.to_local(truth.latitude, truth.longitude)
        )
        unsubscribe = ctx.bus.subscribe(topics.POSE, on_pose)
        await ctx.rpc.call_local("load_map", map=area)
        waypoints = ["{:.8f},{:.8f}".format(*frame.to_geo(x, y)) for x, y in ROUTE]
        await ctx.rpc.call_local("set_waypoints", waypoints=waypoints)
        arming = ctx.arming
        assert arming is not None
        await _until(lambda: not arming.reasons(), 30)
        await ctx.rpc.call_local("patrol_start")
        seen: list[tuple[int | None, int]] = []

        def status() -> tuple[int | None, int]:
            report = ctx.bus.last(topics.PATROL_STATUS)
            assert report is not None
            key = (report.waypoint, report.lap)
            if not seen or seen[-1] != key:
                seen.append(key)
            return key

        patrol_started = time.monotonic()
        await _until(lambda: status()[1] >= LAPS, 60.0 * LAPS)
        arrivals = len(seen) - 1
        unsubscribe()
        patrol_s = time.monotonic() - patrol_started
    finally:
        await daemon.stop()
    return {
        "gpsless_patrol": {
            "placed_after_s": round(placed_s, 2),
            "placed_error_m": round(placed_error, 3),
            "laps": LAPS,
            "waypoints_reached": arrivals,
            "patrol_s": round(patrol_s, 1),
            "pose_error_m_mean": round(float(np.mean(errors)), 3),
            "pose_error_m_max": round(max(errors), 3),
            "map_lost": localizer.placer.losses if localizer.placer is not None else None,
            "loadavg_1m": round(os.getloadavg()[0], 2),
        }
    }


async def _until(predicate: Any, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"not within {timeout:g} s")
        await asyncio.sleep(0.05)


if __name__ == "__main__":
    print(relocalization_rows())
    print(asyncio.run(gpsless_patrol_rows()))
