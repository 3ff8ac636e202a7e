"""Autonomy on the platform: localization (``POSE``) and the patrol (``CMD_VEL``), issue 12."""

from __future__ import annotations

import math
from pathlib import Path

from brasidas import topics
from brasidas.autonomy.follower import FollowerParameters
from brasidas.autonomy.localization import FilterParameters
from brasidas.autonomy.patrol import PatrolParameters
from brasidas.codecs.telemetry_schema import Automation, Autonomy, Pose
from brasidas.config import PlatformConfig
from brasidas.security import state_dir
from platformd.autonomy.home import Home
from platformd.autonomy.localization import Localization
from platformd.autonomy.methods import PatrolMethods
from platformd.autonomy.patrol import PatrolActor, Storage
from platformd.context import PlatformContext
from platformd.sim.demo_area import demo_map, demo_route

TELEMETRY_PATH_POINTS = 30


def map_file(config: PlatformConfig) -> Path:
    """Where the patrol's map is stored (``map.file``, else in the state directory)."""
    return Path(config.map.file) if config.map.file else state_dir() / "map.geojson"


def preload(config: PlatformConfig) -> None:
    """The map parser, with Shapely, when a map loads at start (a stored one, or the --sim
    demo): the worker thread that parses it would import it meanwhile, holding the GIL the
    event loop waits for while it compiles and runs module code."""
    if (config.sim.enabled and config.sim.demo_map) or map_file(config).is_file():
        import brasidas.autonomy.areamap  # noqa: F401


async def async_setup(ctx: PlatformContext) -> None:
    config = ctx.config.autonomy
    full_speed = ctx.config.platform.max_speed_kmh / 3.6
    full_turn = math.radians(config.full_turn_rate_dps)
    localization = Localization(
        ctx.bus,
        FilterParameters(
            max_speed=full_speed,
            max_yaw_rate=full_turn,
            gps_sigma_m=config.gps_sigma_m,
            gps_jitter_m=config.gps_jitter_m,
        ),
        rate_hz=config.rate_hz,
        lidar_localized=ctx.config.lidar.enabled and ctx.config.lidar.odometry,
    )
    parameters = PatrolParameters(
        follower=FollowerParameters(
            cruise_speed=min(config.cruise_speed_kmh / 3.6, full_speed),
            max_turn_rate=math.radians(config.max_turn_rate_dps),
            full_speed=full_speed,
            full_turn_rate=full_turn,
            lookahead_m=config.lookahead_m,
            tolerance_m=config.arrival_tolerance_m,
            decel=config.decel_mps2,
        ),
        clearance_m=config.clearance_m,
        fix_stale_s=config.fix_stale_s,
        corridor_m=config.corridor_m,
    )
    storage = Storage(
        map_file=map_file(ctx.config),
        route_file=Path(config.route_file) if config.route_file else state_dir() / "route.json",
    )
    sim = ctx.config.sim
    patrol = PatrolActor(
        ctx.bus,
        parameters,
        storage,
        rate_hz=config.rate_hz,
        enabled=config.enabled,
        autostart=False,  # platformd.arming resumes it: pre-arm, countdown, the last word
        demo=(demo_map(sim.latitude, sim.longitude), demo_route())
        if sim.enabled and sim.demo_map
        else None,
        commands=ctx.commands,
    )
    await patrol.load()
    ctx.patrol = patrol
    PatrolMethods(patrol).register(ctx.rpc, ctx.authority)
    home = Home(ctx.bus, patrol)
    ctx.telemetry.register(Autonomy, lambda: _autonomy(patrol, home))
    ctx.telemetry.register(Pose, lambda: _pose(ctx))
    ctx.telemetry.register(Automation, lambda: _automation(ctx))
    ctx.supervisor.start(localization)
    ctx.supervisor.start(patrol)


def _autonomy(patrol: PatrolActor, home: Home) -> Autonomy:
    report = patrol.report
    where = home.current()
    return Autonomy(
        state=report.state.value,
        enabled=report.enabled,
        waypoint=report.waypoint,
        waypoints=report.waypoints,
        distance_m=report.distance_m,
        lap=report.lap,
        reason=report.reason,
        # A section must fit one datagram: the path's first points (get_patrol has them all).
        path=tuple(
            (round(lat, 7), round(lon, 7)) for lat, lon in report.path[:TELEMETRY_PATH_POINTS]
        ),
        map_rev=patrol.map_revision,
        map_error=patrol.map_error,
        home=() if where is None else (round(where[0], 7), round(where[1], 7)),
    )


def _pose(ctx: PlatformContext) -> Pose | None:
    pose = ctx.bus.last(topics.POSE)
    if pose is None:
        return None
    return Pose(
        lat=round(pose.latitude, 7),
        lon=round(pose.longitude, 7),
        heading=round(pose.heading_deg, 1) if pose.heading_known else None,
        speed=round(pose.speed_mps, 2),
        sigma_m=round(pose.sigma_xy_m, 2),
        fix_age_s=None if pose.fix_age_s is None else round(pose.fix_age_s, 1),
        source=pose.source,
    )


def _automation(ctx: PlatformContext) -> Automation:
    switches = ctx.bus.last(topics.AUTOMATIONS)
    return Automation(switches=switches.as_dict() if switches is not None else {})
