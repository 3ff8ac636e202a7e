"""A simulated drive on a stepped clock: truth, scans, gyro and GPS fixes, no I/O (issue 30).

For the localization's tests and ``make bench perception``: the vehicle model follows
waypoints (steered from its true pose, as a driver would), the lidar simulator's own
:class:`~platformd.sim.lidar.ScanGenerator` casts every frame from the pose at its moment (a
moving scan is skewed), and the frames go through the real decoder, scan assembler and
:func:`~brasidas.perception.proximity.to_robot`, as the reader's do. GPS fixes carry the GPS
simulator's NEO-6M error process (:class:`~platformd.sim.gps.NmeaGenerator`). Time is
simulated, so a minute's drive takes a few seconds.
"""

from __future__ import annotations

import datetime as dt
import math
import random
from dataclasses import dataclass

import numpy as np
import numpy.random  # NumPy imports it on first use: on the loop, in the first scan
from shapely.geometry import Polygon, box

from brasidas.codecs.ldlidar import FRAME_BYTES, LidarDecoder, ScanAssembler
from brasidas.config.lidar import LidarSection
from brasidas.perception.messages import RobotScan
from brasidas.perception.proximity import Geometry, to_robot
from platformd.sim.gps import NEO_6M, NmeaGenerator, ReceiverErrors
from platformd.sim.lidar import LidarWorld, ScanGenerator
from platformd.sim.vehicle import Pose, VehicleModel

MAX_SPEED_MPS = 6.0 / 3.6
EPOCH = dt.datetime(2026, 1, 1, tzinfo=dt.UTC)


def street_buildings(
    blocks: int = 4, pitch_m: float = 20.0, building_m: float = 12.0
) -> list[Polygon]:
    """Square buildings on a grid, streets between them; the origin is at a crossing."""
    half = building_m / 2
    centres = [
        ((i + 0.5) * pitch_m, (j + 0.5) * pitch_m)
        for i in range(-blocks, blocks)
        for j in range(-blocks, blocks)
    ]
    return [box(cx - half, cy - half, cx + half, cy + half) for cx, cy in centres]


def street_grid(blocks: int = 4, pitch_m: float = 20.0, building_m: float = 12.0) -> LidarWorld:
    """:func:`street_buildings`, and a post at the kerb of each block."""
    polygons = [(b, 0.6) for b in street_buildings(blocks, pitch_m, building_m)]
    posts = [(4.0 + 20.0 * k, 2.5, 0.15, 0.5) for k in range(-blocks, blocks)]
    return LidarWorld(polygons, posts)


def loop_waypoints(side_m: float = 40.0) -> list[tuple[float, float]]:
    """A square loop along the streets from the origin, counter-clockwise."""
    return [(side_m, 0.0), (side_m, side_m), (0.0, side_m), (0.0, 0.0)]


@dataclass(frozen=True)
class DriveStep:
    """One revolution of the sensor, and what the other sensors said meanwhile."""

    time: float
    truth: Pose
    scan: RobotScan
    speed_command_mps: float
    """The commanded forward speed (the odometry's prior: the drive is open loop)."""
    gyro_rad_s: float
    gps: tuple[float, float] | None
    """A fix (metres east, north) if one came during the revolution (1 Hz)."""


class SimulatedDrive:
    """Steps the vehicle, the lidar and the GPS; :meth:`step` returns the next revolution."""

    def __init__(
        self,
        world: LidarWorld,
        waypoints: list[tuple[float, float]],
        *,
        speed_mps: float = 1.0,
        model: str = "ld19",
        seed: int = 1,
        receiver: ReceiverErrors = NEO_6M,
        gyro_noise_rad_s: float = 0.005,
    ) -> None:
        self.now = 0.0
        self.vehicle = VehicleModel(heading_deg=90.0, max_speed_mps=MAX_SPEED_MPS, clock=self._t)
        self.config = LidarSection(enabled=True, model=model, mount_x_m=0.0, min_points=3)
        self.generator = ScanGenerator(self.config, world, rng=np.random.default_rng(seed))
        self.geometry = Geometry(self.config, 4.2, MAX_SPEED_MPS)
        self.decoder = LidarDecoder()
        self.assembler = ScanAssembler()
        self.gps = NmeaGenerator(random.Random(seed), receiver)
        self.rng = random.Random(seed + 1)
        self.waypoints = list(waypoints)
        self.target = 0
        self.speed_mps = speed_mps
        self.gyro_noise = gyro_noise_rad_s
        self.gyro_bias = self.rng.gauss(0.0, 0.002)
        self.next_fix = 1.0
        self.laps = 0
        self._last_start = -1
        """The last frame's start angle (0.01 degree): where the assembler's revolution wraps."""

    def _t(self) -> float:
        return self.now

    def step(self) -> DriveStep:
        """Advance to the end of the next revolution."""
        frame_s = self.generator.model.frame_period_s
        gyro: list[float] = []
        command = 0.0
        fix: tuple[float, float] | None = None
        while True:
            # Drive through the frames up to the one that starts the next revolution (the
            # assembler's wrap), then cast them in one batch, each from its own pose.
            times: list[float] = []
            xs: list[float] = []
            ys: list[float] = []
            yaws: list[float] = []
            for start in self.generator.next_starts():
                self.now += frame_s
                pose = self.vehicle.pose()
                command = self._steer(pose)
                gyro.append(pose.yaw_rate_rad_s)
                if self.now >= self.next_fix:
                    self.next_fix += 1.0
                    self.gps.epoch(pose, EPOCH + dt.timedelta(seconds=self.now))
                    east, north = self.gps.error
                    fix = (pose.x_m + east, pose.y_m + north)
                times.append(self.now)
                xs.append(pose.x_m)
                ys.append(pose.y_m)
                yaws.append(pose.yaw_rad)
                wrapped = 0 <= self._last_start and start < self._last_start
                self._last_start = start
                if wrapped:
                    break
            data = self.generator.batch(times, xs, ys, yaws)
            scan = None
            for i, now in enumerate(times):
                for frame in self.decoder.feed(data[i * FRAME_BYTES : (i + 1) * FRAME_BYTES], now):
                    scan = self.assembler.feed(frame) or scan
            if scan is not None:
                noise = self.rng.gauss(0.0, self.gyro_noise)
                return DriveStep(
                    time=self.now,
                    truth=pose,
                    scan=to_robot(scan, self.geometry),
                    speed_command_mps=command,
                    gyro_rad_s=sum(gyro) / len(gyro) + self.gyro_bias + noise,
                    gps=fix,
                )

    def _steer(self, pose: Pose) -> float:
        tx, ty = self.waypoints[self.target]
        distance = math.hypot(tx - pose.x_m, ty - pose.y_m)
        if distance < 1.0:
            self.target = (self.target + 1) % len(self.waypoints)
            self.laps += self.target == 0
            tx, ty = self.waypoints[self.target]
        error = math.atan2(ty - pose.y_m, tx - pose.x_m) - pose.yaw_rad
        error = math.atan2(math.sin(error), math.cos(error))
        speed = self.speed_mps * max(0.0, math.cos(error)) ** 4
        self.vehicle.set_command(speed / MAX_SPEED_MPS, max(-1.0, min(1.0, 1.5 * error)))
        return self.vehicle.command[0] * MAX_SPEED_MPS
