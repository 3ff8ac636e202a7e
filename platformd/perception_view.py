"""What the platform shows of its lidar (issue 30): the ``lidar_view`` telemetry section, the
fused pose and the occupancy grid on the bus, and the ``get_grid`` signaling method.

Every snapshot carries the latest scan in 5° sectors and the fused pose on the globe
(:mod:`brasidas.perception.view`); the grid is too large for a datagram, so every
``lidar.grid_period_s`` while it grows it is reduced to a small image (in a thread: numpy work),
published on ``OCCUPANCY_GRID`` (the recorder writes it as ``foxglove.Grid``) and its revision
goes in the section; the station asks for it with ``get_grid`` when the revision moves. The
fused pose goes on ``FUSED_POSE`` (the recorder's ``/pose/fused``) at most
:data:`POSE_PERIOD_S`.

The localizer's grid is written by its worker thread. The image is made from the array and
origin read together on the loop, and dropped if either was replaced (the grid grew) while it
was being made: the next period makes it again.
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any, Protocol

from brasidas import topics
from brasidas.actor import Actor
from brasidas.bus import Bus
from brasidas.clock import Clock, sleep
from brasidas.codecs.jsonrpc import CallContext
from brasidas.codecs.telemetry_schema import LidarView
from brasidas.perception.messages import FusedPosition, RobotScan
from brasidas.perception.view import (
    GridImage,
    grid_image,
    heading_deg,
    sector_points,
    sector_ranges,
)

if TYPE_CHECKING:
    from platformd.context import PlatformContext
    from platformd.lidar_localization import Localizer


class LidarReader(Protocol):
    """What the view reads of platformd.lidar_reader's reader (which starts the view)."""

    clock: Clock
    last: RobotScan | None
    localizer: Localizer | None

    def as_shown(self, bearing_deg: float, range_m: float) -> tuple[float, float]: ...


POSE_PERIOD_S = 0.2
SCAN_SHOWN_S = 1.0
"""A scan older than this is not shown (the lidar went silent)."""


class PerceptionView(Actor):
    """Reads the lidar reader and its localizer; publishes what is shown of them."""

    name = "perception_view"

    def __init__(
        self,
        bus: Bus,
        reader: LidarReader,
        clock: Clock | None = None,
        grid_period_s: float = 5.0,
    ) -> None:
        super().__init__(bus)
        self.reader = reader
        self.clock: Clock = clock or reader.clock
        self.grid_period_s = grid_period_s
        self.grid_rev = 0
        self.grid: GridImage | None = None
        self._grid_scans = -1
        self._grid_at = -grid_period_s
        self._pose_time: float | None = None
        self.position: FusedPosition | None = None

    async def run(self) -> None:
        while True:
            self.publish_pose()
            now = self.clock.time()
            # The period counts from the last image made: a grid with nothing new, or one
            # that grew while its image was made, is looked at again at the next tick (the
            # console's first grid waited a whole period after the start's empty look).
            if now - self._grid_at >= self.grid_period_s and await self.refresh_grid():
                self._grid_at = now
            await sleep(self.clock, POSE_PERIOD_S)

    def publish_pose(self) -> None:
        localizer = self.reader.localizer
        fused = localizer.fused if localizer is not None else None
        frame = localizer.frame if localizer is not None else None
        if fused is None or frame is None or fused.time == self._pose_time:
            return
        self._pose_time = fused.time
        latitude, longitude = frame.to_geo(fused.x_m, fused.y_m)
        self.position = FusedPosition(
            fused.time,
            latitude,
            longitude,
            heading_deg(fused.yaw_rad),
            fused.x_m,
            fused.y_m,
            fused.yaw_rad,
            fused.sigma_m,
            fused.source,
        )
        self.bus.publish(topics.FUSED_POSE, self.position)

    async def refresh_grid(self) -> GridImage | None:
        """A new grid image when the grid took scans since the last one."""
        localizer = self.reader.localizer
        grid = localizer.grid if localizer is not None else None
        if grid is None or grid.scans == self._grid_scans:
            return None
        log_odds, origin, scans = grid.log_odds, grid.origin, grid.scans
        image = await asyncio.to_thread(
            grid_image,
            grid.latitude,
            grid.longitude,
            (float(origin[0]), float(origin[1])),
            grid.resolution,
            log_odds,
            scans,
        )
        if grid.log_odds is not log_odds or grid.origin is not origin or image is None:
            return None  # it grew meanwhile (origin and array no longer one pair): next time
        self._grid_scans = scans
        self.grid_rev += 1
        self.grid = image
        self.bus.publish(topics.OCCUPANCY_GRID, image)
        return image

    def section(self) -> LidarView:
        scan = self.reader.last
        fresh = scan is not None and self.clock.time() - scan.time <= SCAN_SHOWN_S
        position = self.position
        ranges: tuple[int, ...] = ()
        if fresh and scan is not None:
            # Around the pose shown with it (the robot moved since): the sectors, moved.
            shown = [
                self.reader.as_shown(bearing, distance)
                for bearing, distance in sector_points(
                    sector_ranges(scan.bearings_deg, scan.ranges_m)
                )
            ]
            ranges = sector_ranges([b for b, _ in shown], [d for _, d in shown])
        return LidarView(
            ranges_dm=ranges,
            fused_lat=round(position.latitude, 8) if position else None,
            fused_lon=round(position.longitude, 8) if position else None,
            fused_heading_deg=round(position.heading_deg, 1) if position else None,
            grid_rev=self.grid_rev,
        )

    async def get_grid(self, call: CallContext) -> dict[str, Any]:
        """The occupancy grid's latest image (``{"rev": 0}`` before the first)."""
        if self.grid is None:
            return {"rev": 0}
        return self.grid.to_json(self.grid_rev)


def start(ctx: PlatformContext, reader: LidarReader) -> PerceptionView:
    view = PerceptionView(ctx.bus, reader, grid_period_s=ctx.config.lidar.grid_period_s)
    ctx.telemetry.register(LidarView, view.section)
    ctx.rpc.add("get_grid", view.get_grid)
    ctx.supervisor.start(view)
    return view
