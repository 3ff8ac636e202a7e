"""Global relocalization: where in a saved occupancy grid one scan was taken (pure; a thread).

A robot started without GPS in a map it saved could have been carried anywhere while it was
off: its saved pose is only a guess. The scan is placed in the whole map:

1. **Coarse search.** Every known-free place of the grid (a ``STRIDE_M`` lattice) at every
   ``YAW_STEP_RAD`` heading is scored by how many of a thinned scan's points land near an
   occupied cell (within ``COARSE_M``), less those that land in space the map saw free. This
   is numpy over a few million lookups: tenths of a second for a room, seconds for a town.
2. **Refinement.** The best ``CANDIDATES`` distinct poses (``DISTINCT_M`` / ``DISTINCT_RAD``
   apart) are registered to the grid's occupied cells by small_gicp's GICP and scored again
   with every point (``INLIER_M``).
3. **Confidence.** The best refined pose is taken only when enough of the scan fits it
   (``MIN_FIT``), the walls it sees fix both directions (a corridor or one wall does not), and
   no other distinct pose fits nearly as well (``AMBIGUOUS_MARGIN``: a symmetric room, a street
   of look-alike buildings). Otherwise the answer is why not, and the robot holds: a wrong
   pose would drive it, sure of itself, into the map's walls.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import small_gicp
from numpy.typing import NDArray

from brasidas.perception.grid import OccupancyGrid
from brasidas.perception.map_match import align_to_walls
from brasidas.perception.odometry import DEGENERATE_RATIO, Pose2D, extrude

OCCUPIED_LOG_ODDS = 1.0
"""A cell hit more often than crossed (two hits net): a wall of the map."""
FREE_LOG_ODDS = -1.0
"""A cell crossed by beams more often than hit: space the map saw empty."""
COARSE_M = 0.2
"""The coarse search's cells: a point within about one of a wall counts."""
STRIDE_M = 0.4
"""Candidate positions, this far apart over the map's free space."""
YAW_STEP_RAD = math.radians(5.0)
SCAN_SAMPLES = 90
"""Points of the scan the coarse search scores (spread over the scan)."""
MIN_RANGE_M = 0.3
MIN_POINTS = 40
"""Fewer returns than this place nothing (an open field, a lidar looking at the sky)."""
MAX_POSITIONS = 20_000
"""The coarse lattice is made sparser beyond this many positions (a town: bounded work)."""
CHUNK = 4_000
"""Positions scored at once (memory: CHUNK * SCAN_SAMPLES cells)."""
CANDIDATES = 8
DISTINCT_M = 1.0
DISTINCT_RAD = math.radians(20.0)
DOWNSAMPLE_M = 0.1
MAX_CORRESPONDENCE_M = 1.0
INLIER_M = 0.15
MIN_FIT = 0.6
"""Of the scan's points, the share that must lie on the map's walls at the pose found (less
what falls in the map's free space): the rest is what the map does not have (a parked car)."""
AMBIGUOUS_MARGIN = 0.04
"""Another distinct pose scoring within this of the best: the scan cannot tell them apart."""


@dataclass(frozen=True)
class Relocalization:
    """The answer: a pose, or why none (``pose`` None, ``reason`` says why)."""

    pose: Pose2D | None
    score: float
    """The best pose's fit: share of the scan on the map's walls, less that in its free space."""
    runner_up: float
    """The best distinct other pose's fit (0 when none)."""
    reason: str
    positions: int
    """Coarse candidate positions searched (each at every heading)."""
    seconds: float
    """Thread CPU time the search took."""

    @property
    def found(self) -> bool:
        return self.pose is not None


class GridRelocalizer:
    """A saved grid in; a scan (robot frame) in, a :class:`Relocalization` out."""

    def __init__(self, grid: OccupancyGrid) -> None:
        log_odds = grid.log_odds
        self.resolution = grid.resolution
        self.origin = np.asarray(grid.origin, dtype=float)
        self.occupied = log_odds >= OCCUPIED_LOG_ODDS
        self.free = log_odds <= FREE_LOG_ODDS
        rows, cols = log_odds.shape
        ys, xs = np.nonzero(self.occupied)
        self.walls = np.column_stack(
            (
                self.origin[0] + (xs + 0.5) * self.resolution,
                self.origin[1] + (ys + 0.5) * self.resolution,
            )
        )
        # The coarse grid: a coarse cell is near a wall when any fine cell in it or its
        # neighbours is occupied; free when most of its fine cells are.
        factor = max(1, round(COARSE_M / self.resolution))
        self.coarse = factor * self.resolution
        crow, ccol = -(-rows // factor), -(-cols // factor)
        padded = np.zeros((crow * factor, ccol * factor), dtype=bool)
        padded[:rows, :cols] = self.occupied
        walls: NDArray[np.bool_] = np.asarray(
            padded.reshape(crow, factor, ccol, factor).any(axis=(1, 3))
        )
        self.near = _dilate(walls)
        padded_free = np.zeros((crow * factor, ccol * factor), dtype=bool)
        padded_free[:rows, :cols] = self.free
        self.coarse_free = padded_free.reshape(crow, factor, ccol, factor).mean(axis=(1, 3)) > 0.5
        self._target: small_gicp.PointCloud | None = None
        self._tree: small_gicp.KdTree | None = None
        if len(self.walls) >= MIN_POINTS:
            self._target, self._tree = small_gicp.preprocess_points(
                extrude(self.walls), DOWNSAMPLE_M, num_neighbors=10
            )

    def positions(self) -> NDArray[np.float64]:
        """The coarse search's candidate positions: the map's free space, every STRIDE_M."""
        step = max(1, round(STRIDE_M / self.coarse))
        free = self.coarse_free & ~self.near
        rows, cols = np.nonzero(free[::step, ::step])
        while len(rows) > MAX_POSITIONS:
            step += 1
            rows, cols = np.nonzero(free[::step, ::step])
        return np.column_stack(
            (
                self.origin[0] + (cols * step + 0.5) * self.coarse,
                self.origin[1] + (rows * step + 0.5) * self.coarse,
            )
        )

    def locate(self, points_xy: NDArray[np.float64], hint: Pose2D | None = None) -> Relocalization:
        """Where ``points_xy`` (the scan, robot frame) was taken in the grid, or why not.
        ``hint`` (the saved pose) is searched too, off the lattice: it is not trusted more."""
        started = time.thread_time()
        points = points_xy[np.hypot(points_xy[:, 0], points_xy[:, 1]) >= MIN_RANGE_M]

        def refused(reason: str, positions: int = 0, score: float = 0.0) -> Relocalization:
            return Relocalization(None, score, 0.0, reason, positions, time.thread_time() - started)

        if len(points) < MIN_POINTS:
            return refused(f"{len(points)} returns: too few to place the robot in the map")
        if self._target is None or self._tree is None:
            return refused("the saved map has no walls to place the robot by")
        positions = self.positions()
        if hint is not None:
            positions = np.vstack((positions, [(hint.x_m, hint.y_m)]))
        if not len(positions):
            return refused("the saved map has no free space to place the robot in")
        coarse = self._coarse(points, positions, hint)
        fits = [self._refine(points, pose) for pose in coarse]
        fits.sort(key=lambda fit: -fit[1])
        best, score, degenerate = fits[0]
        runner_up = next(
            (other for pose, other, _ in fits[1:] if _distinct(pose, best)),
            0.0,
        )
        found = Relocalization(
            best, score, runner_up, "", len(positions), time.thread_time() - started
        )
        if score < MIN_FIT:
            reason = f"the scan fits the saved map nowhere ({100 * score:.0f} % at best)"
        elif degenerate:
            reason = "the walls in sight fix only one direction (a corridor, one wall)"
        elif runner_up > score - AMBIGUOUS_MARGIN:
            reason = (
                f"ambiguous: two places fit the scan ({100 * score:.0f} % and "
                f"{100 * runner_up:.0f} %)"
            )
        else:
            return found
        return Relocalization(None, score, runner_up, reason, found.positions, found.seconds)

    def fit(self, points_xy: NDArray[np.float64], pose: Pose2D) -> float:
        """The scan's fit at ``pose``: share of its points on the map's walls, less the share
        in the map's free space (the confidence test's measure; also to tell a lost match)."""
        assert self._tree is not None
        world = _transform(points_xy, pose)
        _index, squared = self._tree.batch_nearest_neighbor_search(extrude(world)[: len(world)])
        on_walls = np.asarray(squared) < INLIER_M**2
        cells = np.floor((world - self.origin) / self.resolution).astype(np.intp)
        rows, cols = self.free.shape
        inside = (
            (cells[:, 0] >= 0) & (cells[:, 0] < cols) & (cells[:, 1] >= 0) & (cells[:, 1] < rows)
        )
        in_free = np.zeros(len(world), dtype=bool)
        in_free[inside] = self.free[cells[inside, 1], cells[inside, 0]]
        return float(np.mean(on_walls) - np.mean(in_free & ~on_walls))

    def register(
        self, points_xy: NDArray[np.float64], guess: Pose2D
    ) -> tuple[Pose2D, float] | None:
        """The scan registered to the walls from ``guess`` and its fit; None when it has too
        few returns, or the walls in sight leave a direction free (a corridor)."""
        points = points_xy[np.hypot(points_xy[:, 0], points_xy[:, 1]) >= MIN_RANGE_M]
        if len(points) < MIN_POINTS or self._target is None:
            return None
        pose, fit, degenerate = self._refine(points, guess)
        return None if degenerate else (pose, fit)

    def known_fit(
        self, points_xy: NDArray[np.float64], pose: Pose2D, min_points: int
    ) -> float | None:
        """The fit at ``pose`` over the points that land where the map knows something (a
        wall near, or seen free); None when fewer than ``min_points`` do (a place the saved
        map never saw: nothing to compare)."""
        if self._tree is None:
            return None
        points = points_xy[np.hypot(points_xy[:, 0], points_xy[:, 1]) >= MIN_RANGE_M]
        cells = np.floor((_transform(points, pose) - self.origin) / self.coarse).astype(np.intp)
        rows, cols = self.near.shape
        inside = (
            (cells[:, 0] >= 0) & (cells[:, 0] < cols) & (cells[:, 1] >= 0) & (cells[:, 1] < rows)
        )
        known = np.zeros(len(points), dtype=bool)
        near, free = self.near[cells[inside, 1], cells[inside, 0]], self.coarse_free
        known[inside] = near | free[cells[inside, 1], cells[inside, 0]]
        if int(known.sum()) < min_points:
            return None
        return self.fit(points[known], pose)

    def _coarse(
        self, points: NDArray[np.float64], positions: NDArray[np.float64], hint: Pose2D | None
    ) -> list[Pose2D]:
        """The best distinct poses of the lattice at every heading."""
        sample = points[np.linspace(0, len(points) - 1, min(SCAN_SAMPLES, len(points))).astype(int)]
        yaws = np.arange(0.0, 2 * math.pi, YAW_STEP_RAD)
        if hint is not None:
            yaws = np.append(yaws, hint.yaw_rad)
        rows, cols = self.near.shape
        scores = np.empty((len(yaws), len(positions)), dtype=np.float32)
        for k, yaw in enumerate(yaws):
            c, s = math.cos(yaw), math.sin(yaw)
            rotated = sample @ np.array(((c, s), (-s, c)))  # rows: R · p
            for start in range(0, len(positions), CHUNK):  # bounded memory (~6 MB a chunk)
                chunk = positions[start : start + CHUNK] - self.origin
                cells = np.floor((chunk[:, None, :] + rotated[None, :, :]) / self.coarse)
                col, row = cells[..., 0].astype(np.intp), cells[..., 1].astype(np.intp)
                inside = (col >= 0) & (col < cols) & (row >= 0) & (row < rows)
                col, row = np.where(inside, col, 0), np.where(inside, row, 0)
                near = self.near[row, col] & inside
                free = self.coarse_free[row, col] & inside & ~near
                scores[k, start : start + CHUNK] = near.mean(axis=1) - free.mean(axis=1)
        order = np.argsort(scores, axis=None)[::-1]
        chosen: list[Pose2D] = []
        for flat in order[: 50 * CANDIDATES]:
            k, i = divmod(int(flat), len(positions))
            pose = Pose2D(float(positions[i, 0]), float(positions[i, 1]), float(yaws[k]))
            if all(_distinct(pose, other) for other in chosen):
                chosen.append(pose)
                if len(chosen) == CANDIDATES:
                    break
        return chosen

    def _refine(self, points: NDArray[np.float64], guess: Pose2D) -> tuple[Pose2D, float, bool]:
        """``guess`` registered to the walls: the pose, its fit, and whether the walls leave a
        direction free."""
        assert self._target is not None and self._tree is not None
        result, _ = align_to_walls(
            self._target,
            self._tree,
            points,
            guess,
            downsample_m=DOWNSAMPLE_M,
            max_correspondence_m=MAX_CORRESPONDENCE_M,
        )
        pose = Pose2D.of_matrix(np.asarray(result.T_target_source)) if result.converged else guess
        eigen = np.linalg.eigvalsh(np.asarray(result.H)[3:5, 3:5])
        degenerate = bool(eigen[-1] <= 0 or eigen[0] < DEGENERATE_RATIO * eigen[-1])
        return pose, self.fit(points, pose), degenerate


def _distinct(a: Pose2D, b: Pose2D) -> bool:
    turn = abs(math.remainder(a.yaw_rad - b.yaw_rad, 2 * math.pi))
    return math.hypot(a.x_m - b.x_m, a.y_m - b.y_m) > DISTINCT_M or turn > DISTINCT_RAD


def _dilate(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """``mask`` grown by one cell each way (eight neighbours)."""
    grown = mask.copy()
    padded = np.pad(mask, 1)
    rows, cols = mask.shape
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            grown |= padded[dy : dy + rows, dx : dx + cols]
    return grown


def _transform(points_xy: NDArray[np.float64], pose: Pose2D) -> NDArray[np.float64]:
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    return np.column_stack(
        (
            pose.x_m + c * points_xy[:, 0] - s * points_xy[:, 1],
            pose.y_m + s * points_xy[:, 0] + c * points_xy[:, 1],
        )
    )
