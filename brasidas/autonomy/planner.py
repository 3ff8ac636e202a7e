"""Shortest paths inside the boundary around keep-out zones (R-5.3.3.1).

A reduced visibility graph: the keep-outs are inflated and the boundary shrunk by the
clearance (mitred offsets, never closer than the clearance); its nodes are the corners of
that free space that bend around an obstacle, its edges the node pairs that see each other
and leave both ends tangent to their obstacles (no shortest path uses any other). The graph
is built once per map (:class:`Planner`); a plan connects the start and the goal to it and
runs A*. Visibility is checked against slightly smaller obstacles so that segments grazing
a corner are not lost to rounding.
"""

from __future__ import annotations

import copy
import heapq
import math
import threading
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import shapely
from shapely import LinearRing, MultiPolygon, Point, Polygon, unary_union
from shapely.geometry.base import BaseGeometry
from shapely.geometry.polygon import orient

CHUNK = 50_000
"""Node pairs checked at once (bounds the build's memory: ~100 bytes a pair)."""
SAMPLE_ROUNDS = 4
"""Rounds of points tested along a segment before the whole segment is (1, 2, 4, 8 points)."""
RASTER_SAMPLES = 63
"""Points tested along a segment in the free space's raster, evenly spaced."""
RASTER_BLOCK = 2048
"""Segments sampled at once in the raster (bounds the arrays: 63 points a segment)."""
RASTER_CELLS = 4_000_000
"""The raster's cells at most (4 MB); 1 m cells up to 2 km x 2 km, larger beyond."""
CHECK_MARGIN = 0.98
"""Visibility is checked against obstacles inflated by this fraction of the clearance."""
MITRE_LIMIT = 2.0

XY = tuple[float, float]


class BuildCancelled(Exception):
    """The planner's build was stopped (its ``cancelled`` event was set)."""


class Unreachable(Exception):
    """No drivable path; the message says why (for the operator)."""


@dataclass(frozen=True)
class Path:
    points: tuple[XY, ...]
    """From the start to the goal, in the map's local frame (metres)."""

    @property
    def length(self) -> float:
        return sum(math.dist(a, b) for a, b in zip(self.points, self.points[1:], strict=False))


class Planner:
    """The visibility graph of one map at one clearance; :meth:`plan` is cheap, building is not
    (seconds for thousands of buildings: the platform builds it in a process of its own,
    :mod:`brasidas.autonomy.planner_worker`). :meth:`changed` gives the
    graph with keep-outs added or removed, reusing what they do not touch."""

    def __init__(
        self,
        boundary: Polygon | MultiPolygon,
        keepouts: Mapping[str, BaseGeometry] | Iterable[BaseGeometry],
        clearance: float,
        cancelled: threading.Event | None = None,
    ) -> None:
        """Build the graph; setting ``cancelled`` (from another thread) stops the build with
        :class:`BuildCancelled` within one block of node pairs."""
        if clearance < 0:
            raise ValueError("clearance must be >= 0")
        zones = (
            dict(keepouts)
            if isinstance(keepouts, Mapping)
            else dict((str(index), zone) for index, zone in enumerate(keepouts))
        )
        self.clearance = clearance
        self._cancelled = cancelled
        self._boundary = boundary
        self._zones = zones
        self._inflated = {key: _inflate(zone, clearance) for key, zone in zones.items()}
        self._checked = {
            key: _inflate(zone, clearance * CHECK_MARGIN) for key, zone in zones.items()
        }
        self._shrunk = _inflate(boundary, -clearance) if clearance > 0 else boundary
        self._shrunk_checked = (
            _inflate(boundary, -clearance * CHECK_MARGIN) if clearance > 0 else boundary
        )
        self._space = _minus(self._shrunk, list(self._inflated.values()))
        self._escape = _prepared(_minus(boundary, list(zones.values())))
        self._free = _prepared(_minus(self._shrunk_checked, list(self._checked.values())))
        self._stop_if_cancelled()
        self._raster = Raster(self._free, cancelled=cancelled)
        self.nodes, self._before, self._after = _corners(self._space)
        self._edge_u, self._edge_v = self._visible_pairs(_pair_blocks(self.nodes))
        self._edges = self._adjacency()
        self._points: list[XY] = [(x, y) for x, y in self.nodes.tolist()]
        self._cancelled = None

    def _stop_if_cancelled(self) -> None:
        if self._cancelled is not None and self._cancelled.is_set():
            raise BuildCancelled("the planner's build was stopped")

    @property
    def edge_count(self) -> int:
        return len(self._edge_u)

    def changed(
        self,
        add: Mapping[str, BaseGeometry],
        remove: Iterable[str] = (),
        cancelled: threading.Event | None = None,
    ) -> Planner:
        """A planner for the same map with keep-outs added (by id) and removed (by id): the
        free space is cut or reopened where they are, and only the graph's edges that can
        have changed are checked again. This planner is left as it was."""
        new = copy.copy(self)
        new._cancelled = cancelled
        new._zones, new._inflated, new._checked = (
            dict(self._zones), dict(self._inflated), dict(self._checked)
        )  # fmt: skip
        reopened: list[BaseGeometry] = []
        space, free, escape = self._space, self._free, self._escape
        for key in remove:
            zone = new._zones.pop(key)
            inflated, checked = new._inflated.pop(key), new._checked.pop(key)
            space = _reopen(space, self._shrunk, inflated, new._inflated)
            free = _reopen(free, self._shrunk_checked, checked, new._checked)
            escape = _reopen(escape, self._boundary, zone, new._zones)
            reopened.append(checked)
        for key, zone in add.items():
            new._zones[key] = zone
            new._inflated[key] = inflated = _inflate(zone, self.clearance)
            new._checked[key] = _inflate(zone, self.clearance * CHECK_MARGIN)
            space = space.difference(inflated)
            free = free.difference(new._checked[key])
            escape = escape.difference(zone)
        new._space, new._free, new._escape = space, _prepared(free), _prepared(escape)
        changed_where = [new._checked[key] for key in add] + reopened
        new._raster = self._raster.redrawn(new._free, changed_where, cancelled)
        new.nodes, new._before, new._after = _corners(space)
        # Nodes that are still there (same corner, same neighbours) keep their index's edges.
        old = {
            key: index
            for index, key in enumerate(_node_keys(self.nodes, self._before, self._after))
        }
        moved = np.array(
            [old.get(key, -1) for key in _node_keys(new.nodes, new._before, new._after)],
            dtype=np.int64,
        )
        renumber = np.full(len(self.nodes) + 1, -1, dtype=np.int64)
        kept = np.flatnonzero(moved >= 0)
        renumber[moved[kept]] = kept
        u, v = renumber[self._edge_u], renumber[self._edge_v]
        alive = (u >= 0) & (v >= 0)
        u, v = u[alive], v[alive]
        if add:
            cut = [new._checked[key] for key in add]
            crossed = _crossing(new.nodes[u], new.nodes[v], cut)
            if crossed.any():
                still = shapely.covers(
                    new._free, shapely.linestrings(_segments(new.nodes, u[crossed], v[crossed]))
                )
                crossed[np.flatnonzero(crossed)[still]] = False
            u, v = u[~crossed], v[~crossed]
        fresh = np.flatnonzero(moved < 0)
        pairs_u: list[npt.NDArray[np.int64]] = [u]
        pairs_v: list[npt.NDArray[np.int64]] = [v]
        if len(fresh):  # new corners: against every node
            rows, columns = np.meshgrid(fresh, np.arange(len(new.nodes)), indexing="ij")
            a, b = rows.ravel(), columns.ravel()
            keep = (a != b) & ~(np.isin(b, fresh) & (b < a))
            found = new._visible_pairs([(a[keep], b[keep])])
            pairs_u.append(found[0])
            pairs_v.append(found[1])
        if reopened and len(kept):  # old corners that may see each other through a gap
            found = new._visible_pairs(_pair_blocks(new.nodes, kept, reopened))
            pairs_u.append(found[0])
            pairs_v.append(found[1])
        u, v = np.concatenate(pairs_u), np.concatenate(pairs_v)
        u, v = np.minimum(u, v), np.maximum(u, v)
        unique = np.unique(u * (len(new.nodes) + 1) + v)
        new._edge_u, new._edge_v = unique // (len(new.nodes) + 1), unique % (len(new.nodes) + 1)
        new._edges = new._adjacency()
        new._points = [(x, y) for x, y in new.nodes.tolist()]
        new._cancelled = None
        return new

    def plan(self, start: XY, goal: XY) -> Path:
        """The shortest path from ``start`` to ``goal``, or raise :class:`Unreachable`.

        A start within the clearance of a keep-out (but not in it) may leave it by the
        shortest way out; a goal there is unreachable.
        """
        self._check_goal(goal)
        start_space = self._free
        if not self._free.covers(Point(start)):
            if not self._escape.covers(Point(start)):
                raise Unreachable(f"the start ({start[0]:.1f}, {start[1]:.1f}) is not drivable")
            start_space = self._escape
        if start_space.covers(shapely.LineString([start, goal])):
            return Path((start, goal))
        n = len(self.nodes)
        from_start = self._seen_from(start, start_space)
        to_goal = self._seen_from(goal, self._free)
        # A* over nodes 0..n-1, start n, goal n+1; the heuristic is the straight line.
        goal_index = n + 1
        points = [*self._points, start, goal]
        best = {n: 0.0}
        parent: dict[int, int] = {}
        queue = [(math.dist(start, goal), n)]
        done: set[int] = set()
        while queue:
            _, node = heapq.heappop(queue)
            if node in done:
                continue
            if node == goal_index:
                return Path(tuple(_walk(parent, node, points)))
            done.add(node)
            if node == n:
                neighbours: Iterable[tuple[int, float]] = (
                    (int(i), math.dist(start, points[int(i)])) for i in from_start
                )
            else:
                neighbours = self._edges[node]
                if node in to_goal:
                    neighbours = [*neighbours, (goal_index, math.dist(points[node], goal))]
            cost = best[node]
            for other, length in neighbours:
                total = cost + length
                if total < best.get(other, math.inf):
                    best[other] = total
                    parent[other] = node
                    heapq.heappush(queue, (total + math.dist(points[other], goal), other))
        raise Unreachable("no path around the keep-out zones leads there")

    def _check_goal(self, goal: XY) -> None:
        point = Point(goal)
        if self._free.covers(point):
            return
        if not self._escape.covers(point):
            raise Unreachable("it is outside the boundary or in a keep-out zone")
        for key, inflated in self._checked.items():
            if inflated.covers(point):
                raise Unreachable(
                    f"it is {self._zones[key].boundary.distance(point):.1f} m from a keep-out "
                    f"zone (clearance {self.clearance:g} m)"
                )
        raise Unreachable(f"it is closer than {self.clearance:g} m to the boundary")

    def _seen_from(self, point: XY, space: BaseGeometry) -> set[int]:
        if not len(self.nodes):
            return set()
        # Only nodes the segment grazes can be a shortest path's first (or last) bend.
        d = self.nodes - np.asarray(point, dtype=np.float64)
        candidates = np.flatnonzero(
            _tangent(d, self._before - self.nodes, self._after - self.nodes)
        )
        starts = np.broadcast_to(np.asarray(point, dtype=np.float64), (len(candidates), 2))
        raster = self._raster if space is self._free else None
        visible = _covered(space, starts, self.nodes[candidates], raster)
        return set(candidates[visible].tolist())

    def _visible_pairs(
        self, blocks: Iterable[tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]]
    ) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
        """The node pairs that are edges: both ends tangent, the segment in the free space."""
        found_u, found_v = [], []
        for i, j in blocks:
            if self._cancelled is not None and self._cancelled.is_set():
                raise BuildCancelled("the planner's build was stopped")
            a, b = self.nodes[i], self.nodes[j]
            d = b - a
            keep = _tangent(d, self._before[i] - a, self._after[i] - a) & _tangent(
                d, self._before[j] - b, self._after[j] - b
            )
            i, j = i[keep], j[keep]
            visible = _covered(self._free, self.nodes[i], self.nodes[j], self._raster)
            found_u.append(i[visible])
            found_v.append(j[visible])
        if not found_u:
            return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
        return np.concatenate(found_u), np.concatenate(found_v)

    def _adjacency(self) -> list[list[tuple[int, float]]]:
        edges: list[list[tuple[int, float]]] = [[] for _ in range(len(self.nodes))]
        u, v = self._edge_u, self._edge_v
        lengths = np.hypot(*(self.nodes[v] - self.nodes[u]).T) if len(u) else np.empty(0)
        for a, b, length in zip(u.tolist(), v.tolist(), lengths.tolist(), strict=True):
            edges[a].append((b, length))
            edges[b].append((a, length))
        return edges


class Raster:
    """Where a point may be in a space, on a grid: a cell is False when all of it is outside
    the space (its centre is further than half its diagonal from it), so a point in a False
    cell is certainly outside; True says nothing. Built in the planner's thread; looked up
    with NumPy, so testing many points along many segments costs next to nothing."""

    def __init__(
        self,
        space: BaseGeometry,
        cells: int = RASTER_CELLS,
        cancelled: threading.Event | None = None,
    ) -> None:
        self._cancelled = cancelled
        minx, miny, maxx, maxy = space.bounds if not space.is_empty else (0.0, 0.0, 1.0, 1.0)
        self.cell = max(1.0, math.sqrt((maxx - minx) * (maxy - miny) / cells))
        self.x0, self.y0 = minx - self.cell, miny - self.cell
        self.nx = int((maxx - self.x0) / self.cell) + 2
        self.ny = int((maxy - self.y0) / self.cell) + 2
        self.grid = np.zeros((self.ny, self.nx), dtype=bool)
        self._draw(space, 0, self.nx, 0, self.ny)
        self._cancelled = None

    def redrawn(
        self,
        space: BaseGeometry,
        where: list[BaseGeometry],
        cancelled: threading.Event | None = None,
    ) -> Raster:
        """A copy with the cells under ``where`` (changed zones) drawn again from ``space``."""
        new = copy.copy(self)
        new._cancelled = cancelled
        new.grid = self.grid.copy()
        for geometry in where:
            minx, miny, maxx, maxy = geometry.bounds
            col0, row0 = new._index(minx - new.cell, miny - new.cell)
            col1, row1 = new._index(maxx + new.cell, maxy + new.cell)
            new._draw(
                space, max(col0, 0), min(col1 + 1, new.nx), max(row0, 0), min(row1 + 1, new.ny)
            )
        new._cancelled = None
        return new

    def maybe_inside(
        self, xs: npt.NDArray[np.float64], ys: npt.NDArray[np.float64]
    ) -> npt.NDArray[np.bool_]:
        """False for the points certainly outside the space (any shape of arrays)."""
        cols = np.clip(((xs - self.x0) / self.cell).astype(np.int64), 0, self.nx - 1)
        rows = np.clip(((ys - self.y0) / self.cell).astype(np.int64), 0, self.ny - 1)
        result: npt.NDArray[np.bool_] = self.grid[rows, cols]
        return result

    def _index(self, x: float, y: float) -> tuple[int, int]:
        return int((x - self.x0) // self.cell), int((y - self.y0) // self.cell)

    def _draw(self, space: BaseGeometry, col0: int, col1: int, row0: int, row1: int) -> None:
        if col1 <= col0 or row1 <= row0:
            return
        grown = _prepared(space.buffer(self.cell * 0.7072, quad_segs=2))
        xs = self.x0 + (np.arange(col0, col1) + 0.5) * self.cell
        step = max(1, 200_000 // max(len(xs), 1))
        for first in range(row0, row1, step):
            last = min(first + step, row1)
            if self._cancelled is not None and self._cancelled.is_set():
                raise BuildCancelled("the planner's build was stopped")
            ys = self.y0 + (np.arange(first, last) + 0.5) * self.cell
            gx, gy = np.meshgrid(xs, ys)
            self.grid[first:last, col0:col1] = shapely.contains_xy(grown, gx, gy)


def cross_track(path: Sequence[XY], point: XY) -> float:
    """Distance from a point to a polyline (metres)."""
    if len(path) == 1:
        return math.dist(path[0], point)
    return float(shapely.LineString(path).distance(Point(point)))


# --------------------------------------------------------------------------- helpers


def _inflate(geometry: BaseGeometry, distance: float) -> BaseGeometry:
    """Offset by ``distance`` (negative shrinks) with mitred corners: never nearer than it."""
    return geometry.buffer(distance, join_style="mitre", mitre_limit=MITRE_LIMIT)


def _prepared(geometry: BaseGeometry) -> BaseGeometry:
    shapely.prepare(geometry)
    return geometry


def _minus(space: BaseGeometry, zones: list[BaseGeometry]) -> BaseGeometry:
    return space.difference(unary_union(zones)) if zones else space


def _reopen(
    space: BaseGeometry, whole: BaseGeometry, region: BaseGeometry, others: Mapping[str, Any]
) -> BaseGeometry:
    """``space`` with ``region`` given back, except where ``whole`` ends or other zones are."""
    back = whole.intersection(region)
    near = [zone for zone in others.values() if zone.intersects(region)]
    return space.union(_minus(back, near))


def _pair_blocks(
    nodes: npt.NDArray[np.float64],
    among: npt.NDArray[np.int64] | None = None,
    through: list[BaseGeometry] | None = None,
) -> Iterator[tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]]:
    """Every pair i < j of the nodes (of ``among``), in blocks of rows of about
    :data:`CHUNK` pairs (memory stays bounded on a large map); with ``through``, only the
    pairs whose segment crosses one of those geometries' bounding boxes."""
    rows = np.arange(len(nodes), dtype=np.int64) if among is None else np.sort(among)
    count = len(rows)
    # The wedge test's arrays are booleans and two floats a pair: blocks of 8x the pairs.
    step = max(1, (CHUNK if through is None else 8 * CHUNK) // max(count, 1))
    wedges = [_wedges(nodes[rows], geometry.bounds) for geometry in through or ()]
    for first in range(0, count, step):
        block = rows[first : first + step]
        if through is not None:
            # Only the pairs whose far end is in the wedge the box spans from the near end:
            # a few per cent of them, so removing a keep-out checks those, not every pair.
            later = rows[first:]  # (i < j: the columns from the block's first row on)
            seen = np.zeros((len(block), len(later)), dtype=bool)
            dx = nodes[later, 0][None, :] - nodes[block, 0][:, None]
            dy = nodes[later, 1][None, :] - nodes[block, 1][:, None]
            for everywhere, low, high in wedges:
                part = slice(first, first + len(block))
                lx, ly = low[part, 0, None], low[part, 1, None]
                hx, hy = high[part, 0, None], high[part, 1, None]
                seen |= everywhere[part, None] | (
                    (lx * dy - ly * dx >= 0) & (dx * hy - dy * hx >= 0)
                )
            seen &= block[:, None] < later[None, :]
            a, b = np.nonzero(seen)
            i, j = block[a], later[b]
            meets = np.zeros(len(i), dtype=bool)
            for geometry in through:
                meets |= _meets_box(nodes[i], nodes[j], geometry.bounds)
            i, j = i[meets], j[meets]
        else:
            i, j = np.meshgrid(block, rows, indexing="ij")
            keep = i < j
            i, j = i[keep], j[keep]
        if len(i):
            yield i, j


def _wedges(
    points: npt.NDArray[np.float64], box: tuple[float, float, float, float]
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """For each point, the wedge of directions in which it sees the box: its two extreme
    corners (counter-clockwise from ``low`` to ``high``); ``everywhere`` where the point is
    in the box or next to it (every direction)."""
    minx, miny, maxx, maxy = box
    margin = 1e-6
    corners = np.array([[minx, miny], [maxx, miny], [maxx, maxy], [minx, maxy]])
    centre = np.array([(minx + maxx) / 2, (miny + maxy) / 2])
    everywhere = (
        (points[:, 0] >= minx - margin)
        & (points[:, 0] <= maxx + margin)
        & (points[:, 1] >= miny - margin)
        & (points[:, 1] <= maxy + margin)
    )
    v = corners[None, :, :] - points[:, None, :]  # (n, 4, 2)
    r = centre[None, :] - points  # (n, 2)
    angle = np.arctan2(
        r[:, None, 0] * v[..., 1] - r[:, None, 1] * v[..., 0],
        r[:, None, 0] * v[..., 0] + r[:, None, 1] * v[..., 1],
    )
    rows = np.arange(len(points))
    low = v[rows, np.argmin(angle, axis=1)]
    high = v[rows, np.argmax(angle, axis=1)]
    return everywhere, low, high


def _meets_box(
    a: npt.NDArray[np.float64], b: npt.NDArray[np.float64], box: tuple[float, float, float, float]
) -> npt.NDArray[np.bool_]:
    """Which segments a-b meet an axis-aligned box (the slab test)."""
    low = np.zeros(len(a))
    high = np.ones(len(a))
    for axis, (lo, hi) in enumerate(((box[0], box[2]), (box[1], box[3]))):
        start, delta = a[:, axis], b[:, axis] - a[:, axis]
        flat = delta == 0
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo - start) / delta
            t2 = (hi - start) / delta
        inside = (start >= lo) & (start <= hi)
        enter = np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
        leave = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
        low = np.maximum(low, enter)
        high = np.minimum(high, leave)
    result: npt.NDArray[np.bool_] = low <= high
    return result


def _segments(
    nodes: npt.NDArray[np.float64], u: npt.NDArray[np.int64], v: npt.NDArray[np.int64]
) -> npt.NDArray[np.float64]:
    return np.stack([nodes[u], nodes[v]], axis=1)


def _covered(
    space: BaseGeometry,
    a: npt.NDArray[np.float64],
    b: npt.NDArray[np.float64],
    raster: Raster | None = None,
) -> npt.NDArray[np.bool_]:
    """Which segments a-b lie in ``space`` (prepared). Points along each are tested first,
    halving the step each round: a point outside the space blocks the segment for a
    fraction of what testing the whole segment costs (most long segments in a town are
    blocked by something), and only the segments left are tested whole. With the space's
    ``raster`` the points are looked up in it (nanoseconds each), many more of them."""
    alive = np.ones(len(a), dtype=bool)
    if not len(a):
        return alive
    d = b - a
    if raster is not None:
        fractions = np.arange(1, RASTER_SAMPLES + 1) / (RASTER_SAMPLES + 1)
        for first in range(0, len(a), RASTER_BLOCK):
            part = slice(first, first + RASTER_BLOCK)
            xs = a[part, 0, None] + d[part, 0, None] * fractions
            ys = a[part, 1, None] + d[part, 1, None] * fractions
            alive[part] = raster.maybe_inside(xs, ys).all(axis=1)
    else:
        for level in range(1, SAMPLE_ROUNDS + 1):
            for fraction in np.arange(1, 2**level, 2) / 2**level:
                index = np.flatnonzero(alive)
                if not len(index):
                    return alive
                p = a[index] + d[index] * fraction
                alive[index[~shapely.contains_xy(space, p[:, 0], p[:, 1])]] = False
    index = np.flatnonzero(alive)
    if len(index):
        lines = shapely.linestrings(np.stack([a[index], b[index]], axis=1))
        alive[index[~shapely.covers(space, lines)]] = False
    return alive


def _crossing(
    a: npt.NDArray[np.float64], b: npt.NDArray[np.float64], zones: list[BaseGeometry]
) -> npt.NDArray[np.bool_]:
    """Which segments a-b touch one of ``zones``."""
    result = np.zeros(len(a), dtype=bool)
    if not len(a):
        return result
    lines = shapely.linestrings(np.stack([a, b], axis=1))
    for zone in zones:
        result |= shapely.intersects(zone, lines)
    return result


def _node_keys(
    nodes: npt.NDArray[np.float64],
    before: npt.NDArray[np.float64],
    after: npt.NDArray[np.float64],
) -> list[bytes]:
    """A node's identity across rebuilds: its corner and both neighbours, exactly."""
    rows = np.ascontiguousarray(np.hstack([nodes, before, after]))
    return [row.tobytes() for row in rows]


def _corners(
    space: BaseGeometry,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """The free space's reflex corners (where it bends around an obstacle) and their neighbours."""
    polygons: list[Polygon]
    if isinstance(space, Polygon):
        polygons = [space]
    elif isinstance(space, MultiPolygon):
        polygons = list(space.geoms)
    else:
        polygons = [g for g in getattr(space, "geoms", ()) if isinstance(g, Polygon)]
    found: list[tuple[XY, XY, XY]] = []
    for polygon in polygons:
        if polygon.is_empty:
            continue
        polygon = orient(polygon, 1.0)  # free space on the left of every ring
        for ring in (polygon.exterior, *polygon.interiors):
            found.extend(_reflex(ring))
    if not found:
        empty = np.empty((0, 2))
        return empty, empty, empty
    array = np.array(found, dtype=np.float64)
    return array[:, 1, :].copy(), array[:, 0, :].copy(), array[:, 2, :].copy()


def _reflex(ring: LinearRing) -> list[tuple[XY, XY, XY]]:
    coords = list(ring.coords)[:-1]
    found = []
    for index, here in enumerate(coords):
        before, after = coords[index - 1], coords[(index + 1) % len(coords)]
        turn = (here[0] - before[0]) * (after[1] - here[1]) - (here[1] - before[1]) * (
            after[0] - here[0]
        )
        if turn < 0:  # a right turn with the free space on the left: an obstacle's corner
            found.append(((before[0], before[1]), (here[0], here[1]), (after[0], after[1])))
    return found


def _tangent(
    d: npt.NDArray[np.float64], before: npt.NDArray[np.float64], after: npt.NDArray[np.float64]
) -> npt.NDArray[np.bool_]:
    """The line along ``d`` leaves both neighbours of a corner on one side (it grazes it)."""
    s1 = d[:, 0] * before[:, 1] - d[:, 1] * before[:, 0]
    s2 = d[:, 0] * after[:, 1] - d[:, 1] * after[:, 0]
    result: npt.NDArray[np.bool_] = s1 * s2 >= -1e-9
    return result


def _walk(parent: dict[int, int], node: int, points: list[XY]) -> list[XY]:
    path = [points[node]]
    while node in parent:
        node = parent[node]
        path.append(points[node])
    path.reverse()
    return path
