"""Madgwick's gradient-descent orientation filter, gyro + accelerometer (no magnetometer).

S. Madgwick, "An efficient orientation filter for inertial and inertial/magnetic sensor
arrays" (2010), the IMU variant: the gyro rates are integrated as a quaternion and a
gradient step of size ``beta`` pulls the estimated gravity towards the measured one, which
corrects roll and pitch drift. Yaw has no reference and drifts with the gyro bias.

The quaternion ``(w, x, y, z)`` turns body vectors into world vectors (world: x east, y north,
z up, REP-103); body: x forward, y left, z up. Pure and allocation-light: 100 Hz costs a few
tens of microseconds per sample.
"""

from __future__ import annotations

import math

Quaternion = tuple[float, float, float, float]


class Madgwick:
    """The filter's state: feed :meth:`update` with each sample."""

    def __init__(self, beta: float = 0.05, q: Quaternion = (1.0, 0.0, 0.0, 0.0)) -> None:
        self.beta = beta
        """Gradient step (rad/s): the gyro error it corrects; higher trusts gravity more."""
        self.q = q
        self.initialized = False

    def reset(self, q: Quaternion = (1.0, 0.0, 0.0, 0.0)) -> None:
        self.q = q
        self.initialized = False

    def update(
        self,
        gyro: tuple[float, float, float],
        accel: tuple[float, float, float],
        dt: float,
    ) -> Quaternion:
        """One sample: gyro in rad/s, accel in any unit (only its direction counts), dt in s.

        The first sample with an accelerometer reading sets roll and pitch directly, so the
        filter does not spend seconds converging from level.
        """
        ax, ay, az = accel
        if not self.initialized and (ax or ay or az):
            self.q = from_gravity(ax, ay, az)
            self.initialized = True
            return self.q
        gx, gy, gz = gyro
        q0, q1, q2, q3 = self.q
        # Rate of change of the quaternion from the gyroscope.
        d0 = 0.5 * (-q1 * gx - q2 * gy - q3 * gz)
        d1 = 0.5 * (q0 * gx + q2 * gz - q3 * gy)
        d2 = 0.5 * (q0 * gy - q1 * gz + q3 * gx)
        d3 = 0.5 * (q0 * gz + q1 * gy - q2 * gx)
        norm = math.sqrt(ax * ax + ay * ay + az * az)
        if norm > 0.0:
            ax, ay, az = ax / norm, ay / norm, az / norm
            # Gradient of the error between estimated and measured gravity direction.
            _2q0, _2q1, _2q2, _2q3 = 2.0 * q0, 2.0 * q1, 2.0 * q2, 2.0 * q3
            _4q0, _4q1, _4q2 = 4.0 * q0, 4.0 * q1, 4.0 * q2
            _8q1, _8q2 = 8.0 * q1, 8.0 * q2
            q0q0, q1q1, q2q2, q3q3 = q0 * q0, q1 * q1, q2 * q2, q3 * q3
            s0 = _4q0 * q2q2 + _2q2 * ax + _4q0 * q1q1 - _2q1 * ay
            s1 = (
                _4q1 * q3q3
                - _2q3 * ax
                + 4.0 * q0q0 * q1
                - _2q0 * ay
                - _4q1
                + _8q1 * q1q1
                + _8q1 * q2q2
                + _4q1 * az
            )
            s2 = (
                4.0 * q0q0 * q2
                + _2q0 * ax
                + _4q2 * q3q3
                - _2q3 * ay
                - _4q2
                + _8q2 * q1q1
                + _8q2 * q2q2
                + _4q2 * az
            )
            s3 = 4.0 * q1q1 * q3 - _2q1 * ax + 4.0 * q2q2 * q3 - _2q2 * ay
            s_norm = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2 + s3 * s3)
            if s_norm > 0.0:
                beta = self.beta / s_norm
                d0 -= beta * s0
                d1 -= beta * s1
                d2 -= beta * s2
                d3 -= beta * s3
        q0 += d0 * dt
        q1 += d1 * dt
        q2 += d2 * dt
        q3 += d3 * dt
        self.q = normalized((q0, q1, q2, q3))
        return self.q


def normalized(q: Quaternion) -> Quaternion:
    w, x, y, z = q
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    if norm == 0.0:
        return (1.0, 0.0, 0.0, 0.0)
    return (w / norm, x / norm, y / norm, z / norm)


def from_gravity(ax: float, ay: float, az: float) -> Quaternion:
    """The orientation with zero yaw whose gravity matches a (still) accelerometer reading."""
    roll = math.atan2(ay, az)
    pitch = math.atan2(-ax, math.hypot(ay, az))
    return from_euler(roll, pitch, 0.0)


def from_euler(roll: float, pitch: float, yaw: float) -> Quaternion:
    """Z-Y-X (yaw, then pitch, then roll) angles in radians to a quaternion."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def euler(q: Quaternion) -> tuple[float, float, float]:
    """Roll, pitch, yaw in radians (Z-Y-X); yaw counter-clockwise about z up."""
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def euler_deg(q: Quaternion) -> tuple[float, float, float]:
    roll, pitch, yaw = euler(q)
    return math.degrees(roll), math.degrees(pitch), math.degrees(yaw)
