"""The localization actor: GPS fixes, the IMU's yaw and the motors' command in, ``POSE`` out.

It owns a :class:`~brasidas.autonomy.localization.PoseFilter` in a local frame centred on the
first fix and publishes the pose ``autonomy.rate_hz`` times a second. It is the only
publisher of ``POSE``.

With the lidar's localization on (``lidar.odometry``, ``lidar_localized``) the pose is the
lidar localization's (``LIDAR_POSE``: scan registration fused with the GPS fixes its gate
accepted, and the area map's walls) while it registers scans, carried forward to now; the
GPS+IMU filter stands in when it does not (no pose yet, scans on the motion prior, lidar
silent), and it too follows only the fixes the gate accepted (``GPS_ACCEPTED``): a fix
refused as a jump or a drag is never followed, by either. While the lidar localization says its
pose must not be driven on (``POSE_HOLD``: without GPS, not yet placed in a saved map tied to
latitude and longitude, or in a map frame of the robot's own) no pose is published.
"""

from __future__ import annotations

import asyncio
import bisect
import collections
import logging
import math
from collections.abc import Callable

from brasidas import topics
from brasidas.actor import Actor
from brasidas.autonomy.geo import LocalFrame, heading_to_yaw, wrap
from brasidas.autonomy.localization import FilterParameters, PoseFilter
from brasidas.bus import Bus
from brasidas.messages import Attitude, GpsFix, MotionState, PoseEstimate
from brasidas.perception.messages import LidarPose, PoseHold

_LOGGER = logging.getLogger(__name__)

LIDAR_POSE_AHEAD_S = 0.5
"""A lidar pose is carried forward at most this far (five scans): a lidar that stalls has its
motors held (platformd.lidar), and its pose's growing fix age holds the patrol."""
IMU_HISTORY = 200
"""The IMU's recent yaws kept to turn a late lidar pose by, at most this many ..."""
IMU_HISTORY_S = 5.0
"""... and none older than this: a scan is registered well within it even on a loaded machine,
and a history bounded in time stops growing within seconds at any IMU rate (at 5 Hz, 200
samples would keep growing for 40 s, which reads as a leak)."""
IMU_JUMP_RAD_S = math.radians(150.0)
"""A yaw change faster than any rover turns: the IMU's filter restarted, not a turn."""


class Localization(Actor):
    name = "localization"

    def __init__(
        self,
        bus: Bus,
        parameters: FilterParameters,
        *,
        rate_hz: float,
        clock: Callable[[], float] | None = None,
        lidar_localized: bool = False,
    ) -> None:
        super().__init__(bus)
        self.lidar_localized = lidar_localized
        self._lidar: LidarPose | None = None
        self.hold = ""
        """Why the lidar localization's pose must not be driven on (``POSE_HOLD``)."""
        self._imu: collections.deque[tuple[float, float]] = collections.deque(maxlen=IMU_HISTORY)
        """(time, yaw) of the IMU's recent attitudes, on this actor's clock."""
        self.filter = PoseFilter(parameters)
        self.period = 1.0 / rate_hz
        self._clock = clock
        self._monotonic = clock is None
        """On the loop's clock, ``time.monotonic``: the IMU's readings carry their time on it."""
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
        if self.lidar_localized:
            self.subscribe(topics.GPS_ACCEPTED, self._on_fix)
            self.subscribe(topics.POSE_HOLD, self._on_hold)
            self.subscribe(topics.LIDAR_POSE, self._on_lidar)
        else:
            self.subscribe(topics.GPS_FIX, self._on_fix)
        self.subscribe(topics.ATTITUDE, self._on_attitude)
        self.subscribe(topics.MOTION_STATE, self._on_motion)

    def publish(self) -> PoseEstimate | None:
        """Publish the pose now (none before the first fix)."""
        if self.frame is None:
            return None
        now = self._now()
        lidar = self._lidar
        if self.hold:  # not placed in a map tied to latitude and longitude: nothing to drive on
            return None
        if lidar is not None and lidar.measured_at is not None:
            return self._publish_lidar(now, self.frame, lidar)
        if not self.filter.initialized:
            return None
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

    def _publish_lidar(self, now: float, frame: LocalFrame, lidar: LidarPose) -> PoseEstimate:
        """The lidar pose carried forward to ``now``: along its heading at the filter's speed,
        turned by what the IMU turned since. The lidar pose is the scan's, late by the scan's
        registration (and more on a loaded machine: a map search); a patrol steering on a
        heading that lags the turn overshoots, and weaves, into what the lidar stops it for."""
        assert lidar.measured_at is not None
        speed = self.filter.estimate(now).speed if self.filter.initialized else 0.0
        until = min(now, lidar.time + LIDAR_POSE_AHEAD_S)
        ahead = speed * max(0.0, until - lidar.time)
        turn = self._imu_turn(lidar.time, until)
        yaw = wrap(lidar.yaw_rad + turn)
        x, y = frame.to_local(lidar.latitude, lidar.longitude)
        x += ahead * math.cos(lidar.yaw_rad + turn / 2)
        y += ahead * math.sin(lidar.yaw_rad + turn / 2)
        latitude, longitude = frame.to_geo(x, y)
        pose = PoseEstimate(
            time=now,
            latitude=latitude,
            longitude=longitude,
            x_m=x,
            y_m=y,
            origin=(frame.latitude, frame.longitude),
            yaw_rad=yaw,
            speed_mps=speed,
            sigma_xy_m=lidar.sigma_m,
            sigma_heading_deg=math.degrees(lidar.sigma_yaw_rad),
            heading_known=True,
            fix_age_s=now - lidar.measured_at,
            source=lidar.source,
        )
        self.bus.publish(topics.POSE, pose)
        return pose

    def _on_hold(self, hold: PoseHold) -> None:
        self.hold = hold.reason

    def _on_lidar(self, pose: LidarPose) -> None:
        self._lidar = pose
        if self.frame is None and not self.hold:
            self.frame = LocalFrame(pose.latitude, pose.longitude)

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
        # At the reading's own time: a loaded loop hands over the IMU's batches late and two
        # at once, and the yaw's change over their arrival times read as a turn of hundreds
        # of °/s, dead-reckoned into the heading until the next (tens of degrees off).
        now = attitude.stamp if self._monotonic else self._now()
        yaw = math.radians(attitude.yaw_deg)
        self.filter.imu_yaw(now, yaw)
        imu = self._imu
        imu.append((now, yaw))
        while imu[0][0] < now - IMU_HISTORY_S:
            imu.popleft()

    def _imu_turn(self, start: float, end: float) -> float:
        """What the IMU turned from ``start`` to ``end`` (0 without one, or across a restart
        of its filter)."""
        imu = self._imu
        if end <= start or len(imu) < 2 or imu[0][0] > start:
            return 0.0
        times = [t for t, _ in imu]

        def yaw_at(t: float) -> float:
            return imu[max(0, bisect.bisect_right(times, t) - 1)][1]

        turn = wrap(yaw_at(end) - yaw_at(start))
        if abs(turn) > IMU_JUMP_RAD_S * (end - start) + math.radians(5.0):
            return 0.0
        return turn

    def _on_motion(self, state: MotionState) -> None:
        self.filter.command(self._now(), state.command.linear, state.command.angular)
