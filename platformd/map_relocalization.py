"""Placing the robot in its saved map without GPS, and noticing when it is no longer there.

The localizer (:mod:`platformd.lidar_localization`) owns one :class:`MapPlacer` per loaded grid
and calls it from its worker thread (never the event loop: a search takes tenths of a second in
a room, seconds in a town). Without GPS the fusion starts only once a scan is placed in the
saved map with confidence (:mod:`brasidas.perception.relocalize`) and the next scan, searched
for afresh, is found where the odometry says (a confirmed place); until then, and while a
place is ambiguous, the robot holds and says why, and a new search is made every
``RETRY_S`` (the operator may drive it by hand to a place that tells). After it is placed, every
``CHECK_EVERY`` scans the scan is registered to the saved map from the fused pose: a clear fit
nearby is an absolute measurement for the fusion (as the area map's walls are with GPS), which
keeps the odometry's drift out. Where it does not fit, its fit is measured over the points
that fall where the map knows something (a place it never mapped says nothing); ``LOST_AFTER``
poor fits in a row and the match is lost: the robot holds and searches again.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray

from brasidas.perception.grid import OccupancyGrid
from brasidas.perception.odometry import Pose2D
from brasidas.perception.relocalize import GridRelocalizer, Relocalization

_LOGGER = logging.getLogger(__name__)

RETRY_S = 2.0
"""Between searches while the robot is not placed."""
CHECK_EVERY = 3
"""Scans between registrations to the saved map once placed (3 a second for a 10 Hz lidar)."""
LOST_FIT = 0.3
LOST_AFTER = 6
"""Fits under ``LOST_FIT`` in a row (1.8 s at 10 Hz) after which the match is lost."""
MIN_KNOWN_POINTS = 40
"""A fit over fewer points the map knows something about tells nothing."""
PLACED_SIGMAS = (0.15, math.radians(2.0))
"""The fusion's start at a placed pose (the refined registration's, the grid's cells)."""
CONFIRM_M = 0.3
CONFIRM_RAD = math.radians(3.0)
"""The second scan's place must be this close to the first's carried by the odometry."""
TRACK_FIT = 0.6
"""A registration to the saved map is fused only where this much of the scan fits it."""
TRACK_MAX_M = 1.5
TRACK_MAX_RAD = math.radians(25.0)
"""...and only this close to the fused pose (further: a look-alike place, not a correction)."""
TRACK_COVARIANCE = np.diag((0.1**2, 0.1**2, math.radians(1.0) ** 2))
"""Of a registration to the saved grid (its 0.1 m cells)."""
SEARCHING = "searching the saved map for the robot (no GPS)"


class MapPlacer:
    """(Worker thread.) A loaded grid in; scans in, a confident pose or why not out."""

    def __init__(self, grid: OccupancyGrid) -> None:
        self.relocalizer = GridRelocalizer(grid)
        self.status = SEARCHING
        """What the operator is told: searching, placed (with the fit), why not, or lost."""
        self.placed = False
        self.last: Relocalization | None = None
        self.searches = 0
        self.placements = 0
        self.losses = 0
        self._searched_at: float | None = None
        self._candidate: tuple[Pose2D, Pose2D] | None = None
        """A place found, waiting for the next scan to confirm it: (place, odometry then)."""
        self.unconfirmed = 0
        self._poor = 0
        self._scans = 0

    @property
    def hold(self) -> str:
        """Why the pose must not be driven on now ("" once placed)."""
        return "" if self.placed else self.status

    def search(
        self, points: NDArray[np.float64], now: float, hint: Pose2D | None, odometry: Pose2D
    ) -> Pose2D | None:
        """The scan placed in the map; None when not (yet): not due, not confident, or not yet
        confirmed. ``odometry``: the odometry's pose now (its own frame), to carry a candidate
        to the next scan. A place is taken only when the next scan, searched for afresh, is
        found where the first place moved by the odometry says it should be: one scan can
        fit a wrong place well (a moving robot's skewed scan, a passer-by)."""
        candidate = self._candidate
        if (
            candidate is None
            and self._searched_at is not None
            and now - self._searched_at < RETRY_S
        ):
            return None
        self._searched_at = now
        self.searches += 1
        answer = self.relocalizer.locate(points, hint)
        self.last = answer
        if answer.pose is None:
            self._candidate = None
            status = f"holding, not placed in the saved map: {answer.reason}"
            if status != self.status:
                _LOGGER.warning("localization: %s", status)
            self.status = status
            return None
        if candidate is None:
            self._candidate = (answer.pose, odometry)
            self.status = (
                "holding: a place found in the saved map, confirming it with the next scan"
            )
            return None
        self._candidate = None
        first, odometry_then = candidate
        expected = first.compose(odometry_then.between(odometry))
        off = expected.between(answer.pose)
        if math.hypot(off.x_m, off.y_m) > CONFIRM_M or abs(off.yaw_rad) > CONFIRM_RAD:
            self.unconfirmed += 1
            self.status = (
                "holding, not placed in the saved map: the next scan was found "
                f"{math.hypot(off.x_m, off.y_m):.1f} m, {math.degrees(abs(off.yaw_rad)):.0f}° "
                "from the first"
            )
            _LOGGER.warning("localization: %s", self.status)
            return None
        self.placed = True
        self.placements += 1
        self._poor = 0
        self.status = (
            f"placed in the saved map (fit {100 * answer.score:.0f} %, next best "
            f"{100 * answer.runner_up:.0f} %)"
        )
        _LOGGER.info(
            "localization: %s at (%.1f, %.1f) m, %.0f° in %.2f s",
            self.status,
            answer.pose.x_m,
            answer.pose.y_m,
            math.degrees(answer.pose.yaw_rad),
            answer.seconds,
        )
        return answer.pose

    def track(
        self, points: NDArray[np.float64], pose: Pose2D
    ) -> tuple[tuple[Pose2D, NDArray[np.float64]] | None, bool]:
        """Every ``CHECK_EVERY`` scans once placed: the scan registered to the saved map from
        ``pose`` (the fused pose), as an absolute measurement for the fusion (pose and
        covariance; None when it does not fit there clearly), and whether the match has just
        been lost (``LOST_AFTER`` poor fits in a row)."""
        self._scans += 1
        if not self.placed or self._scans % CHECK_EVERY:
            return None, False
        match = self.relocalizer.register(points, pose)
        if match is not None:
            fitted, fit = match
            off = pose.between(fitted)
            if (
                fit >= TRACK_FIT
                and math.hypot(off.x_m, off.y_m) <= TRACK_MAX_M
                and abs(off.yaw_rad) <= TRACK_MAX_RAD
            ):
                self._poor = 0
                return (fitted, TRACK_COVARIANCE), False
        fit_known = self.relocalizer.known_fit(points, pose, MIN_KNOWN_POINTS)
        if fit_known is None:
            return None, False  # off the saved map: the new scans map it, nothing to compare
        self._poor = self._poor + 1 if fit_known < LOST_FIT else 0
        if self._poor < LOST_AFTER:
            return None, False
        self.placed = False
        self.losses += 1
        self._poor = 0
        self._searched_at = None
        self.status = (
            f"lost: the scans no longer fit the saved map ({100 * fit_known:.0f} %); "
            "searching it again"
        )
        _LOGGER.warning("localization: %s", self.status)
        return None, True
