"""The localization actor: GPS fixes, the IMU's yaw and the motors' command in, ``POSE`` out.

It owns a :class:`~brasidas.autonomy.localization.PoseFilter` in a local frame centred on the
first fix and publishes the pose ``autonomy.rate_hz`` times a second. It is the only
publisher of ``POSE``: a SLAM actor would take its place without the patrol noticing.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable

from brasidas import topics
from brasidas.actor import Actor
from brasidas.autonomy.geo import LocalFrame, heading_to_yaw
from brasidas.autonomy.localization import FilterParameters, PoseFilter
from brasidas.bus import Bus
from brasidas.messages import Attitude, GpsFix, MotionState, PoseEstimate

_LOGGER = logging.getLogger(__name__)


class Localization(Actor):
    name = "localization"

    def __init__(
        self,
        bus: Bus,
        parameters: FilterParameters,
        *,
        rate_hz: float,
        clock: Callable[[], float] | None = None,
    ) -> None:
        super().__init__(bus)
        self.filter = PoseFilter(parameters)
        self.period = 1.0 / rate_hz
        self._clock = clock
        self.frame: LocalFrame | None = None
        self._last_fix: float | None = None
        self.fixes = 0

    async def run(self) -> None:
        if self._clock is None:
            self._clock = asyncio.get_running_loop().time
        self.start()
        while True:
            await asyncio.sleep(self.period)
            self.publish()

    def start(self) -> None:
        """Subscribe to the sensors (retained values arrive at once)."""
        self.subscribe(topics.GPS_FIX, self._on_fix)
        self.subscribe(topics.ATTITUDE, self._on_attitude)
        self.subscribe(topics.MOTION_STATE, self._on_motion)

    def publish(self) -> PoseEstimate | None:
        """Publish the pose now (none before the first fix)."""
        if self.frame is None or not self.filter.initialized:
            return None
        now = self._now()
        estimate = self.filter.estimate(now)
        latitude, longitude = self.frame.to_geo(estimate.x, estimate.y)
        pose = PoseEstimate(
            time=now,
            latitude=latitude,
            longitude=longitude,
            x_m=estimate.x,
            y_m=estimate.y,
            origin=(self.frame.latitude, self.frame.longitude),
            yaw_rad=estimate.yaw,
            speed_mps=estimate.speed,
            sigma_xy_m=estimate.sigma_xy,
            sigma_heading_deg=math.degrees(estimate.sigma_yaw),
            heading_known=estimate.heading_known,
            fix_age_s=None if self._last_fix is None else now - self._last_fix,
        )
        self.bus.publish(topics.POSE, pose)
        return pose

    def _now(self) -> float:
        assert self._clock is not None
        return self._clock()

    def _on_fix(self, fix: GpsFix) -> None:
        now = self._now()
        if self.frame is None:
            self.frame = LocalFrame(fix.latitude, fix.longitude)
            _LOGGER.info("localization: frame origin %.7f, %.7f", fix.latitude, fix.longitude)
        x, y = self.frame.to_local(fix.latitude, fix.longitude)
        course = heading_to_yaw(fix.course_deg) if fix.course_deg is not None else None
        self.filter.gps(now, x, y, fix.hdop, fix.speed_mps, course)
        self._last_fix = now
        self.fixes += 1

    def _on_attitude(self, attitude: Attitude) -> None:
        self.filter.imu_yaw(self._now(), math.radians(attitude.yaw_deg))

    def _on_motion(self, state: MotionState) -> None:
        self.filter.command(self._now(), state.command.linear, state.command.angular)
