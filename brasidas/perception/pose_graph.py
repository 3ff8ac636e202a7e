"""A pose graph over keyframes, smoothed by GTSAM's iSAM2, with loop closure (pure; one thread).

Nodes are keyframes every ``KEYFRAME_M`` (or ``KEYFRAME_RAD``); odometry between them is a
between-factor whose noise grows with the step; absolute measurements (the fused pose while
GPS or the area map's walls hold it) are priors on the newest node. When a keyframe comes back
within ``LOOP_RADIUS_M`` of one at least ``LOOP_MIN_PATH_M`` of path before it (or of a keyframe of
a map loaded from a previous run), its scan is registered to that keyframe's scan (small_gicp
GICP from the graph's relative estimate); a fit with most points matched closes the loop with a
tight between-factor, and iSAM2 spreads the correction over the whole path since.

Bounded: each keyframe keeps its scan as 2-D points thinned to ``DOWNSAMPLE_M`` (a few kB; the
3-D cloud GICP needs is built when a closure is tried), and past ``MAX_KEYFRAMES`` the graph is
compacted to its newest half, chained by their smoothed relative poses. Saved with the
occupancy grid (:func:`save_keyframes`) so a restarted robot closes loops against its old map.

The platform's localizer (:mod:`platformd.lidar_localization`) runs it in its worker thread;
the grid is rebuilt from the keyframes at their smoothed poses after a loop closes.
"""

from __future__ import annotations

import math
import os
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np
import small_gicp
from numpy.typing import NDArray

from brasidas.perception.odometry import DEGENERATE_RATIO, LAYERS_M, Pose2D

KEYFRAME_M = 1.0
KEYFRAME_RAD = math.radians(15.0)
LOOP_RADIUS_M = 4.0
LOOP_MIN_PATH_M = 15.0
"""Keyframes nearer than this along the path are the odometry's business, not a loop."""
LOOP_INLIERS = 0.8
LOOP_FIT_M = 0.2
LOOP_FIT_SHARE = 0.7
"""Of the registered scan's points, the share that must lie this close to the old scan's (the
registration's own inlier count, at its wide correspondence distance, accepts a near miss in
a room whose walls look alike from a metre away)."""
LOOP_TRIES = 3
LOOP_CORRESPONDENCE_M = 2.0
LOOP_SIGMAS = (0.05, 0.05, math.radians(0.5))
DRIFT_PER_M = (0.05, 0.05, 0.02)
"""Between keyframes, on top of the steps' own noise: the odometry's drift (m per metre along
and across, rad per metre), which grows with the distance, not with its square root as the
steps' independent noise does. Without it a loop of a few dozen keyframes was held as sure as a
closure, and closing it took out only half the drift."""
LOOP_MIN_POINTS = 60
"""A keyframe with fewer returns (an open field) is not registered for a loop closure."""
DOWNSAMPLE_M = 0.1
MAX_KEYFRAMES = 2000
"""2 km of path at a keyframe a metre: ~10 MB of scans; past it the oldest half is let go."""
LOADED_SIGMAS = (0.02, 0.02, math.radians(0.2))
"""A keyframe of a map loaded from disk: held where it was (the map's frame is its poses)."""
CHAIN_SIGMAS = (0.02, 0.02, math.radians(0.2))
"""Between compacted keyframes: their smoothed relative poses, held as they are."""
KEYFRAMES_FORMAT = 1
CLOSURE_ITERATIONS = 4
"""iSAM2 takes one Gauss-Newton step an update: a closure that turns the loop by degrees needs
a few (after one, a 1 m drift was only a third taken out)."""


@dataclass(frozen=True)
class Closure:
    """A loop closed at keyframe ``k`` against keyframe ``j``; the most any keyframe moved."""

    j: int
    k: int
    moved_m: float


def _pose(p: Pose2D) -> gtsam.Pose2:
    return gtsam.Pose2(p.x_m, p.y_m, p.yaw_rad)


def _of(p: gtsam.Pose2) -> Pose2D:
    return Pose2D(p.x(), p.y(), p.theta())


class PoseGraph:
    """Odometry steps, priors and scans in; the smoothed newest pose out."""

    def __init__(
        self,
        start: Pose2D,
        sigmas: tuple[float, float, float],
        *,
        loaded: list[tuple[Pose2D, NDArray[np.float32]]] | None = None,
    ) -> None:
        """``loaded``: keyframes of a map from a previous run (fixed where they were); the
        robot starts at ``start`` with ``sigmas`` among them."""
        self.isam = _isam()
        self.poses: list[Pose2D] = []
        self.points: list[NDArray[np.float32]] = []
        self.path_m: list[float] = []
        """Each keyframe's distance along the path driven (odometry)."""
        self.pending = Pose2D(0.0, 0.0, 0.0)
        self.pending_var = np.zeros(3)
        self.closures = 0
        self.last_closure: Closure | None = None
        self.compactions = 0
        self.keyframe_cpu_s: list[float] = []
        """Thread CPU time of each keyframe added (closure search and smoothing), the latest
        ``MAX_KEYFRAMES``."""
        self.first_live = 0
        """Keyframes before this index were loaded from disk (any gap closes a loop)."""
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for pose, points in loaded or []:
            i = len(self.poses)
            graph.add(gtsam.PriorFactorPose2(i, _pose(pose), _noise(LOADED_SIGMAS)))
            values.insert(i, _pose(pose))
            self.poses.append(pose)
            self.points.append(points)
            self.path_m.append(0.0)
        self.first_live = len(self.poses)
        k = len(self.poses)
        graph.add(gtsam.PriorFactorPose2(k, _pose(start), _noise(sigmas)))
        values.insert(k, _pose(start))
        self.poses.append(start)
        self.points.append(np.empty((0, 2), dtype=np.float32))
        self.path_m.append(0.0)
        self._pending_path = 0.0
        self.isam.update(graph, values)

    @property
    def pose(self) -> Pose2D:
        """The newest keyframe, smoothed, moved by the odometry since it."""
        return self.poses[-1].compose(self.pending)

    def odometry(
        self, delta: Pose2D, sigmas: tuple[float, float, float], points_xy: NDArray[np.float64]
    ) -> Closure | None:
        """The robot moved ``delta`` (its own frame), with that step's noise; its scan (robot
        frame). The loop this step closed, if any."""
        self.pending = self.pending.compose(delta)
        self.pending_var += np.square(sigmas)
        self._pending_path += math.hypot(delta.x_m, delta.y_m)
        moved = math.hypot(self.pending.x_m, self.pending.y_m)
        if moved < KEYFRAME_M and abs(self.pending.yaw_rad) < KEYFRAME_RAD:
            return None
        started = time.thread_time()
        if len(self.poses) >= MAX_KEYFRAMES:
            self._compact()
        k = len(self.poses)
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        drift = np.array(DRIFT_PER_M) * self._pending_path
        noise = gtsam.noiseModel.Diagonal.Variances(self.pending_var + np.square(drift))
        graph.add(gtsam.BetweenFactorPose2(k - 1, k, _pose(self.pending), noise))
        guess = self.poses[-1].compose(self.pending)
        values.insert(k, _pose(guess))
        self.poses.append(guess)
        thinned = _thin(points_xy)
        self.points.append(thinned)
        self.path_m.append(self.path_m[-1] + self._pending_path)
        self.pending, self.pending_var = Pose2D(0.0, 0.0, 0.0), np.zeros(3)
        self._pending_path = 0.0
        found = self._closure(k, thinned)
        closure = None
        if found is not None:
            j, relative = found
            graph.add(gtsam.BetweenFactorPose2(j, k, _pose(relative), _noise(LOOP_SIGMAS)))
            self.closures += 1
        before = self.poses
        self._update(graph, values, CLOSURE_ITERATIONS if found is not None else 0)
        if found is not None:
            shift = max(math.dist(_xy(a), _xy(b)) for a, b in zip(before, self.poses, strict=True))
            closure = Closure(found[0], k, shift)
            self.last_closure = closure
        self.keyframe_cpu_s.append(time.thread_time() - started)
        del self.keyframe_cpu_s[:-MAX_KEYFRAMES]
        return closure

    def prior(self, pose: Pose2D, sigmas: tuple[float, float, float]) -> None:
        """An absolute measurement of the newest keyframe (a GPS fix: a wide yaw sigma)."""
        graph = gtsam.NonlinearFactorGraph()
        graph.add(gtsam.PriorFactorPose2(len(self.poses) - 1, _pose(pose), _noise(sigmas)))
        self._update(graph, gtsam.Values())

    def keyframes(self) -> list[tuple[Pose2D, NDArray[np.float32]]]:
        """Each keyframe's smoothed pose and scan (robot frame), oldest first."""
        return [(p, s) for p, s in zip(self.poses, self.points, strict=True) if len(s)]

    def _closure(self, k: int, thinned: NDArray[np.float32]) -> tuple[int, Pose2D] | None:
        """The spatially nearest old keyframe whose scan this one's fits, if any."""
        if len(thinned) < LOOP_MIN_POINTS:
            return None
        here, travelled = self.poses[k], self.path_m[k]
        old = [
            (math.hypot(p.x_m - here.x_m, p.y_m - here.y_m), j)
            for j, p in enumerate(self.poses[:k])
            if len(self.points[j]) >= LOOP_MIN_POINTS
            and (j < self.first_live or travelled - self.path_m[j] >= LOOP_MIN_PATH_M)
        ]
        old.sort()
        if not old or old[0][0] > LOOP_RADIUS_M:
            return None
        cloud = _cloud(thinned)
        for distance, j in old[:LOOP_TRIES]:
            if distance > LOOP_RADIUS_M:
                break
            scan = _cloud(self.points[j])
            guess = self.poses[j].between(here)
            result = small_gicp.align(
                scan,
                cloud,
                small_gicp.KdTree(scan),
                guess.matrix(),
                max_correspondence_distance=LOOP_CORRESPONDENCE_M,
            )
            if not (result.converged and result.num_inliers >= LOOP_INLIERS * cloud.size()):
                continue
            # Along a street or a corridor the scans look alike metres apart: such a fit
            # would close the loop in the wrong place (seen: 6.4 m off along a street).
            eigen = np.linalg.eigvalsh(np.asarray(result.H)[3:5, 3:5])
            if eigen[-1] <= 0 or eigen[0] < DEGENERATE_RATIO * eigen[-1]:
                continue
            relative = Pose2D.of_matrix(np.asarray(result.T_target_source))
            if _fit_share(self.points[j], thinned, relative) >= LOOP_FIT_SHARE:
                return j, relative
        return None

    def _update(
        self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, iterations: int = 0
    ) -> None:
        self.isam.update(graph, values)
        for _ in range(iterations):
            self.isam.update()
        estimate = self.isam.calculateEstimate()
        self.poses = [_of(estimate.atPose2(i)) for i in range(len(self.poses))]

    def _compact(self) -> None:
        """Let the oldest half go: a new graph of the newest half, the first held where it is
        and each chained to the next by their smoothed relative pose."""
        keep = len(self.poses) // 2
        poses, points = self.poses[-keep:], self.points[-keep:]
        self.isam = _isam()
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        graph.add(gtsam.PriorFactorPose2(0, _pose(poses[0]), _noise(CHAIN_SIGMAS)))
        values.insert(0, _pose(poses[0]))
        for i in range(1, keep):
            between = poses[i - 1].between(poses[i])
            graph.add(gtsam.BetweenFactorPose2(i - 1, i, _pose(between), _noise(CHAIN_SIGMAS)))
            values.insert(i, _pose(poses[i]))
        self.isam.update(graph, values)
        self.poses, self.points = list(poses), list(points)
        self.path_m = self.path_m[-keep:]
        self.first_live = 0
        self.compactions += 1


def save_keyframes(path: Path, keyframes: list[tuple[Pose2D, NDArray[np.float32]]]) -> None:
    """Atomically, as a NumPy ``.npz`` (no pickles): poses, and the scans end to end."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial.npz")
    poses = np.array([(p.x_m, p.y_m, p.yaw_rad) for p, _ in keyframes], dtype=float)
    counts = np.array([len(s) for _, s in keyframes], dtype=np.int64)
    points = (
        np.vstack([s for _, s in keyframes]).astype(np.float32)
        if keyframes
        else np.empty((0, 2), dtype=np.float32)
    )
    np.savez_compressed(
        partial,
        format=np.array(KEYFRAMES_FORMAT),
        poses=poses.reshape(-1, 3),
        counts=counts,
        points=points,
    )
    os.replace(partial, path)


class KeyframesError(Exception):
    """A file that is not keyframes this version can read."""


def load_keyframes(path: Path) -> list[tuple[Pose2D, NDArray[np.float32]]]:
    """The keyframes saved at ``path`` (the newest ``MAX_KEYFRAMES // 2``);
    :class:`KeyframesError` saying why when it is not such a file."""
    try:
        with np.load(path, allow_pickle=False) as data:
            if int(data["format"]) != KEYFRAMES_FORMAT:
                raise KeyframesError(f"{path}: keyframes format {int(data['format'])}")
            poses = np.asarray(data["poses"], dtype=float)
            counts = np.asarray(data["counts"], dtype=np.int64)
            points = np.asarray(data["points"], dtype=np.float32)
    except KeyframesError:
        raise
    except (OSError, EOFError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as err:
        raise KeyframesError(f"{path}: not saved keyframes ({err})") from None
    if (
        poses.ndim != 2
        or poses.shape[1:] != (3,)
        or counts.shape != (len(poses),)
        or points.ndim != 2
        or points.shape[1:] != (2,)
        or (counts < 0).any()
        or int(counts.sum()) != len(points)
        or not (np.isfinite(poses).all() and np.isfinite(points).all())
    ):
        raise KeyframesError(f"{path}: keyframes of inconsistent shapes refused")
    ends = np.cumsum(counts)
    starts = ends - counts
    keyframes = [
        (Pose2D(float(x), float(y), float(yaw)), points[a:b])
        for (x, y, yaw), a, b in zip(poses, starts, ends, strict=True)
    ]
    return keyframes[-(MAX_KEYFRAMES // 2) :]


def _isam() -> gtsam.ISAM2:
    params = gtsam.ISAM2Params()
    params.relinearizeSkip = 1  # relinearize at every update (a closure moves the linearization)
    return gtsam.ISAM2(params)


def _noise(sigmas: tuple[float, float, float]) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Diagonal.Sigmas(np.array(sigmas, dtype=float))


def _xy(p: Pose2D) -> tuple[float, float]:
    return (p.x_m, p.y_m)


def _thin(points_xy: NDArray[np.float64]) -> NDArray[np.float32]:
    """One point per ``DOWNSAMPLE_M`` cell (the first seen)."""
    if not len(points_xy):
        return np.empty((0, 2), dtype=np.float32)
    cells = np.floor(np.asarray(points_xy) / DOWNSAMPLE_M).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return np.asarray(points_xy, dtype=np.float32)[np.sort(first)]


def _fit_share(target: NDArray[np.float32], source: NDArray[np.float32], relative: Pose2D) -> float:
    """The share of ``source``'s points, moved by ``relative`` into ``target``'s frame, within
    ``LOOP_FIT_M`` of one of ``target``'s."""
    c, s = math.cos(relative.yaw_rad), math.sin(relative.yaw_rad)
    x, y = source[:, 0].astype(float), source[:, 1].astype(float)
    moved = np.column_stack((relative.x_m + c * x - s * y, relative.y_m + s * x + c * y))
    gaps = np.full(len(moved), np.inf)
    for chunk in np.array_split(np.asarray(target, dtype=float), max(1, len(target) // 256)):
        d = np.hypot(moved[:, None, 0] - chunk[None, :, 0], moved[:, None, 1] - chunk[None, :, 1])
        gaps = np.minimum(gaps, d.min(axis=1))
    return float(np.mean(gaps <= LOOP_FIT_M))


def _cloud(points_xy: NDArray[np.float32]) -> small_gicp.PointCloud:
    n = len(points_xy)
    xy = np.asarray(points_xy, dtype=np.float64)
    extruded = np.vstack([np.column_stack((xy, np.full(n, z))) for z in LAYERS_M])
    cloud, _ = small_gicp.preprocess_points(extruded, DOWNSAMPLE_M)
    return cloud
