"""Scan-to-map registration: where a scan fits the area map's walls (pure; run in a thread).

The GPS of the rover (a NEO-6M) is wrong by a few metres, and wrong the same way for minutes:
odometry cannot see that bias, since it only measures motion. The area map's keep-outs
(buildings, walls, a shed) are fixed in the world: registering a scan against their outlines
gives an absolute pose, and the bias becomes observable. The outlines are sampled every
``SAMPLE_M`` and extruded like the odometry's scans (a wall is a plane to GICP); each scan is
registered by GICP from the fused pose, with a correspondence distance wide enough for the
GPS's error (``MAX_CORRESPONDENCE_M``).

A match is refused, with the reason, when too few of the scan's points lie on the map's walls
(things the map does not have: parked cars, people, a wall not drawn), when GICP does not
converge, or when it lands far from the guess. Along a single wall or a street between two the
registration fixes only the direction across it: the measurement's covariance says so (the
free direction gets ``FREE_SIGMA_M``), so the fusion takes the across part only.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import shapely
import small_gicp
from numpy.typing import NDArray

from brasidas.perception.odometry import DEGENERATE_RATIO, Pose2D, extrude

SAMPLE_M = 0.1
DOWNSAMPLE_M = 0.15
MAX_CORRESPONDENCE_M = 3.0
MAX_ITERATIONS = 30
MIN_POINTS = 40
MIN_INLIER_FRACTION = 0.8
"""Of the scan's points, those that must land near a wall of the map (the rest: things the
map does not have)."""
INLIER_M = 0.3
MAX_CORRECTION_M = 6.0
MAX_CORRECTION_RAD = math.radians(15.0)
MAX_THROUGH_WALLS = 0.02
BEAM_MARGIN_M = 0.4
"""A beam is checked up to this short of its return (its own wall, the map's error)."""
BEAM_SAMPLES = 12
SEARCH_M = 2.0
SEARCH_RAD = math.radians(8.0)
SEARCH_TURN_RAD = math.radians(25.0)
AMBIGUOUS_M = 1.0
AMBIGUOUS_INLIERS = 0.05
"""Two fits this far apart and this close in inliers: the scan cannot tell which is right."""
SIGMA_M = 0.15
"""Of a well-constrained match, on each axis (the map's own accuracy dominates)."""
SIGMA_YAW_RAD = math.radians(1.0)
FREE_SIGMA_M = 100.0
"""Along a direction the walls do not constrain: the match says nothing there."""


@dataclass(frozen=True)
class MapMatch:
    pose: Pose2D
    """Where the scan fits the map (world frame: x east, y north, yaw from east)."""
    covariance: NDArray[np.float64]
    """3x3 over (x, y, yaw)."""
    inliers: float
    """Fraction of the scan's points on the map's walls."""
    note: str
    """"" or what the match could not see (a degenerate direction)."""


def wall_points(polygons: Iterable[NDArray[np.float64]]) -> NDArray[np.float64]:
    """The outlines of ``polygons`` ((N, 2) rings, world frame), sampled every ``SAMPLE_M``."""
    samples: list[NDArray[np.float64]] = []
    for ring in polygons:
        for a, b in itertools.pairwise(np.asarray(ring, dtype=float)):
            count = max(1, math.ceil(float(np.hypot(*(b - a))) / SAMPLE_M))
            t = np.arange(count)[:, None] / count
            samples.append(a + t * (b - a))
    return np.vstack(samples) if samples else np.empty((0, 2))


class MapMatcher:
    """The map's buildings in; a scan and a guess in, a :class:`MapMatch` (or why not) out."""

    def __init__(self, rings: list[NDArray[np.float64]]) -> None:
        walls_xy = wall_points(rings)
        self.walls = len(walls_xy)
        self._solid = shapely.union_all([shapely.Polygon(r) for r in rings])
        shapely.prepare(self._solid)
        self._target: small_gicp.PointCloud | None = None
        self._tree: small_gicp.KdTree | None = None
        if self.walls:
            self._target, self._tree = small_gicp.preprocess_points(
                extrude(walls_xy), DOWNSAMPLE_M, num_neighbors=10
            )
        self.matches = 0
        self.refused = 0
        self.last_refusal = ""

    def match(
        self, points_xy: NDArray[np.float64], guess: Pose2D, *, search: bool = False
    ) -> MapMatch | str:
        """The scan (robot frame) registered to the walls from ``guess``; or why not.

        With ``search`` (the estimate is uncertain: GPS only, or the fusion refused the map
        lately) GICP starts from guesses around it too (``SEARCH_M``, ``SEARCH_RAD``) and the
        best fit wins, if it is clearly the best: a street of look-alike buildings has fits a
        few metres apart, and taking the wrong one would be worse than none."""
        if search:
            answer = self._search(points_xy, guess)
        else:
            answer = self._match(points_xy, guess)
        if isinstance(answer, str):
            self.refused += 1
            self.last_refusal = answer
        else:
            self.matches += 1
        return answer

    def _search(self, points_xy: NDArray[np.float64], guess: Pose2D) -> MapMatch | str:
        fits: list[MapMatch] = []
        reason = ""
        for dx in (-SEARCH_M, 0.0, SEARCH_M):
            for dy in (-SEARCH_M, 0.0, SEARCH_M):
                for dyaw in (-2 * SEARCH_RAD, -SEARCH_RAD, 0.0, SEARCH_RAD, 2 * SEARCH_RAD):
                    start = Pose2D(guess.x_m + dx, guess.y_m + dy, guess.yaw_rad + dyaw)
                    answer = self._match(points_xy, start, reference=guess, turn=SEARCH_TURN_RAD)
                    if isinstance(answer, str):
                        reason = reason or answer
                    else:
                        fits.append(answer)
        if not fits:
            return reason
        fits.sort(key=lambda fit: -fit.inliers)
        best = fits[0]
        for other in fits[1:]:
            apart = math.hypot(other.pose.x_m - best.pose.x_m, other.pose.y_m - best.pose.y_m)
            if apart > AMBIGUOUS_M and other.inliers > best.inliers - AMBIGUOUS_INLIERS:
                return f"the map fits in more than one place ({apart:.1f} m apart)"
        return best

    def _match(
        self,
        points_xy: NDArray[np.float64],
        guess: Pose2D,
        reference: Pose2D | None = None,
        turn: float = MAX_CORRECTION_RAD,
    ) -> MapMatch | str:
        if self._target is None or self._tree is None:
            return "no walls in the map"
        if len(points_xy) < MIN_POINTS:
            return f"{len(points_xy)} returns (< {MIN_POINTS})"
        result, source = align_to_walls(self._target, self._tree, points_xy, guess)
        if not result.converged:
            return "registration to the map did not converge"
        pose = Pose2D.of_matrix(np.asarray(result.T_target_source))
        off = (reference or guess).between(pose)
        if math.hypot(off.x_m, off.y_m) > MAX_CORRECTION_M:
            return f"the map fits {math.hypot(off.x_m, off.y_m):.1f} m from the estimate"
        if abs(off.yaw_rad) > turn:
            return f"the map fits {math.degrees(abs(off.yaw_rad)):.0f}° from the estimate"
        inliers = self._inliers(source, pose)
        if inliers < MIN_INLIER_FRACTION:
            return f"{100 * inliers:.0f} % of the scan on the map's walls"
        through = self._through_walls(points_xy, pose)
        if through > MAX_THROUGH_WALLS:
            return f"{100 * through:.0f} % of the beams would pass through the map's buildings"
        covariance, note = _covariance(np.asarray(result.H), pose.yaw_rad)
        return MapMatch(pose, covariance, inliers, note)

    def _through_walls(self, points_xy: NDArray[np.float64], pose: Pose2D) -> float:
        """The fraction of beams that, at ``pose``, would cross a building to their return.
        GICP matches a wall to any wall parallel to it, whichever side faces the sensor: in a
        street of evenly spaced buildings the far face of one gap fits the near face of the
        next. Only the free space the beams crossed tells those fits apart."""
        c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        ranges = np.hypot(points_xy[:, 0], points_xy[:, 1])
        keep = ranges > BEAM_MARGIN_M
        fractions = 1.0 - BEAM_MARGIN_M / ranges[keep]
        along = np.linspace(0.0, 1.0, BEAM_SAMPLES)[None, :] * fractions[:, None]
        x = points_xy[keep, 0][:, None] * along
        y = points_xy[keep, 1][:, None] * along
        wx = pose.x_m + c * x - s * y
        wy = pose.y_m + s * x + c * y
        inside = shapely.contains_xy(self._solid, wx.ravel(), wy.ravel()).reshape(wx.shape)
        return float(np.mean(inside.any(axis=1))) if len(inside) else 0.0

    def _inliers(self, source: small_gicp.PointCloud, pose: Pose2D) -> float:
        assert self._tree is not None
        points = np.asarray(source.points())[:, :3]
        world = points @ pose.matrix()[:3, :3].T + pose.matrix()[:3, 3]
        _index, squared = self._tree.batch_nearest_neighbor_search(world)
        near = np.asarray(squared) < INLIER_M**2
        return float(np.mean(near)) if len(near) else 0.0


def _covariance(hessian: NDArray[np.float64], yaw: float) -> tuple[NDArray[np.float64], str]:
    """The match's covariance: ``SIGMA_M`` across what the walls constrain, ``FREE_SIGMA_M``
    along a direction they do not (small_gicp's Hessian is in the scan's frame)."""
    eigen, vectors = np.linalg.eigh(hessian[3:5, 3:5])
    c, s = math.cos(yaw), math.sin(yaw)
    rotation = np.array(((c, -s), (s, c)))
    sigmas = np.array((SIGMA_M, SIGMA_M))
    note = ""
    if eigen[-1] <= 0 or eigen[0] < DEGENERATE_RATIO * eigen[-1]:
        sigmas[0] = FREE_SIGMA_M
        note = "the map's walls fix only one direction"
    axes = rotation @ vectors
    covariance = np.zeros((3, 3))
    covariance[:2, :2] = axes @ np.diag(sigmas**2) @ axes.T
    covariance[2, 2] = SIGMA_YAW_RAD**2
    return covariance, note


def align_to_walls(
    target: small_gicp.PointCloud,
    tree: small_gicp.KdTree,
    points_xy: NDArray[np.float64],
    guess: Pose2D,
    *,
    downsample_m: float = DOWNSAMPLE_M,
    max_correspondence_m: float = MAX_CORRESPONDENCE_M,
) -> tuple[small_gicp.RegistrationResult, small_gicp.PointCloud]:
    """A scan's points registered by GICP to walls prepared with their kd-tree, from
    ``guess``; and the scan as registered (downsampled, with covariances)."""
    source, _ = small_gicp.preprocess_points(extrude(points_xy), downsample_m, num_neighbors=10)
    result = small_gicp.align(
        target,
        source,
        tree,
        guess.matrix(),
        registration_type="GICP",
        max_correspondence_distance=max_correspondence_m,
        max_iterations=MAX_ITERATIONS,
    )
    return result, source
