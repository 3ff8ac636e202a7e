"""Pose from GPS fixes, the IMU's yaw and the commanded motion: a small extended Kalman filter.

State: x, y (metres east and north in a local frame), yaw (counter-clockwise from east) and
forward speed. Between fixes the pose is dead-reckoned: the speed follows the commanded speed
with the vehicle's lag, the yaw turns at the IMU's rate (or the commanded rate without an
IMU). A fix corrects the position; while moving, its course and speed correct yaw and speed.

Two figures describe a fix. Its absolute error (``gps_sigma_m``, about 2 m per axis for a
NEO-6M) wanders over minutes: consecutive fixes share it, so averaging them does not remove it,
and nothing on a GPS-only robot can observe it. The filter therefore weights fixes by their
fix-to-fix noise (``gps_jitter_m``: the receiver's own navigation filter smooths its output)
and tracks where the receiver puts the robot, and :attr:`Estimate.sigma_xy` adds the absolute
error back: it is the uncertainty against the ground and the map, the figure a clearance from
keep-out zones must cover.
The IMU has no magnetometer, so the heading is unknown until the robot has driven a little:
the first course over ground sets it (:attr:`Estimate.heading_known`).

Sans-IO: every input carries its time (seconds, any monotonic clock). The matrices are 4x4 at
most, in plain Python: the platform localizes without a map, and NumPy would cost it ~15 MB.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from brasidas.autonomy.geo import wrap

UNKNOWN_YAW_SIGMA = math.pi
HEADING_KNOWN_SIGMA = math.radians(15.0)
MIN_COURSE_SPEED = 0.4
"""GPS course is used only above this speed (m/s): slower, it is noise."""
MAX_STEP_S = 0.5
"""A longer gap is integrated in steps of this length."""

Matrix = list[list[float]]


@dataclass(frozen=True)
class Estimate:
    """The filter's pose at ``time``."""

    time: float
    x: float
    y: float
    yaw: float
    """Counter-clockwise from east, radians, (-pi, pi]."""
    speed: float
    """Forward, m/s (negative reversing)."""
    sigma_xy: float
    """One standard deviation of the position against the ground (metres, the larger axis):
    the filter's own uncertainty plus the receiver's absolute error."""
    sigma_yaw: float
    """One standard deviation of the yaw (radians)."""

    @property
    def heading_known(self) -> bool:
        return self.sigma_yaw < HEADING_KNOWN_SIGMA


@dataclass(frozen=True)
class FilterParameters:
    max_speed: float
    """m/s at linear = 1."""
    max_yaw_rate: float
    """rad/s at angular = 1."""
    lag_s: float = 0.25
    """Time constant of the speed's response to a command."""
    gps_sigma_m: float = 2.1
    """Absolute position error of a fix at HDOP 1, one axis, 1 sigma (NEO-6M: 2.5 m CEP)."""
    gps_jitter_m: float = 0.5
    """Fix-to-fix position noise at HDOP 1: what the filter weights a fix by."""
    position_noise: float = 0.05
    """Process noise: m²/s of position drift (wheel slip, the model's errors)."""
    yaw_noise_gyro: float = 0.0005
    """rad²/s of yaw drift while the IMU's rate is used."""
    yaw_noise_commanded: float = 0.05
    """rad²/s of yaw drift while only the commanded turn rate is known."""
    speed_noise: float = 0.1
    """(m/s)²/s."""
    gyro_timeout_s: float = 0.5
    """The IMU's rate is used for this long after its last reading."""


class PoseFilter:
    def __init__(self, parameters: FilterParameters) -> None:
        self.p = parameters
        self._t: float | None = None
        self._state = [0.0, 0.0, 0.0, 0.0]
        self._cov = _diag([1e6, 1e6, UNKNOWN_YAW_SIGMA**2, 1.0])
        self._initialized = False
        self._command = (0.0, 0.0)
        self._gyro_rate: float | None = None
        self._gyro_time = -math.inf
        self._imu_yaw: tuple[float, float] | None = None
        self._heading_set = False
        self._absolute_var = 0.0

    @property
    def initialized(self) -> bool:
        """A fix has been seen: the position means something."""
        return self._initialized

    def command(self, t: float, linear: float, angular: float) -> None:
        """The motors' command changed (normalized, [-1, 1])."""
        self._predict(t)
        self._command = (linear * self.p.max_speed, angular * self.p.max_yaw_rate)

    def imu_yaw(self, t: float, yaw: float) -> None:
        """The IMU's yaw (radians, relative to its own start): its change is the turn rate."""
        if self._imu_yaw is not None:
            last_t, last_yaw = self._imu_yaw
            if t > last_t:
                rate = wrap(yaw - last_yaw) / (t - last_t)
                # The rate over the interval that just ended is exact for that interval.
                self._gyro_rate, self._gyro_time = rate, last_t
                self._predict(t)
                self._gyro_time = t
        self._imu_yaw = (t, yaw)

    def gps(
        self,
        t: float,
        x: float,
        y: float,
        hdop: float | None = None,
        speed: float | None = None,
        course_yaw: float | None = None,
    ) -> None:
        """A fix at (x, y) in the local frame; course over ground as an ENU yaw, if known."""
        dilution = max(1.0, hdop or 1.0)
        sigma = self.p.gps_jitter_m * dilution
        self._absolute_var = (self.p.gps_sigma_m * dilution) ** 2
        if not self._initialized:
            self._t = t
            self._state[0:2] = (x, y)
            _clear(self._cov, 0)
            _clear(self._cov, 1)
            self._cov[0][0] = self._cov[1][1] = sigma**2
            self._initialized = True
        else:
            self._predict(t)
            self._update(0, x - self._state[0], sigma**2)
            self._update(1, y - self._state[1], sigma**2)
        if speed is not None and speed >= MIN_COURSE_SPEED and course_yaw is not None:
            reversing = self._state[3] < -0.1
            measured = wrap(course_yaw + math.pi) if reversing else course_yaw
            sigma_yaw = min(0.5, max(0.03, 0.15 / speed))
            if not self._heading_set:
                # First heading: take it as it is (a linearized update from "unknown"
                # would drag the position along with it).
                self._state[2] = measured
                _clear(self._cov, 2)
                self._cov[2][2] = sigma_yaw**2
                self._heading_set = True
            else:
                self._update(2, wrap(measured - self._state[2]), sigma_yaw**2)
        if speed is not None:
            signed = -speed if self._state[3] < -0.1 else speed
            self._update(3, signed - self._state[3], 0.1**2)

    def estimate(self, t: float) -> Estimate:
        """The pose at ``t`` (dead-reckoned from the last input)."""
        self._predict(t)
        x, y, yaw, speed = self._state
        # The position covariance's larger eigenvalue (2x2 symmetric, its lower triangle).
        a, b, d = self._cov[0][0], self._cov[1][0], self._cov[1][1]
        largest = (a + d) / 2.0 + math.hypot((a - d) / 2.0, b)
        sigma_xy = math.sqrt(max(0.0, largest) + self._absolute_var)
        sigma_yaw = math.sqrt(max(0.0, self._cov[2][2]))
        return Estimate(t, x, y, wrap(yaw), speed, sigma_xy, min(sigma_yaw, UNKNOWN_YAW_SIGMA))

    def _predict(self, t: float) -> None:
        if self._t is None:
            self._t = t
            return
        remaining = t - self._t
        if remaining <= 0:
            return
        self._t = t
        while remaining > 1e-9:
            dt = min(remaining, MAX_STEP_S)
            remaining -= dt
            self._step(dt, t - remaining)

    def _step(self, dt: float, t: float) -> None:
        x, y, yaw, v = self._state
        v_cmd, w_cmd = self._command
        gyro = self._gyro_rate is not None and t - self._gyro_time <= self.p.gyro_timeout_s
        rate = self._gyro_rate if gyro and self._gyro_rate is not None else w_cmd
        keep = math.exp(-dt / self.p.lag_s)
        new_v = v_cmd + (v - v_cmd) * keep
        mean_v = (v + new_v) / 2.0
        mid_yaw = yaw + rate * dt / 2.0
        cos_y, sin_y = math.cos(mid_yaw), math.sin(mid_yaw)
        self._state = [x + mean_v * cos_y * dt, y + mean_v * sin_y * dt, yaw + rate * dt, new_v]
        # P' = F P F' + Q, with F the identity but for the yaw's and the speed's effect on the
        # position and the speed's lag: written out (this runs at the IMU's rate).
        dmean_dv = (1.0 + keep) / 2.0
        a = -mean_v * sin_y * dt if self._heading_set else 0.0  # d x / d yaw
        b = mean_v * cos_y * dt if self._heading_set else 0.0  # d y / d yaw
        c = cos_y * dt * dmean_dv  # d x / d v
        d = sin_y * dt * dmean_dv  # d y / d v
        p0, p1, p2, p3 = self._cov
        rows = [
            [p0[m] + a * p2[m] + c * p3[m] for m in range(4)],
            [p1[m] + b * p2[m] + d * p3[m] for m in range(4)],
            list(p2),
            [keep * p3[m] for m in range(4)],
        ]
        yaw_noise = self.p.yaw_noise_gyro if gyro else self.p.yaw_noise_commanded
        q = (
            self.p.position_noise * dt,
            self.p.position_noise * dt,
            yaw_noise * dt,
            self.p.speed_noise * dt,
        )
        cov = [
            [r[0] + a * r[2] + c * r[3], r[1] + b * r[2] + d * r[3], r[2], keep * r[3]]
            for r in rows
        ]
        for i in range(4):
            cov[i][i] += q[i]
        self._cov = cov
        if self._cov[2][2] > UNKNOWN_YAW_SIGMA**2:
            self._cov[2][2] = UNKNOWN_YAW_SIGMA**2

    def _update(self, i: int, innovation: float, variance: float) -> None:
        """A measurement of state variable ``i`` with noise ``variance`` (independent
        measurements, one after the other, make the joint update)."""
        cov = self._cov
        column = [row[i] for row in cov]
        s = column[i] + variance
        gain = [c / s for c in column]
        self._state = [v + g * innovation for v, g in zip(self._state, gain, strict=True)]
        self._state[2] = wrap(self._state[2])
        # P - K H P: symmetric as written (the outer product of P's column with itself).
        self._cov = [[cov[r][m] - gain[r] * column[m] for m in range(4)] for r in range(4)]


def _diag(values: list[float]) -> Matrix:
    return [[v if i == j else 0.0 for j in range(len(values))] for i, v in enumerate(values)]


def _clear(cov: Matrix, i: int) -> None:
    """Zero row and column ``i``."""
    cov[i] = [0.0] * len(cov)
    for row in cov:
        row[i] = 0.0
