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

import heapq
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import shapely
from shapely import LinearRing, MultiPolygon, Point, Polygon, unary_union
from shapely.geometry.base import BaseGeometry
from shapely.geometry.polygon import orient

CHECK_MARGIN = 0.98
"""Visibility is checked against obstacles inflated by this fraction of the clearance."""
MITRE_LIMIT = 2.0

XY = tuple[float, float]


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
    """The visibility graph of one map at one clearance; :meth:`plan` is cheap, building is not."""

    def __init__(self, boundary: Polygon, keepouts: Iterable[Polygon], clearance: float) -> None:
        if clearance < 0:
            raise ValueError("clearance must be >= 0")
        zones = list(keepouts)
        self.clearance = clearance
        self._escape = _prepared(boundary.difference(unary_union(zones)) if zones else boundary)
        self._free = _prepared(_free_space(boundary, zones, clearance * CHECK_MARGIN))
        self._blocked_by = [(_inflate(zone, clearance * CHECK_MARGIN), zone) for zone in zones]
        nodes, before, after = _corners(_free_space(boundary, zones, clearance))
        self.nodes: npt.NDArray[np.float64] = nodes
        self._before = before
        self._after = after
        self._edges = self._visibility()

    @property
    def edge_count(self) -> int:
        return sum(len(edges) for edges in self._edges) // 2

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
        points = [*map(tuple, self.nodes.tolist()), start, goal]
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
        for inflated, zone in self._blocked_by:
            if inflated.covers(point):
                raise Unreachable(
                    f"it is {zone.exterior.distance(point):.1f} m from a keep-out zone "
                    f"(clearance {self.clearance:g} m)"
                )
        raise Unreachable(f"it is closer than {self.clearance:g} m to the boundary")

    def _seen_from(self, point: XY, space: BaseGeometry) -> set[int]:
        if not len(self.nodes):
            return set()
        segments = np.empty((len(self.nodes), 2, 2))
        segments[:, 0, :] = point
        segments[:, 1, :] = self.nodes
        visible = shapely.covers(space, shapely.linestrings(segments))
        return set(np.flatnonzero(visible).tolist())

    def _visibility(self) -> list[list[tuple[int, float]]]:
        n = len(self.nodes)
        edges: list[list[tuple[int, float]]] = [[] for _ in range(n)]
        if n < 2:
            return edges
        i, j = np.triu_indices(n, k=1)
        a, b = self.nodes[i], self.nodes[j]
        d = b - a
        keep = _tangent(d, self._before[i] - a, self._after[i] - a) & _tangent(
            d, self._before[j] - b, self._after[j] - b
        )
        i, j = i[keep], j[keep]
        segments = np.stack([self.nodes[i], self.nodes[j]], axis=1)
        visible = shapely.covers(self._free, shapely.linestrings(segments))
        i, j = i[visible], j[visible]
        lengths = np.hypot(*(self.nodes[j] - self.nodes[i]).T)
        for u, v, length in zip(i.tolist(), j.tolist(), lengths.tolist(), strict=True):
            edges[u].append((v, length))
            edges[v].append((u, length))
        return edges


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


def _free_space(boundary: Polygon, zones: list[Polygon], margin: float) -> BaseGeometry:
    space: BaseGeometry = _inflate(boundary, -margin) if margin > 0 else boundary
    if zones:
        space = space.difference(unary_union([_inflate(zone, margin) for zone in zones]))
    return space


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
