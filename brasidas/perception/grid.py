"""An occupancy grid built from the scans at the fused pose, kept on the robot (R-12). Pure.

Cells of ``resolution_m`` hold log-odds of being occupied: each return marks its cell more
occupied and the cells its beam crossed more free (clamped, so a parked car that leaves is
forgotten again after a few passes). The grid is in the localizer's geo-anchored local frame
(metres east and north of ``latitude``, ``longitude``) and grows in ``CHUNK_CELLS`` steps as
the robot goes. Saved as a NumPy ``.npz`` (no pickles) with its anchor, written atomically;
loaded at start, a file that is not a grid is refused with the reason and a new grid begun.

Scans are integrated at the fused pose as they come; when the pose graph
(:mod:`brasidas.perception.pose_graph`) closes a loop the grid is rebuilt from its keyframes at
their smoothed poses (:meth:`OccupancyGrid.rebuilt`). The robot's last pose is saved with the
grid, so a robot without GPS starts where it stopped, in the map's own frame.
"""

from __future__ import annotations

import math
import os
import zipfile
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from brasidas.perception.odometry import Pose2D

HIT = 0.85
MISS = -0.4
CLAMP = 5.0
CHUNK_CELLS = 128
MAX_CELLS = 8192
"""A side of at most 8192 cells (820 m at 0.1 m; 268 MB as float32 would be too much for a
Pi: at 0.1 m the practical limit is a few hundred metres a side)."""
FORMAT = 1


class GridError(Exception):
    """A file that is not a grid this version can read."""


class OccupancyGrid:
    def __init__(
        self, latitude: float, longitude: float, resolution_m: float = 0.1, max_range_m: float = 12
    ) -> None:
        self.latitude = latitude
        self.longitude = longitude
        self.resolution = resolution_m
        self.max_range = max_range_m
        self.origin = np.zeros(2)
        """The world position (east, north) of cell [0, 0]'s corner."""
        self.log_odds: NDArray[np.float32] = np.zeros((0, 0), dtype=np.float32)
        self.scans = 0
        self.pose: Pose2D | None = None
        """Where the robot was when the grid was saved (None: not known)."""
        self.geo = True
        """The anchor is a GPS position (False: a map frame of the robot's own, never tied to
        latitude and longitude: GPS fixes are not positions in it)."""

    def rebuilt(self, keyframes: list[tuple[Pose2D, NDArray[np.float32]]]) -> OccupancyGrid:
        """A copy of this grid with ``keyframes``' scans integrated at their poses (on an
        empty grid: the map as a corrected path saw it)."""
        grid = OccupancyGrid(self.latitude, self.longitude, self.resolution, self.max_range)
        grid.origin = self.origin.copy()
        grid.log_odds = self.log_odds.copy()
        grid.scans = self.scans
        grid.pose = self.pose
        grid.geo = self.geo
        for pose, points in keyframes:
            grid.integrate(pose, np.asarray(points, dtype=float))
        return grid

    def integrate(self, pose: Pose2D, points_xy: NDArray[np.float64]) -> None:
        """One scan (robot frame) taken at ``pose`` (east, north, yaw)."""
        if not len(points_xy):
            return
        c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        ends = np.column_stack(
            (
                pose.x_m + c * points_xy[:, 0] - s * points_xy[:, 1],
                pose.y_m + s * points_xy[:, 0] + c * points_xy[:, 1],
            )
        )
        start = np.array((pose.x_m, pose.y_m))
        self._cover(np.vstack((ends, start[None, :])))
        # Free cells: samples along each beam, short of its end by a cell.
        lengths = np.hypot(*(ends - start).T)
        steps = np.maximum(1, (lengths / self.resolution).astype(int))
        fractions = np.concatenate([np.arange(n) / n for n in steps])
        beams = np.repeat(ends - start, steps, axis=0)
        free = self._cells(start + beams * fractions[:, None])
        hit = self._cells(ends)
        grid = self.log_odds
        np.add.at(grid, (free[:, 1], free[:, 0]), MISS)
        np.add.at(grid, (hit[:, 1], hit[:, 0]), HIT - MISS)  # the end was counted free too
        np.clip(grid, -CLAMP, CLAMP, out=grid)
        self.scans += 1

    def _cells(self, world: NDArray[np.float64]) -> NDArray[np.intp]:
        return np.floor((world - self.origin) / self.resolution).astype(np.intp)

    def _cover(self, world: NDArray[np.float64]) -> None:
        """Grow the array (in chunks) so every point falls inside it."""
        lo, hi = world.min(axis=0), world.max(axis=0)
        rows, cols = self.log_odds.shape
        if rows == 0:
            self.origin = np.floor(lo / self.resolution) * self.resolution
        first = self._cells(lo[None, :])[0]
        last = self._cells(hi[None, :])[0]
        pad_lo = np.maximum(0, -first)
        pad_hi = np.maximum(0, last + 1 - np.array((cols, rows)))
        if not (pad_lo.any() or pad_hi.any()):
            return
        pad_lo = -(-pad_lo // CHUNK_CELLS) * CHUNK_CELLS
        pad_hi = -(-pad_hi // CHUNK_CELLS) * CHUNK_CELLS
        if max(cols + pad_lo[0] + pad_hi[0], rows + pad_lo[1] + pad_hi[1]) > MAX_CELLS:
            raise GridError(f"the grid would exceed {MAX_CELLS} cells a side")
        self.log_odds = np.pad(self.log_odds, ((pad_lo[1], pad_hi[1]), (pad_lo[0], pad_hi[0])))
        self.origin = self.origin - pad_lo * self.resolution

    def occupied(self, x_m: float, y_m: float) -> float:
        """Probability that the cell at (east, north) is occupied (0.5: never seen)."""
        col, row = self._cells(np.array(((x_m, y_m),)))[0]
        rows, cols = self.log_odds.shape
        if not (0 <= row < rows and 0 <= col < cols):
            return 0.5
        return float(1.0 / (1.0 + math.exp(-float(self.log_odds[row, col]))))

    def save(self, path: Path) -> None:
        """Atomically: a crash mid-write leaves the previous grid."""
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(path.name + ".partial.npz")
        np.savez_compressed(
            partial,
            format=np.array(FORMAT),
            anchor=np.array((self.latitude, self.longitude)),
            resolution=np.array(self.resolution),
            origin=self.origin,
            log_odds=self.log_odds,
            scans=np.array(self.scans),
            geo=np.array(self.geo),
            pose=np.array(
                (self.pose.x_m, self.pose.y_m, self.pose.yaw_rad) if self.pose else (np.nan,) * 3
            ),
        )
        os.replace(partial, path)

    @classmethod
    def load(cls, path: Path) -> OccupancyGrid:
        """The grid saved at ``path``; :class:`GridError` saying why when it is not one."""
        try:
            with np.load(path, allow_pickle=False) as data:
                if int(data["format"]) != FORMAT:
                    raise GridError(f"{path}: grid format {int(data['format'])}, not {FORMAT}")
                latitude, longitude = (float(v) for v in data["anchor"])
                grid = cls(latitude, longitude, float(data["resolution"]))
                grid.origin = np.asarray(data["origin"], dtype=float).reshape(2)
                log_odds = np.asarray(data["log_odds"], dtype=np.float32)
                grid.scans = int(data["scans"])
                pose = np.asarray(data["pose"], dtype=float) if "pose" in data else None
                grid.geo = bool(data["geo"]) if "geo" in data else True
        except GridError:
            raise
        except (
            OSError,
            EOFError,
            ValueError,
            KeyError,
            TypeError,
            AttributeError,
            zipfile.BadZipFile,
        ) as err:
            raise GridError(f"{path}: not a saved grid ({err})") from None
        if log_odds.ndim != 2 or max(log_odds.shape) > MAX_CELLS or not grid.resolution > 0:
            raise GridError(f"{path}: grid of shape {log_odds.shape} refused")
        if not (-90 <= latitude <= 90 and -180 <= longitude <= 180):
            raise GridError(f"{path}: anchor {latitude}, {longitude} is not on Earth")
        grid.log_odds = np.clip(np.nan_to_num(log_odds), -CLAMP, CLAMP)
        if pose is not None and pose.shape == (3,) and np.isfinite(pose).all():
            grid.pose = Pose2D(float(pose[0]), float(pose[1]), float(pose[2]))
        return grid
