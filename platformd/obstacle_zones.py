"""Obstacles the lidar sees become temporary keep-outs of the patrol's map (issue 30).

Each scan's obstacles (clusters, :mod:`brasidas.perception.proximity`) are placed on the map
with the robot's pose at the scan. One seen in two scans within a second, not inside (or
within ``MATCH_M`` of) a keep-out the map already has, is added as keep-out ``lidar:N`` (a
disc around it); one not seen for ``FORGET_S`` is removed. The patrol re-plans around them in
its planner process, or holds saying why when no path is left (its "unreachable" reasons).
Changes go to the patrol at most every ``UPDATE_S``: within 1 s of an obstacle appearing,
within 3 s of it being gone. They are never written to ``map.file`` (the obstacle may be gone
by the next start), and the simulated lidar does not see them as walls.

The geometry (matching, the map's keep-out test) runs in a worker thread.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from shapely.geometry import Point

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


@dataclass
class ZoneChanges:
    add: list[dict[str, Any]] = field(default_factory=list)
    remove: list[str] = field(default_factory=list)


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
                changes.add.append(_feature(track))
                zones += 1
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
            for track in self.tracks:
                if any(f["id"] == track.zone_id for f in changes.add):
                    track.zone_id = None
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


def _feature(track: Track) -> dict[str, Any]:
    frame = LocalFrame(track.latitude, track.longitude)
    ring = []
    for k in range(9):
        angle = 2 * math.pi * k / 8
        latitude, longitude = frame.to_geo(
            track.radius_m * math.cos(angle), track.radius_m * math.sin(angle)
        )
        ring.append([round(longitude, 8), round(latitude, 8)])
    ring[-1] = ring[0]
    return {
        "type": "Feature",
        "id": track.zone_id,
        "properties": {"role": "keepout", "source": "lidar"},
        "geometry": {"type": "Polygon", "coordinates": [ring]},
    }


def start(ctx: PlatformContext) -> ObstacleZones:
    zones = ObstacleZones(ctx)
    ctx.telemetry.add_counters(
        "obstacle_zones", lambda: {"updates": zones.updates, "failures": zones.failures}
    )
    ctx.supervisor.start(zones)
    return zones
