"""A pose graph over keyframes, smoothed by GTSAM's iSAM2, with loop closure (pure; one thread).

Nodes are keyframes every ``KEYFRAME_M`` (or ``KEYFRAME_RAD``); odometry between them is a
between-factor whose noise grows with the step; absolute measurements (an accepted GPS fix, a
match to the area map) are priors on the newest node. When a keyframe comes back within
``LOOP_RADIUS_M`` of one at least ``LOOP_MIN_GAP`` keyframes older, its scan is registered to
that keyframe's scan (small_gicp GICP from the graph's relative estimate); a fit with most points
matched closes the loop with a tight between-factor, and iSAM2 spreads the correction over the
whole path since. Not yet wired to the platform: :mod:`brasidas.perception.fusion`'s filter is.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np
import small_gicp
from numpy.typing import NDArray

from brasidas.perception.odometry import LAYERS_M, Pose2D

KEYFRAME_M = 1.0
KEYFRAME_RAD = math.radians(15.0)
LOOP_RADIUS_M = 4.0
LOOP_MIN_GAP = 30
LOOP_INLIERS = 0.8
LOOP_TRIES = 3
LOOP_CORRESPONDENCE_M = 2.0
LOOP_SIGMAS = (0.05, 0.05, math.radians(0.5))
DOWNSAMPLE_M = 0.1


def _pose(p: Pose2D) -> gtsam.Pose2:
    return gtsam.Pose2(p.x_m, p.y_m, p.yaw_rad)


def _of(p: gtsam.Pose2) -> Pose2D:
    return Pose2D(p.x(), p.y(), p.theta())


class PoseGraph:
    """Odometry steps, priors and scans in; the smoothed newest pose out."""

    def __init__(self, start: Pose2D, sigmas: tuple[float, float, float]) -> None:
        self.isam = gtsam.ISAM2()
        self.poses: list[Pose2D] = [start]
        self.scans: list[small_gicp.PointCloud | None] = [None]
        self.pending = Pose2D(0.0, 0.0, 0.0)
        self.pending_var = np.zeros(3)
        self.closures = 0
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.PriorFactorPose2(0, _pose(start), _noise(sigmas)))
        values.insert(0, _pose(start))
        self.isam.update(graph, values)

    @property
    def pose(self) -> Pose2D:
        """The newest keyframe, smoothed, moved by the odometry since it."""
        return self.poses[-1].compose(self.pending)

    def odometry(
        self, delta: Pose2D, sigmas: tuple[float, float, float], points_xy: NDArray[np.float64]
    ) -> None:
        """The robot moved ``delta`` (its own frame), with that step's noise; its scan."""
        self.pending = self.pending.compose(delta)
        self.pending_var += np.square(sigmas)
        moved = math.hypot(self.pending.x_m, self.pending.y_m)
        if moved < KEYFRAME_M and abs(self.pending.yaw_rad) < KEYFRAME_RAD:
            return
        k = len(self.poses)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        noise = gtsam.noiseModel.Diagonal.Variances(self.pending_var)
        graph.add(gtsam.BetweenFactorPose2(k - 1, k, _pose(self.pending), noise))
        guess = self.poses[-1].compose(self.pending)
        values.insert(k, _pose(guess))
        self.poses.append(guess)
        cloud, _ = small_gicp.preprocess_points(_extrude(points_xy), DOWNSAMPLE_M)
        self.scans.append(cloud)
        self.pending, self.pending_var = Pose2D(0.0, 0.0, 0.0), np.zeros(3)
        closure = self._closure(k, cloud)
        if closure is not None:
            j, relative = closure
            graph.add(gtsam.BetweenFactorPose2(j, k, _pose(relative), _noise(LOOP_SIGMAS)))
            self.closures += 1
        self._update(graph, values)

    def prior(self, pose: Pose2D, sigmas: tuple[float, float, float]) -> None:
        """An absolute measurement of the newest keyframe (a GPS fix: a wide yaw sigma)."""
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose2(len(self.poses) - 1, _pose(pose), _noise(sigmas)))
        self._update(graph, gtsam.Values())

    def _closure(self, k: int, cloud: small_gicp.PointCloud) -> tuple[int, Pose2D] | None:
        """The spatially nearest old keyframe whose scan this one's fits, if any."""
        here = self.poses[k]
        old = [
            (math.hypot(p.x_m - here.x_m, p.y_m - here.y_m), j)
            for j, p in enumerate(self.poses[: max(0, k - LOOP_MIN_GAP)])
            if self.scans[j] is not None
        ]
        for distance, j in sorted(old)[:LOOP_TRIES]:
            if distance > LOOP_RADIUS_M:
                break
            scan = self.scans[j]
            assert scan is not None
            guess = self.poses[j].between(here)
            result = small_gicp.align(
                scan,
                cloud,
                small_gicp.KdTree(scan),
                guess.matrix(),
                max_correspondence_distance=LOOP_CORRESPONDENCE_M,
            )
            if result.converged and result.num_inliers >= LOOP_INLIERS * cloud.size():
                return j, Pose2D.of_matrix(np.asarray(result.T_target_source))
        return None

    def _update(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        self.isam.update(graph, values)
        estimate = self.isam.calculateEstimate()
        self.poses = [_of(estimate.atPose2(i)) for i in range(len(self.poses))]


def _noise(sigmas: tuple[float, float, float]) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Diagonal.Sigmas(np.array(sigmas, dtype=float))


def _extrude(points_xy: NDArray[np.float64]) -> NDArray[np.float64]:
    n = len(points_xy)
    return np.vstack([np.column_stack((points_xy, np.full(n, z))) for z in LAYERS_M])
