"""What the operator is shown of perception: the scan in sectors, the occupancy grid as a
small image, the fused pose on the globe. Pure (no I/O, no clock), shared by the platform
(which makes them), the recorder and Foxglove live (which encode them) and the tests.

The scan goes in every telemetry snapshot, so it is coarse: :data:`SECTORS` sectors of equal
width clockwise from forward, each the nearest return in it in decimetres (0: none), which is
a byte each on the wire for the LD19's 12 m. The grid is too large for telemetry: the platform
keeps its latest :class:`GridImage` (the occupied and free cells, cropped to what was seen and
reduced to at most :data:`MAX_SIDE` cells a side, an obstacle in a block winning over free
space) and hands it out on request, a revision in telemetry saying when there is a new one.
"""

from __future__ import annotations

import base64
import itertools
import math
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from brasidas.autonomy.geo import LocalFrame

SECTORS = 72
"""5° sectors, as MAVLink's OBSTACLE_DISTANCE."""
MAX_SIDE = 256
"""The grid image's largest side in cells (a block of cells becomes one)."""
UNKNOWN = 255
"""A cell never seen; the others are the probability of being occupied, in percent."""
OCCUPIED_PERCENT = 65
"""From this percentage up, a cell is drawn as an obstacle."""


def sector_ranges(
    bearings_deg: Sequence[float], ranges_m: Sequence[float], sectors: int = SECTORS
) -> tuple[int, ...]:
    """The nearest return in each sector (clockwise from forward, sector 0 centred on
    forward), in decimetres; 0 where there is none."""
    width = 360.0 / sectors
    best = [0] * sectors
    for bearing, distance in zip(bearings_deg, ranges_m, strict=True):
        if distance <= 0 or not math.isfinite(distance):
            continue
        k = int(((bearing + width / 2) % 360.0) // width) % sectors
        dm = max(1, round(distance * 10))
        if best[k] == 0 or dm < best[k]:
            best[k] = dm
    return tuple(best)


def sector_points(ranges_dm: Sequence[int]) -> list[tuple[float, float]]:
    """(bearing clockwise from forward °, range m) of each sector with a return."""
    width = 360.0 / len(ranges_dm) if ranges_dm else 0.0
    return [(k * width, dm / 10) for k, dm in enumerate(ranges_dm) if dm > 0]


def heading_deg(yaw_rad: float) -> float:
    """A yaw counter-clockwise from east (the local frame's) as a heading clockwise from north."""
    return (90.0 - math.degrees(yaw_rad)) % 360.0


PlanePose = tuple[float, float, float]
"""(x east m, y north m, yaw rad counter-clockwise from east) in the localization's frame."""


def pose_at(history: Iterable[tuple[float, PlanePose]], time: float) -> PlanePose | None:
    """The pose at ``time`` from (time, pose) samples in time order: interpolated between
    the two around it (yaw the short way round), extrapolated a little after the last, the
    first before them, None without samples."""
    samples = list(history)
    if not samples:
        return None
    if time <= samples[0][0]:
        return samples[0][1]
    pairs = list(itertools.pairwise(samples))
    for (t0, a), (t1, b) in pairs:
        if t0 <= time <= t1:
            return _between(t0, a, t1, b, time)
    if pairs:  # after the last: carried on at the last two's rates, briefly
        (t0, a), (t1, b) = pairs[-1]
        return _between(t0, a, t1, b, min(time, t1 + MAX_EXTRAPOLATION_S))
    return samples[-1][1]


MAX_EXTRAPOLATION_S = 0.25
"""A scan newer than the last pose is placed where that pose was heading, this far at most."""


def _between(t0: float, a: PlanePose, t1: float, b: PlanePose, time: float) -> PlanePose:
    f = (time - t0) / (t1 - t0) if t1 > t0 else 1.0
    turn = math.remainder(b[2] - a[2], math.tau)
    return (a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), a[2] + f * turn)


def reframe(
    bearing_deg: float, range_m: float, then: PlanePose, now: PlanePose
) -> tuple[float, float]:
    """A point seen at ``bearing_deg`` (clockwise from forward) and ``range_m`` from the
    robot at pose ``then``, as seen from pose ``now``: where a scan taken a moment ago lies
    around the pose shown with it (a turning robot's scan is otherwise drawn rotated)."""
    world = then[2] - math.radians(bearing_deg)
    x = then[0] + range_m * math.cos(world) - now[0]
    y = then[1] + range_m * math.sin(world) - now[1]
    bearing = (math.degrees(now[2] - math.atan2(y, x))) % 360.0
    return bearing, math.hypot(x, y)


@dataclass(frozen=True)
class GridImage:
    """The occupancy grid as one byte a cell, row 0 the southernmost, column 0 the westernmost,
    in the local frame anchored at ``latitude``, ``longitude`` (x east, y north, metres)."""

    latitude: float
    longitude: float
    x_m: float
    """The south-west corner of cell [0, 0], east of the anchor."""
    y_m: float
    cell_m: float
    columns: int
    rows: int
    cells: bytes
    """``rows`` x ``columns`` bytes: occupancy percent (0-100) or :data:`UNKNOWN`."""
    scans: int
    """Scans the grid holds (a new one: more)."""

    def corners(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """(latitude, longitude) of the south-west and north-east corners."""
        frame = LocalFrame(self.latitude, self.longitude)
        south_west = frame.to_geo(self.x_m, self.y_m)
        north_east = frame.to_geo(
            self.x_m + self.columns * self.cell_m, self.y_m + self.rows * self.cell_m
        )
        return south_west, north_east

    def occupied_cells(self) -> int:
        data = np.frombuffer(self.cells, dtype=np.uint8)
        return int(np.count_nonzero((data >= OCCUPIED_PERCENT) & (data != UNKNOWN)))

    def to_json(self, rev: int) -> dict[str, Any]:
        """The answer of the platform's ``get_grid``: the cells zlib-compressed, base64."""
        south_west, north_east = self.corners()
        return {
            "rev": rev,
            "anchor": [self.latitude, self.longitude],
            "origin": [self.x_m, self.y_m],
            "cell_m": self.cell_m,
            "columns": self.columns,
            "rows": self.rows,
            "south_west": list(south_west),
            "north_east": list(north_east),
            "scans": self.scans,
            "cells": base64.b64encode(zlib.compress(self.cells, 6)).decode("ascii"),
        }


class GridRefused(ValueError):
    """A ``get_grid`` answer that is not a grid (from a platform we talk to, still checked)."""


def grid_from_json(answer: Mapping[str, Any], max_cells: int = MAX_SIDE * MAX_SIDE) -> GridImage:
    """A :class:`GridImage` back from :meth:`GridImage.to_json` (the station's side)."""
    try:
        columns, rows = int(answer["columns"]), int(answer["rows"])
        if columns < 0 or rows < 0 or columns * rows > max_cells:
            raise GridRefused(f"{columns} x {rows} cells is not a grid image")
        packed = base64.b64decode(answer["cells"], validate=True)
        inflater = zlib.decompressobj()
        cells = inflater.decompress(packed, columns * rows + 1)
        if len(cells) != columns * rows:
            raise GridRefused(f"{len(cells)} bytes of cells for {columns} x {rows}")
        latitude, longitude = (float(v) for v in answer["anchor"])
        x_m, y_m = (float(v) for v in answer["origin"])
        return GridImage(
            latitude,
            longitude,
            x_m,
            y_m,
            float(answer["cell_m"]),
            columns,
            rows,
            cells,
            int(answer.get("scans", 0)),
        )
    except (KeyError, TypeError, ValueError, zlib.error) as err:
        if isinstance(err, GridRefused):
            raise
        raise GridRefused(f"not a grid image: {err}") from None


def grid_image(
    latitude: float,
    longitude: float,
    origin_xy: Sequence[float],
    resolution_m: float,
    log_odds: NDArray[np.float32],
    scans: int,
    max_side: int = MAX_SIDE,
) -> GridImage | None:
    """The seen part of an occupancy grid (:class:`~brasidas.perception.grid.OccupancyGrid`'s
    arrays), reduced by whole blocks to at most ``max_side`` cells a side; None when nothing
    was seen."""
    seen = log_odds != 0
    if not seen.any():
        return None
    rows_seen = np.flatnonzero(seen.any(axis=1))
    cols_seen = np.flatnonzero(seen.any(axis=0))
    r0, r1 = int(rows_seen[0]), int(rows_seen[-1]) + 1
    c0, c1 = int(cols_seen[0]), int(cols_seen[-1]) + 1
    crop = log_odds[r0:r1, c0:c1].astype(np.float32)
    block = max(1, math.ceil(max(crop.shape) / max_side))
    rows, cols = -(-crop.shape[0] // block), -(-crop.shape[1] // block)
    padded = np.zeros((rows * block, cols * block), dtype=np.float32)
    padded[: crop.shape[0], : crop.shape[1]] = crop
    blocks = padded.reshape(rows, block, cols, block).transpose(0, 2, 1, 3).reshape(rows, cols, -1)
    # The block's most occupied seen cell: an obstacle anywhere in it is kept.
    strongest = np.where(blocks != 0, blocks, -np.inf).max(axis=2)
    known = np.isfinite(strongest)
    # Within +-30 (0 % and 100 % once rounded): a long-seen free cell's float32 log-odds past
    # -88 overflowed exp() (a RuntimeWarning a driven loop raised) for the same 0 %.
    odds = np.clip(np.where(known, strongest, 0.0), -30.0, 30.0)
    percent = np.rint(100.0 / (1.0 + np.exp(-odds)))
    cells = np.where(known, percent, UNKNOWN).astype(np.uint8)
    return GridImage(
        latitude,
        longitude,
        float(origin_xy[0]) + c0 * resolution_m,
        float(origin_xy[1]) + r0 * resolution_m,
        resolution_m * block,
        cols,
        rows,
        cells.tobytes(),
        scans,
    )
