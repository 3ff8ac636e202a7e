"""Lidar odometry: each scan registered to a local map of the last ones (pure; run in a thread).

A 2-D scan becomes a 3-D cloud with z = 0, extruded to three layers (z = -0.2, 0, 0.2) so a
wall is a vertical plane to small_gicp's covariance estimation (a line of points at one height
has no plane to fit: its covariance would be degenerate in the wrong direction). Each scan is
registered by VGICP to a :class:`small_gicp.GaussianVoxelMap` of the scans so far, in the
odometry frame, starting from the motion prior; keyframes (every ``KEYFRAME_M`` or
``KEYFRAME_RAD``) are inserted into the map, whose voxels not seen for a while are forgotten
(LRU), so the map is local.

The motion prior is the commanded forward speed and the gyro's yaw rate over the interval
since the previous scan (the AX3500 runs open loop: there are no wheel encoders). The result
is the prior, said so, when:

- the scan has fewer than ``min_points`` returns (an empty field, a blinded sensor);
- the registration is degenerate: along a long straight wall (or between two parallel ones)
  one translation is unconstrained, seen as the smallest eigenvalue of the translation block
  of its Hessian falling under ``DEGENERATE_RATIO`` of the largest;
- it did not converge, matched too few points, or disagrees with the prior by more than the
  prior's own plausible error (a bad match is worse than dead reckoning).

Only the pose in the plane is kept (x, y, yaw): z, roll and pitch of the 3-D result are
dropped. Frames: x forward, y left of the robot; the odometry frame starts at the first scan.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import small_gicp
from numpy.typing import NDArray

from brasidas.autonomy.geo import wrap
from brasidas.perception.messages import RobotScan

LAYERS_M = (-0.2, 0.0, 0.2)
"""Heights the 2-D scan is extruded to (see the module's docstring)."""
KEYFRAME_M = 0.3
KEYFRAME_RAD = math.radians(10.0)
DEGENERATE_RATIO = 0.02
"""Smallest over largest eigenvalue of the translation Hessian below which one direction is
unconstrained (a corridor, a single wall)."""
MIN_INLIER_FRACTION = 0.4
MAX_ITERATIONS = 30
RESTART_AFTER = 5
"""Registrations failed in a row after which the local map is started afresh at the prior."""
DOWNSAMPLE_M = 0.08
VOXEL_M = 0.5
MAX_CORRESPONDENCE_M = 1.0
LRU_HORIZON = 60
"""Keyframes after which an unvisited voxel of the local map is dropped."""
PRIOR_SPEED_ERROR = 0.3
"""The open-loop prior's plausible error, as a fraction of the distance (skid, slope, load)."""
PRIOR_SLACK_M = 0.15
PRIOR_SLACK_RAD = math.radians(3.0)
"""The gyro is good to a fraction of a degree a scan: a registration turned more is wrong."""


@dataclass(frozen=True)
class Pose2D:
    x_m: float
    y_m: float
    yaw_rad: float

    def compose(self, delta: Pose2D) -> Pose2D:
        """This pose moved by ``delta`` (expressed in this pose's own frame)."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return Pose2D(
            self.x_m + c * delta.x_m - s * delta.y_m,
            self.y_m + s * delta.x_m + c * delta.y_m,
            wrap(self.yaw_rad + delta.yaw_rad),
        )

    def between(self, other: Pose2D) -> Pose2D:
        """``other`` in this pose's frame (so ``self.compose(self.between(other)) == other``)."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        dx, dy = other.x_m - self.x_m, other.y_m - self.y_m
        return Pose2D(c * dx + s * dy, -s * dx + c * dy, wrap(other.yaw_rad - self.yaw_rad))

    def matrix(self) -> NDArray[np.float64]:
        """As a 4x4 homogeneous transform in the plane z = 0."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        t = np.eye(4)
        t[:2, :2] = ((c, -s), (s, c))
        t[0, 3], t[1, 3] = self.x_m, self.y_m
        return t

    @staticmethod
    def of_matrix(t: NDArray[np.float64]) -> Pose2D:
        return Pose2D(float(t[0, 3]), float(t[1, 3]), math.atan2(float(t[1, 0]), float(t[0, 0])))


IDENTITY = Pose2D(0.0, 0.0, 0.0)


def prior_motion(speed_mps: float, yaw_rate_rad_s: float, dt_s: float) -> Pose2D:
    """The unicycle's motion over ``dt_s`` at a constant speed and yaw rate (its own frame)."""
    dyaw = yaw_rate_rad_s * dt_s
    distance = speed_mps * dt_s
    return Pose2D(distance * math.cos(dyaw / 2), distance * math.sin(dyaw / 2), dyaw)


def scan_points(
    scan: RobotScan, speed_mps: float = 0.0, yaw_rate_rad_s: float = 0.0, period_s: float = 0.1
) -> NDArray[np.float64]:
    """The scan's returns as (N, 2) x forward, y left of the robot (metres) where it was at
    the scan's end. The points come in the order they were measured over ``period_s``; each is
    moved by the motion (the prior) still to come after it, so a scan taken while turning is
    not smeared (at 1.5 rad/s a revolution turns 9°)."""
    ranges = np.asarray(scan.ranges_m, dtype=float)
    bearings = np.radians(np.asarray(scan.bearings_deg, dtype=float))
    n = len(ranges)
    seen = ranges > 0
    r, b = ranges[seen], bearings[seen]
    x, y = r * np.cos(b), -r * np.sin(b)  # bearings are clockwise
    if not n or (speed_mps == 0.0 and yaw_rate_rad_s == 0.0):
        return np.column_stack((x, y))
    remaining = (1.0 - (np.arange(n)[seen] + 1) / n) * period_s
    turn = yaw_rate_rad_s * remaining
    ahead = speed_mps * remaining  # the robot's travel still to come, along its axis
    c, s = np.cos(turn), np.sin(turn)
    px, py = x - ahead, y
    return np.column_stack((c * px + s * py, -s * px + c * py))


@dataclass(frozen=True)
class OdometryStep:
    """The odometry after one scan."""

    time: float
    pose: Pose2D
    """In the odometry frame (where the first scan was taken)."""
    delta: Pose2D
    """The motion since the previous scan, in the robot's frame at that scan."""
    source: str
    """"lidar" (registered) or "prior" (the commanded speed and gyro; ``reason`` says why)."""
    reason: str
    points: int
    inliers: int


class LidarOdometry:
    """Scans and the motion prior in, poses out. Not thread-safe: one worker thread owns it."""

    def __init__(self, *, min_points: int = 60) -> None:
        self.min_points = min_points
        self.yaw_slack_rad: float | None = None
        """How far the registration may turn from the prior's turn (None: PRIOR_SLACK_RAD,
        for a prior with a gyro)."""
        self.pose = IDENTITY
        self.last_time: float | None = None
        self.keyframe: Pose2D | None = None
        self.map = _new_map()
        self.scans = 0
        self.fallbacks = 0
        """Scans where the prior stood in for the registration."""
        self.partial = 0
        """Scans registered in all but a degenerate direction, where the prior stood in."""
        self.failures = 0
        """Registrations failed in a row (``RESTART_AFTER`` restarts the local map)."""

    def update(
        self,
        points_xy: NDArray[np.float64],
        now: float,
        speed_mps: float,
        yaw_rate_rad_s: float,
    ) -> OdometryStep:
        """One scan (robot frame, (N, 2)) taken at ``now``; the commanded speed and the gyro's
        yaw rate since the previous scan."""
        dt = 0.0 if self.last_time is None else max(0.0, now - self.last_time)
        self.last_time = now
        self.scans += 1
        prior = prior_motion(speed_mps, yaw_rate_rad_s, dt)
        guess = self.pose.compose(prior)
        n = len(points_xy)
        if n < self.min_points:
            return self._fallback(now, guess, prior, f"{n} returns (< {self.min_points})", n)
        cloud = extrude(points_xy)
        source, _ = small_gicp.preprocess_points(cloud, DOWNSAMPLE_M, num_neighbors=10)
        if self.keyframe is None:  # the first scan starts the map
            self.map.insert(source, guess.matrix())
            self.keyframe = guess
            self.pose = guess
            return OdometryStep(now, guess, prior, "lidar", "", n, n)
        result = small_gicp.align(
            self.map,
            source,
            guess.matrix(),
            max_correspondence_distance=MAX_CORRESPONDENCE_M,
            max_iterations=MAX_ITERATIONS,
        )
        slack = self.yaw_slack_rad if self.yaw_slack_rad is not None else PRIOR_SLACK_RAD
        registered, problem, note = _judge(result, source.size(), prior, guess, slack)
        if problem:
            self.failures += 1
            if self.failures >= RESTART_AFTER:  # lost the local map: start a new one here
                self.failures = 0
                self.map = _new_map()
                self.map.insert(source, guess.matrix())
                self.keyframe = guess
                problem += "; local map restarted"
            return self._fallback(now, guess, prior, problem, n)
        self.failures = 0
        moved = self.keyframe.between(registered)
        if math.hypot(moved.x_m, moved.y_m) >= KEYFRAME_M or abs(moved.yaw_rad) >= KEYFRAME_RAD:
            self.map.insert(source, registered.matrix())
            self.keyframe = registered
        delta = self.pose.between(registered)
        self.pose = registered
        if note:
            self.partial += 1
        return OdometryStep(now, registered, delta, "lidar", note, n, result.num_inliers)

    def _fallback(
        self, now: float, guess: Pose2D, prior: Pose2D, reason: str, points: int
    ) -> OdometryStep:
        self.pose = guess
        self.fallbacks += 1
        return OdometryStep(now, guess, prior, "prior", reason, points, 0)


def extrude(points_xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """Layers at each of :data:`LAYERS_M` (a wall is a plane to GICP); the first
    ``len(points_xy)`` rows are the lowest layer."""
    n = len(points_xy)
    return np.vstack([np.column_stack((points_xy, np.full(n, z))) for z in LAYERS_M])


def _new_map() -> small_gicp.GaussianVoxelMap:
    voxels = small_gicp.GaussianVoxelMap(VOXEL_M)
    voxels.set_lru(LRU_HORIZON, 10)
    return voxels


def _judge(
    result: small_gicp.RegistrationResult,
    size: int,
    prior: Pose2D,
    guess: Pose2D,
    yaw_slack_rad: float,
) -> tuple[Pose2D, str, str]:
    """The registered pose, why it cannot be trusted ("" when it can) and a note when the
    prior stood in along a degenerate direction."""
    registered = Pose2D.of_matrix(np.asarray(result.T_target_source))
    if result.num_inliers < MIN_INLIER_FRACTION * size:
        return registered, f"{result.num_inliers} of {size} points matched the map", ""
    # small_gicp's Hessian is over (rotation x, y, z; translation x, y, z) in the scan's frame.
    eigen, vectors = np.linalg.eigh(np.asarray(result.H)[3:5, 3:5])
    note = ""
    if eigen[-1] <= 0:
        return registered, "nothing constrains the registration", ""
    if eigen[0] < DEGENERATE_RATIO * eigen[-1]:
        # Keep the correction across the free direction; along it, the prior's position.
        c, s = math.cos(registered.yaw_rad), math.sin(registered.yaw_rad)
        fx, fy = vectors[:, 0]
        free = (c * fx - s * fy, s * fx + c * fy)  # in the odometry frame
        dx, dy = registered.x_m - guess.x_m, registered.y_m - guess.y_m
        along = dx * free[0] + dy * free[1]
        registered = Pose2D(
            registered.x_m - along * free[0], registered.y_m - along * free[1], registered.yaw_rad
        )
        bearing = math.degrees(math.atan2(-fy, fx)) % 180.0
        note = f"degenerate scene (a long wall or corridor): prior used along {bearing:.0f}°"
    elif not result.converged:
        return registered, "registration did not converge", ""
    off = guess.between(registered)
    distance = math.hypot(prior.x_m, prior.y_m)
    if math.hypot(off.x_m, off.y_m) > PRIOR_SLACK_M + PRIOR_SPEED_ERROR * distance:
        return registered, f"registration {math.hypot(off.x_m, off.y_m):.2f} m off the prior", ""
    if abs(off.yaw_rad) > yaw_slack_rad:
        return registered, f"registration {math.degrees(abs(off.yaw_rad)):.0f}° off the prior", ""
    return registered, "", note
