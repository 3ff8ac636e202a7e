"""Obstacles the lidar sees become temporary keep-outs of the patrol's map (issue 30).

Each scan's obstacles (clusters, :mod:`brasidas.perception.proximity`) are placed on the map
with the robot's pose at the scan. One seen in two scans within a second, not inside (or
within ``MATCH_M`` of) a keep-out the map already has, is added as keep-out ``lidar:N`` (a
disc around it); one not seen for ``FORGET_S`` is removed. The patrol re-plans around them in
its planner process, or holds saying why when no path is left (its "unreachable" reasons).
Changes go to the patrol at most every ``UPDATE_S``: within 1 s of an obstacle appearing,
within 3 s of it being gone.

Each track keeps a smoothed velocity (a cluster's centre jitters 0.1-0.2 m a scan as the view
of it changes: two scans give no speed, a few updates do). A person walking (faster than
``MOVING_MPS``) gets a keep-out stretched along the way they go, ``PREDICT_S`` ahead, redrawn
as they move (``REDRAW_M``): the patrol plans round where they are going, and a robot whose
way they are about to cross is inside it and holds for them, as a driver yields. Before, the
zone stayed where the person was first seen while they walked on. They are never written to ``map.file`` (the obstacle may be gone
by the next start), and the simulated lidar does not see them as walls.

The geometry (matching, the map's keep-out test) runs in a worker thread.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from shapely.geometry import LineString, Point, Polygon

from brasidas import topics
from brasidas.actor import Actor
from brasidas.autonomy.geo import LocalFrame
from brasidas.messages import PoseEstimate
from brasidas.perception.messages import RobotScan
from platformd.context import PlatformContext
from platformd.lidar_models import TEMPORARY_KEEPOUT_PREFIX

if TYPE_CHECKING:
    from brasidas.autonomy.areamap import AreaMap

_LOGGER = logging.getLogger(__name__)

MATCH_M = 1.0
"""A detection within this of a tracked obstacle is that obstacle again."""
CONFIRM_SCANS = 2
"""Seen in this many scans before it becomes a keep-out (a passing glitch does not)."""
FORGET_S = 2.0
"""Not seen for this long: gone."""
UPDATE_S = 0.5
"""At most one map change this often (each one is a re-plan)."""
MAX_ZONES = 24
"""Temporary keep-outs at most (the nearest are kept)."""
RANGE_M = 8.0
"""Only obstacles this near are mapped: far returns are thin and noisy."""
MIN_RADIUS_M = 0.25
VELOCITY_GAIN = 0.4
"""The share of each update's measured velocity taken into the track's smoothed one."""
MAX_SPEED_MPS = 3.0
"""A faster jump between updates is a mismatch or a jittery centre, not a walk: capped."""
MOVING_MPS = 0.5
"""A track this fast (smoothed) is moving: its zone is stretched along its way."""
PREDICT_S = 1.5
"""How far ahead a moving obstacle's zone reaches, in seconds of its velocity."""
REDRAW_M = 0.5
"""A zone is redrawn when its track has moved (or its predicted end) this far from it."""
ROBOT_CUT_M = 0.1
"""A new zone over the robot is applied without this much round it (:func:`clear_of_robot`)."""
MIN_CUT_AREA_M2 = 0.02


@dataclass
class Track:
    """One obstacle on the map (latitude, longitude; its radius)."""

    latitude: float
    longitude: float
    radius_m: float
    last_seen: float
    seen: int = 1
    zone_id: str | None = None
    """Its keep-out's id once added."""
    velocity: tuple[float, float] = (0.0, 0.0)
    """Smoothed, metres a second east and north in the area map's frame."""
    drawn: tuple[float, float, float, float] | None = None
    """Where its zone was drawn: the area map's x, y and the predicted end's."""

    @property
    def moving(self) -> bool:
        return math.hypot(*self.velocity) >= MOVING_MPS


@dataclass
class ZoneChanges:
    add: list[dict[str, Any]] = field(default_factory=list)
    remove: list[str] = field(default_factory=list)
    redrawn: dict[str, str] = field(default_factory=dict)
    """New zone id: the one it replaces (kept if the change is refused)."""


class ObstacleZones(Actor):
    """Keeps the patrol's temporary keep-outs in step with what the lidar sees."""

    name = "obstacle_zones"

    def __init__(self, ctx: PlatformContext, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self._clock = clock
        self.tracks: list[Track] = []
        self._ids = itertools.count(1)
        self._scan: RobotScan | None = None
        self._wake = asyncio.Event()
        self.updates = 0
        self.failures = 0

    async def run(self) -> None:
        self.subscribe(topics.LIDAR_SCAN, self._on_scan)
        while True:
            await self._wake.wait()
            self._wake.clear()
            scan, pose = self._scan, self.bus.last(topics.POSE)
            patrol = self.ctx.patrol
            area = patrol.area if patrol is not None else None
            if scan is None or pose is None or area is None or patrol is None:
                continue
            changes = await asyncio.to_thread(self.track, scan, pose, area, self._clock())
            if changes.add or changes.remove:
                await self._apply(changes)
            await asyncio.sleep(UPDATE_S)  # scans meanwhile: the newest is taken next

    def _on_scan(self, scan: RobotScan) -> None:
        self._scan = scan
        self._wake.set()

    def track(self, scan: RobotScan, pose: PoseEstimate, area: AreaMap, now: float) -> ZoneChanges:
        """(Worker thread.) Match the scan's obstacles to the tracks; what to add and remove."""
        here = LocalFrame(pose.latitude, pose.longitude)
        cos_yaw, sin_yaw = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        for obstacle in scan.obstacles:
            if math.hypot(obstacle.x_m, obstacle.y_m) > RANGE_M:
                continue
            # Robot frame (x forward, y left) to east/north.
            east = cos_yaw * obstacle.x_m - sin_yaw * obstacle.y_m
            north = sin_yaw * obstacle.x_m + cos_yaw * obstacle.y_m
            latitude, longitude = here.to_geo(east, north)
            x, y = area.local(latitude, longitude)
            radius = max(MIN_RADIUS_M, obstacle.radius_m)
            if _known(area, x, y, radius):
                continue  # on the map already (a building's wall)
            track = self._nearest(area, x, y)
            if track is None:
                self.tracks.append(Track(latitude, longitude, radius, now))
            else:
                _follow(track, area, x, y, now)
                track.latitude, track.longitude = latitude, longitude
                track.radius_m = max(track.radius_m * 0.8, radius)
                track.last_seen = now
                track.seen += 1
        changes = ZoneChanges()
        kept: list[Track] = []
        for track in self.tracks:
            if now - track.last_seen > FORGET_S:
                if track.zone_id is not None:
                    changes.remove.append(track.zone_id)
                continue
            kept.append(track)
        self.tracks = kept
        zones = sum(1 for t in kept if t.zone_id is not None)
        for track in kept:
            if track.zone_id is None and track.seen >= CONFIRM_SCANS and zones < MAX_ZONES:
                track.zone_id = f"{TEMPORARY_KEEPOUT_PREFIX}{next(self._ids)}"
                changes.add.append(_feature(track, area))
                zones += 1
            elif track.zone_id is not None and _moved(track, area):
                old = track.zone_id
                track.zone_id = f"{TEMPORARY_KEEPOUT_PREFIX}{next(self._ids)}"
                changes.remove.append(old)
                changes.add.append(_feature(track, area))
                changes.redrawn[track.zone_id] = old
        return changes

    def _nearest(self, area: AreaMap, x: float, y: float) -> Track | None:
        best, best_d = None, MATCH_M
        for track in self.tracks:
            tx, ty = area.local(track.latitude, track.longitude)
            d = math.hypot(tx - x, ty - y)
            if d <= best_d:
                best, best_d = track, d
        return best

    async def _apply(self, changes: ZoneChanges) -> None:
        patrol = self.ctx.patrol
        if patrol is None:
            return
        area = patrol.area
        present = set(area.keepouts) if area is not None else set()
        remove = [zone for zone in changes.remove if zone in present]
        try:
            await patrol.update_map(changes.add, remove, store=False)
        except ValueError as err:  # MapError: e.g. the robot is inside one (it moved)
            self.failures += 1
            _LOGGER.warning("obstacle keep-outs not applied: %s", err)
            added = {f["id"] for f in changes.add}
            for track in self.tracks:
                if track.zone_id is not None and track.zone_id in added:
                    # A redrawn zone keeps its old one (still on the map), a new one is none.
                    track.zone_id = changes.redrawn.get(track.zone_id)
            return
        self.updates += 1
        _LOGGER.info(
            "obstacle keep-outs: %s", ", ".join(
                [f"+{f['id']}" for f in changes.add] + [f"-{z}" for z in remove]
            ),
        )  # fmt: skip


def _known(area: AreaMap, x: float, y: float, radius: float) -> bool:
    disc = Point(x, y).buffer(radius + MATCH_M * 0.5)
    for zone_id, keepout in area.keepouts.items():
        if not zone_id.startswith(TEMPORARY_KEEPOUT_PREFIX) and keepout.intersects(disc):
            return True
    return False


def _follow(track: Track, area: AreaMap, x: float, y: float, now: float) -> None:
    """The track's smoothed velocity, from where it was to ``x``, ``y`` (the map's frame)."""
    dt = now - track.last_seen
    if dt <= 0.0:
        return
    tx, ty = area.local(track.latitude, track.longitude)
    vx, vy = (x - tx) / dt, (y - ty) / dt
    speed = math.hypot(vx, vy)
    if speed > MAX_SPEED_MPS:
        vx, vy = vx * MAX_SPEED_MPS / speed, vy * MAX_SPEED_MPS / speed
    ox, oy = track.velocity
    track.velocity = (ox + VELOCITY_GAIN * (vx - ox), oy + VELOCITY_GAIN * (vy - oy))


def _reach(track: Track, area: AreaMap) -> tuple[float, float, float, float]:
    """Where the track is and where its zone reaches to (itself when not moving)."""
    x, y = area.local(track.latitude, track.longitude)
    if not track.moving:
        return x, y, x, y
    vx, vy = track.velocity
    return x, y, x + vx * PREDICT_S, y + vy * PREDICT_S


def _moved(track: Track, area: AreaMap) -> bool:
    """Its zone no longer covers where it is, or where it goes."""
    if track.drawn is None:
        return False
    x, y, ex, ey = _reach(track, area)
    dx, dy, dex, dey = track.drawn
    return math.hypot(x - dx, y - dy) > REDRAW_M or math.hypot(ex - dex, ey - dey) > REDRAW_M


def _feature(track: Track, area: AreaMap) -> dict[str, Any]:
    """Its keep-out: a disc, stretched along its way when it moves."""
    reach = _reach(track, area)
    track.drawn = reach
    x, y, ex, ey = reach
    shape = Point(x, y) if (ex, ey) == (x, y) else LineString([(x, y), (ex, ey)])
    ring = []
    for px, py in shape.buffer(track.radius_m, quad_segs=2).exterior.coords:
        latitude, longitude = area.frame.to_geo(px, py)
        ring.append([round(longitude, 8), round(latitude, 8)])
    return {
        "type": "Feature",
        "id": track.zone_id,
        "properties": {"role": "keepout", "source": "lidar"},
        "geometry": {"type": "Polygon", "coordinates": [ring]},
    }


def clear_of_robot(
    features: Sequence[Mapping[str, Any]], area: AreaMap, latitude: float, longitude: float
) -> list[Mapping[str, Any]]:
    """(Worker thread.) The lidar's new zones without the part under the robot
    (``ROBOT_CUT_M`` round it): a post it is passing close to still enters the plan, which then
    keeps the path off it, and neither that zone nor the others' are refused because the robot
    is in one (before, the whole update was, and the planner did not know the post it passed)."""
    x, y = area.local(latitude, longitude)
    spot = Point(x, y)
    kept: list[Mapping[str, Any]] = []
    for feature in features:
        ring = feature["geometry"]["coordinates"][0]
        zone = Polygon([area.local(lat, lon) for lon, lat in ring])
        if not zone.contains(spot):
            kept.append(feature)
            continue
        rest = zone.difference(spot.buffer(ROBOT_CUT_M, quad_segs=4))
        parts = [rest] if isinstance(rest, Polygon) else list(getattr(rest, "geoms", []))
        part = max(parts, key=lambda g: g.area, default=None)
        if part is None or part.area < MIN_CUT_AREA_M2:
            continue  # (almost) all of it under the robot: its body, not a post beside it
        coords = []
        for px, py in part.exterior.coords:
            lat, lon = area.frame.to_geo(px, py)
            coords.append([round(lon, 8), round(lat, 8)])
        kept.append(dict(feature) | {"geometry": {"type": "Polygon", "coordinates": [coords]}})
    return kept


def start(ctx: PlatformContext) -> ObstacleZones:
    zones = ObstacleZones(ctx)
    ctx.telemetry.add_counters(
        "obstacle_zones", lambda: {"updates": zones.updates, "failures": zones.failures}
    )
    ctx.supervisor.start(zones)
    return zones
