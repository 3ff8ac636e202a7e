"""CARMEN robot logs (the format of the public 2-D SLAM benchmark logs): sans-IO reader and
writer of the lines a lidar replay needs.

Lines read (fields separated by blanks; ``#`` starts a comment; other message types are
skipped and counted)::

    FLASER n r1 .. rn  x y theta  odom_x odom_y odom_theta  ipc_timestamp ipc_hostname logger_timestamp
    ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode
        n r1 .. rn  m v1 .. vm  laser_x laser_y laser_theta  robot_x robot_y robot_theta
        tv rv forward_safety_dist side_safety_dist turn_axis  ipc_timestamp ipc_hostname logger_timestamp
    ODOM x y theta tv rv accel  ipc_timestamp ipc_hostname logger_timestamp

Angles are radians counter-clockwise, x forward and y left of the robot, ranges metres. A
FLASER scan spans 180° from -90° (right) in ``n`` equal steps (181 readings: 1°, 361: 0.5°;
an even count: 180°/n). The laser pose (``x y theta``) is the log's best pose (corrected,
where the log was), the odometry the robot's own dead reckoning. A malformed line is dropped
and counted with its line number and why, never an exception.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

MAX_READINGS = 4096
MAX_LINE = 65536
FLASER_MAX_RANGE_M = 81.0
"""FLASER lines carry no maximum range: readings this far are the SICK's "nothing"."""


@dataclass(frozen=True)
class CarmenScan:
    time: float
    """The logger's timestamp (seconds)."""
    angles_rad: tuple[float, ...]
    """Of each reading, counter-clockwise from the robot's forward axis."""
    ranges_m: tuple[float, ...]
    max_range_m: float
    pose: tuple[float, float, float]
    """The laser's pose as logged (x, y, theta)."""
    odometry: tuple[float, float, float]


@dataclass(frozen=True)
class CarmenOdometry:
    time: float
    x_m: float
    y_m: float
    theta_rad: float
    speed_mps: float
    turn_rad_s: float


@dataclass
class CarmenLog:
    scans: list[CarmenScan] = field(default_factory=list)
    odometry: list[CarmenOdometry] = field(default_factory=list)
    skipped: dict[str, int] = field(default_factory=dict)
    """Other message types, by name, counted."""
    malformed: list[tuple[int, str]] = field(default_factory=list)
    """(line number, why) of each line dropped."""


class _Bad(ValueError):
    pass


def flaser_angles(n: int) -> tuple[float, ...]:
    step = math.pi / (n - 1) if n % 2 == 1 and n > 1 else math.pi / max(1, n)
    return tuple(-math.pi / 2 + i * step for i in range(n))


def parse(lines: Iterable[str]) -> CarmenLog:
    """Every line of a log (its text split in lines)."""
    log = CarmenLog()
    for number, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        words = text.split()
        kind = words[0]
        try:
            if len(text) > MAX_LINE:
                raise _Bad(f"longer than {MAX_LINE} characters")
            if kind == "FLASER":
                log.scans.append(_flaser(words))
            elif kind == "ROBOTLASER1":
                log.scans.append(_robotlaser(words))
            elif kind == "ODOM":
                x, y, theta, tv, rv = _floats(words, 1, 5)
                log.odometry.append(CarmenOdometry(_time(words), x, y, theta, tv, rv))
            else:
                log.skipped[kind] = log.skipped.get(kind, 0) + 1
        except _Bad as err:
            log.malformed.append((number, f"{kind}: {err}"))
    return log


def _floats(words: Sequence[str], start: int, count: int) -> list[float]:
    if start + count > len(words):
        raise _Bad(f"{len(words)} fields, too few")
    try:
        values = [float(w) for w in words[start : start + count]]
    except ValueError:
        raise _Bad(f"not a number in fields {start}-{start + count - 1}") from None
    if not all(math.isfinite(v) for v in values):
        raise _Bad("a value that is not finite")
    return values


def _count(words: Sequence[str], index: int) -> int:
    if index >= len(words):
        raise _Bad("truncated")
    try:
        n = int(words[index])
    except ValueError:
        raise _Bad(f"count {words[index]!r} is not a whole number") from None
    if not 0 < n <= MAX_READINGS:
        raise _Bad(f"{n} readings (1-{MAX_READINGS})")
    return n


def _time(words: Sequence[str]) -> float:
    """The logger timestamp: the last field (the IPC one before the host name if missing)."""
    (value,) = _floats(words, len(words) - 1, 1)
    return value


def _flaser(words: Sequence[str]) -> CarmenScan:
    n = _count(words, 1)
    ranges = _floats(words, 2, n)
    x, y, theta, ox, oy, otheta = _floats(words, 2 + n, 6)
    if len(words) != 2 + n + 6 + 3:
        raise _Bad(f"{len(words)} fields for {n} readings (expected {2 + n + 9})")
    return CarmenScan(
        _time(words),
        flaser_angles(n),
        tuple(ranges),
        FLASER_MAX_RANGE_M,
        (x, y, theta),
        (ox, oy, otheta),
    )


def _robotlaser(words: Sequence[str]) -> CarmenScan:
    start, fov, resolution, max_range = _floats(words, 2, 4)
    n = _count(words, 8)
    ranges = _floats(words, 9, n)
    m_at = 9 + n
    m = int(_floats(words, m_at, 1)[0])
    if not 0 <= m <= MAX_READINGS:
        raise _Bad(f"{m} remissions")
    pose_at = m_at + 1 + m
    lx, ly, ltheta, rx, ry, rtheta = _floats(words, pose_at, 6)
    if len(words) != pose_at + 6 + 5 + 3:
        raise _Bad(f"{len(words)} fields for {n} readings and {m} remissions")
    if resolution <= 0 or fov <= 0:
        raise _Bad("field of view and resolution must be positive")
    return CarmenScan(
        _time(words),
        tuple(start + i * resolution for i in range(n)),
        tuple(ranges),
        max_range,
        (lx, ly, ltheta),
        (rx, ry, rtheta),
    )


def format_flaser(
    ranges_m: Sequence[float],
    pose: tuple[float, float, float],
    odometry: tuple[float, float, float],
    time: float,
    host: str = "brasidas-sim",
) -> str:
    """One FLASER line (readings as :func:`flaser_angles` lays them out)."""
    readings = " ".join(f"{r:.3f}" for r in ranges_m)
    poses = " ".join(f"{v:.6f}" for v in (*pose, *odometry))
    return f"FLASER {len(ranges_m)} {readings} {poses} {time:.6f} {host} {time:.6f}"


def format_odom(
    pose: tuple[float, float, float],
    speed_mps: float,
    turn_rad_s: float,
    time: float,
    host: str = "brasidas-sim",
) -> str:
    x, y, theta = pose
    return (
        f"ODOM {x:.6f} {y:.6f} {theta:.6f} {speed_mps:.4f} {turn_rad_s:.4f} 0.0 "
        f"{time:.6f} {host} {time:.6f}"
    )
