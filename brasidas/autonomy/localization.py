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
            h = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]]
            innovation = [x - self._state[0], y - self._state[1]]
            self._update(h, innovation, _diag([sigma**2, sigma**2]))
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
                h = [[0.0, 0.0, 1.0, 0.0]]
                innovation = [wrap(measured - self._state[2])]
                self._update(h, innovation, [[sigma_yaw**2]])
        if speed is not None:
            h = [[0.0, 0.0, 0.0, 1.0]]
            signed = -speed if self._state[3] < -0.1 else speed
            self._update(h, [signed - self._state[3]], [[0.1**2]])

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
        f = _eye(4)
        dmean_dv = (1.0 + keep) / 2.0
        if self._heading_set:  # an unknown yaw must not leak into the position's covariance
            f[0][2] = -mean_v * sin_y * dt
            f[1][2] = mean_v * cos_y * dt
        f[0][3] = cos_y * dt * dmean_dv
        f[1][3] = sin_y * dt * dmean_dv
        f[3][3] = keep
        yaw_noise = self.p.yaw_noise_gyro if gyro else self.p.yaw_noise_commanded
        q = _diag(
            [
                self.p.position_noise * dt,
                self.p.position_noise * dt,
                yaw_noise * dt,
                self.p.speed_noise * dt,
            ]
        )
        self._cov = _add(_mul(_mul(f, self._cov), _t(f)), q)
        if self._cov[2][2] > UNKNOWN_YAW_SIGMA**2:
            self._cov[2][2] = UNKNOWN_YAW_SIGMA**2

    def _update(self, h: Matrix, innovation: list[float], noise: Matrix) -> None:
        """A linear measurement of one or two state variables (``h`` is 1x4 or 2x4)."""
        s = _add(_mul(_mul(h, self._cov), _t(h)), noise)
        gain = _mul(_mul(self._cov, _t(h)), _inverse(s))
        self._state = [
            v + sum(g * e for g, e in zip(row, innovation, strict=True))
            for v, row in zip(self._state, gain, strict=True)
        ]
        self._state[2] = wrap(self._state[2])
        # Joseph form: stays symmetric and positive under rounding.
        a = _add(_eye(4), _mul(gain, h), -1.0)
        self._cov = _add(_mul(_mul(a, self._cov), _t(a)), _mul(_mul(gain, noise), _t(gain)))


def _eye(n: int) -> Matrix:
    return _diag([1.0] * n)


def _diag(values: list[float]) -> Matrix:
    return [[v if i == j else 0.0 for j in range(len(values))] for i, v in enumerate(values)]


def _t(a: Matrix) -> Matrix:
    return [list(column) for column in zip(*a, strict=True)]


def _mul(a: Matrix, b: Matrix) -> Matrix:
    columns = list(zip(*b, strict=True))
    return [[sum(x * y for x, y in zip(row, col, strict=True)) for col in columns] for row in a]


def _add(a: Matrix, b: Matrix, scale: float = 1.0) -> Matrix:
    """a + scale * b."""
    return [
        [x + scale * y for x, y in zip(ra, rb, strict=True)] for ra, rb in zip(a, b, strict=True)
    ]


def _inverse(s: Matrix) -> Matrix:
    """The inverse of a 1x1 or 2x2 matrix (an innovation covariance: positive definite)."""
    if len(s) == 1:
        return [[1.0 / s[0][0]]]
    (a, b), (c, d) = s
    det = a * d - b * c
    return [[d / det, -b / det], [-c / det, a / det]]


def _clear(cov: Matrix, i: int) -> None:
    """Zero row and column ``i``."""
    cov[i] = [0.0] * len(cov)
    for row in cov:
        row[i] = 0.0
