"""A patrol driven in a kinematic simulation, faster than real time (tests and ``make bench``).

The simulated vehicle's model and the simulated GPS's error model (through its NMEA and the
real decoder), the IMU's yaw, and the real pose filter and patrol, all on one fake clock:
no actors, no ptys. The full platform's tests drive the real drivers instead.
"""

from __future__ import annotations

import datetime as dt
import math
import random
from dataclasses import dataclass

from brasidas.autonomy.areamap import AreaMap
from brasidas.autonomy.geo import heading_to_yaw
from brasidas.autonomy.localization import Estimate, FilterParameters, PoseFilter
from brasidas.autonomy.patrol import Command, Patrol
from brasidas.codecs.nmea import EpochAssembler, NmeaDecoder
from brasidas.messages import GpsFix
from platformd.sim.gps import NEO_6M, NmeaGenerator, ReceiverErrors
from platformd.sim.vehicle import Pose, VehicleModel

UTC0 = dt.datetime(2026, 1, 1, 12, 0, tzinfo=dt.UTC)


@dataclass(frozen=True)
class Tick:
    time: float
    truth: Pose
    truth_xy: tuple[float, float]
    """The true position in the map's frame."""
    receiver_xy: tuple[float, float]
    """Where the simulated receiver puts it (the truth plus the receiver's own error): the
    best any estimator on the robot can do, with the receiver as its only absolute reference."""
    estimate: Estimate | None
    command: Command


class KinematicRun:
    """One vehicle, one patrol: :meth:`tick` advances everything by ``period`` seconds."""

    def __init__(
        self,
        patrol: Patrol,
        area: AreaMap,
        *,
        vehicle: VehicleModel | None = None,
        start: tuple[float, float] | None = None,
        heading_deg: float = 0.0,
        max_speed_mps: float = 6.0 / 3.6,
        max_yaw_rate: float = 1.5,
        seed: int = 1,
        period: float = 0.1,
        receiver: ReceiverErrors = NEO_6M,
        gps_sigma_m: float = FilterParameters.gps_sigma_m,
        gps_jitter_m: float = FilterParameters.gps_jitter_m,
    ) -> None:
        """``receiver``: the simulated receiver's error; ``gps_sigma_m``, ``gps_jitter_m``:
        what the pose filter is told of it (``autonomy.gps_sigma_m``, ``gps_jitter_m``)."""
        self.now = 0.0
        self.period = period
        latitude, longitude = (
            start if start is not None else (area.frame.latitude, area.frame.longitude)
        )
        self.vehicle = vehicle or VehicleModel(
            latitude=latitude,
            longitude=longitude,
            heading_deg=heading_deg,
            max_speed_mps=max_speed_mps,
            max_yaw_rate_rad_s=max_yaw_rate,
            clock=lambda: self.now,
        )
        self.patrol = patrol
        self.area = area
        self.filter = PoseFilter(
            FilterParameters(
                max_speed=max_speed_mps,
                max_yaw_rate=max_yaw_rate,
                gps_sigma_m=gps_sigma_m,
                gps_jitter_m=gps_jitter_m,
            )
        )
        self.gps = NmeaGenerator(random.Random(seed), receiver)
        self.gps_on = True
        self._decoder = NmeaDecoder()
        self._epochs = EpochAssembler()
        self._yaw0 = heading_to_yaw(heading_deg)
        self._last_fix = -math.inf

    def tick(self) -> Tick:
        self.now += self.period
        truth = self.vehicle.pose()
        self.filter.imu_yaw(self.now, truth.yaw_rad - self._yaw0)
        if self.gps_on:
            for message in self._decoder.feed(
                self.gps.epoch(truth, UTC0 + dt.timedelta(seconds=self.now))
            ):
                for fix in self._epochs.feed(message, self.now):
                    self._fix(fix)
            for fix in self._epochs.poll(self.now + 1.0):
                self._fix(fix)
        estimate = self.filter.estimate(self.now) if self.filter.initialized else None
        fix_age = self.now - self._last_fix if estimate is not None else None
        command = self.patrol.step(estimate, fix_age)
        self.vehicle.set_command(command.linear, command.angular)
        self.filter.command(self.now, command.linear, command.angular)
        x, y = self.area.local(truth.latitude, truth.longitude)
        east, north = self.gps.error
        return Tick(self.now, truth, (x, y), (x + east, y + north), estimate, command)

    def _fix(self, fix: GpsFix | None) -> None:
        if fix is None:
            return
        x, y = self.area.local(fix.latitude, fix.longitude)
        course = heading_to_yaw(fix.course_deg) if fix.course_deg is not None else None
        self.filter.gps(self.now, x, y, fix.hdop, fix.speed_mps, course)
        self._last_fix = self.now
