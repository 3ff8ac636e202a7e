"""The simulated vehicle: a skid-steer rover driven by the simulated controller's outputs.

One model per simulated platform (:func:`vehicle_for`, kept in ``ctx.sim.vehicle``): the AX3500 simulator sets its
command from the controller's channel outputs, the GPS and IMU simulators read its pose. The
model integrates lazily, on read or write, on its own clock, so it costs nothing when idle
and tests can drive it with a fake clock.

Frames follow ROS REP-103: x east, y north, z up; ``yaw`` counter-clockwise from east, so a
positive angular command (turn left, R-2.2) increases it. ``heading_deg`` is the compass
heading (clockwise from north) that GPS course and the operator use.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from brasidas.config import PlatformConfig

EARTH_RADIUS_M = 6_371_000.0
GRAVITY = 9.80665


@dataclass(frozen=True)
class Pose:
    """The vehicle's state at ``time`` (the model's clock)."""

    time: float
    x_m: float
    """East of the origin."""
    y_m: float
    """North of the origin."""
    yaw_rad: float
    """Counter-clockwise from east, wrapped to (-pi, pi]."""
    speed_mps: float
    """Forward speed (negative when reversing)."""
    yaw_rate_rad_s: float
    """Counter-clockwise positive: what a z-up gyro reads."""
    accel_mps2: float
    """Forward (body x) acceleration."""
    lateral_accel_mps2: float
    """Body y (left) acceleration: the centripetal term of a turn."""
    latitude: float
    longitude: float
    altitude_m: float

    @property
    def heading_deg(self) -> float:
        """Compass heading: clockwise from north, in [0, 360)."""
        return (90.0 - math.degrees(self.yaw_rad)) % 360.0

    @property
    def course_deg(self) -> float:
        """Course over ground: the heading, turned round when reversing."""
        return self.heading_deg if self.speed_mps >= 0 else (self.heading_deg + 180.0) % 360.0


class VehicleModel:
    """A first-order skid-steer model: commands in [-1, 1] approach their speeds with a lag."""

    def __init__(
        self,
        *,
        latitude: float = 37.9415,
        longitude: float = 23.6530,
        altitude_m: float = 42.0,
        heading_deg: float = 0.0,
        max_speed_mps: float = 6.0 / 3.6,
        max_yaw_rate_rad_s: float = 1.5,
        time_constant_s: float = 0.25,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.origin = (latitude, longitude, altitude_m)
        self.max_speed = max_speed_mps
        self.max_yaw_rate = max_yaw_rate_rad_s
        self.tau = time_constant_s
        self._clock = clock
        # The emulated IMU samples the pose from its driver's thread while the other
        # simulators use the loop: integration steps must not interleave.
        self._lock = threading.Lock()
        self._t = clock()
        self._x = 0.0
        self._y = 0.0
        self._yaw = math.radians(90.0 - heading_deg)
        self._speed = 0.0
        self._yaw_rate = 0.0
        self._accel = 0.0
        self._target_speed = 0.0
        self._target_yaw_rate = 0.0

    def set_command(self, speed: float, steering: float) -> None:
        """Normalized forward speed and turn rate (positive = left), each clamped to [-1, 1]."""
        with self._lock:
            self._advance()
            self._target_speed = max(-1.0, min(1.0, speed)) * self.max_speed
            self._target_yaw_rate = max(-1.0, min(1.0, steering)) * self.max_yaw_rate

    @property
    def command(self) -> tuple[float, float]:
        """The last command, normalized (speed, steering)."""
        return (self._target_speed / self.max_speed, self._target_yaw_rate / self.max_yaw_rate)

    def pose(self) -> Pose:
        with self._lock:
            self._advance()
            return self._pose()

    def _pose(self) -> Pose:
        lat0, lon0, alt0 = self.origin
        latitude = lat0 + math.degrees(self._y / EARTH_RADIUS_M)
        longitude = lon0 + math.degrees(self._x / (EARTH_RADIUS_M * math.cos(math.radians(lat0))))
        return Pose(
            time=self._t,
            x_m=self._x,
            y_m=self._y,
            yaw_rad=math.atan2(math.sin(self._yaw), math.cos(self._yaw)),
            speed_mps=self._speed,
            yaw_rate_rad_s=self._yaw_rate,
            accel_mps2=self._accel,
            lateral_accel_mps2=self._speed * self._yaw_rate,
            latitude=latitude,
            longitude=longitude,
            altitude_m=alt0,
        )

    def _advance(self) -> None:
        now = self._clock()
        remaining = now - self._t
        self._t = now
        # Fixed sub-steps keep the integration honest after a long idle gap.
        while remaining > 1e-9:
            dt = min(remaining, 0.01)
            remaining -= dt
            blend = 1.0 - math.exp(-dt / self.tau)
            new_speed = self._speed + (self._target_speed - self._speed) * blend
            self._accel = (new_speed - self._speed) / dt
            self._yaw_rate += (self._target_yaw_rate - self._yaw_rate) * blend
            mean_speed = (self._speed + new_speed) / 2.0
            self._yaw += self._yaw_rate * dt
            self._x += mean_speed * math.cos(self._yaw) * dt
            self._y += mean_speed * math.sin(self._yaw) * dt
            self._speed = new_speed


def vehicle_for(config: PlatformConfig) -> VehicleModel:
    """The simulated vehicle where ``sim.*`` puts it, as fast as the platform's top speed."""
    sim = config.sim
    return VehicleModel(
        latitude=sim.latitude,
        longitude=sim.longitude,
        altitude_m=sim.altitude_m,
        heading_deg=sim.heading_deg,
        max_speed_mps=config.platform.max_speed_kmh / 3.6,
    )
