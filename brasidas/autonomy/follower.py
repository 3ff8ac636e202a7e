"""Pure pursuit (R-5.3.3.2): a path and a pose in, a normalized (linear, angular) command out.

The robot steers along the arc to the point one look-ahead distance down the path; it turns
on the spot when that point is far to a side (a skid-steer can), slows for tight arcs so the
turn rate stays under its limit, slows again near the goal, and stops within the arrival
tolerance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from brasidas.autonomy.geo import wrap

XY = tuple[float, float]

TURN_IN_PLACE = math.radians(60.0)
"""A look-ahead point further off the nose than this is turned to on the spot."""
MIN_SPEED = 0.15
"""m/s: slower than this the controller's dead band stops the robot short of the goal."""


@dataclass(frozen=True)
class FollowerParameters:
    cruise_speed: float
    """m/s."""
    max_turn_rate: float
    """rad/s."""
    full_speed: float
    """m/s at linear = 1 (the platform's top speed)."""
    full_turn_rate: float
    """rad/s at angular = 1."""
    lookahead_m: float = 2.0
    tolerance_m: float = 0.5
    decel: float = 0.5
    """m/s²: how hard it slows towards the goal."""


@dataclass(frozen=True)
class Steering:
    linear: float
    """Normalized forward command, [-1, 1]."""
    angular: float
    """Normalized turn command, [-1, 1] (positive turns left)."""
    arrived: bool
    cross_track_m: float
    """Distance from the path."""
    remaining_m: float
    """Along the path to the goal."""


class PurePursuit:
    def __init__(self, parameters: FollowerParameters) -> None:
        self.p = parameters
        self._path: tuple[XY, ...] = ()
        self._segment = 0
        self.cruise_speed = parameters.cruise_speed
        """m/s on this leg: the cruise speed, or a mission's DO_CHANGE_SPEED for it."""

    def set_speed(self, speed: float | None) -> None:
        """The leg's speed (None: the cruise speed), never above the platform's top speed."""
        wanted = self.p.cruise_speed if speed is None else speed
        self.cruise_speed = max(MIN_SPEED, min(wanted, self.p.full_speed))

    @property
    def path(self) -> tuple[XY, ...]:
        return self._path

    def set_path(self, path: Sequence[XY]) -> None:
        self._path = tuple(path)
        self._segment = 0

    def step(self, x: float, y: float, yaw: float) -> Steering:
        """The command for the pose (x, y, yaw): yaw counter-clockwise from east."""
        if not self._path:
            return Steering(0.0, 0.0, True, 0.0, 0.0)
        goal = self._path[-1]
        if len(self._path) == 1:
            cross, remaining = 0.0, math.dist((x, y), goal)
        else:
            cross, remaining = self._progress((x, y))
        to_goal = math.dist((x, y), goal)
        bearing = wrap(math.atan2(goal[1] - y, goal[0] - x) - yaw)
        # Within the tolerance, or within twice it with the goal abeam or behind: turning on
        # the spot for the last few decimetres would be a dance, not a patrol.
        if to_goal <= self.p.tolerance_m or (
            to_goal <= 2.0 * self.p.tolerance_m and abs(bearing) > TURN_IN_PLACE
        ):
            return Steering(0.0, 0.0, True, cross, remaining)
        target = self._lookahead((x, y))
        dx, dy = target[0] - x, target[1] - y
        distance = math.hypot(dx, dy)
        alpha = wrap(math.atan2(dy, dx) - yaw)
        if abs(alpha) > TURN_IN_PLACE:
            turn = math.copysign(self.p.max_turn_rate, alpha)
            return self._command(0.0, turn, cross, remaining)
        curvature = 2.0 * math.sin(alpha) / max(distance, 1e-6)
        speed = self.cruise_speed
        if abs(curvature) > 1e-9:
            speed = min(speed, self.p.max_turn_rate / abs(curvature))
        speed = min(speed, math.sqrt(2.0 * self.p.decel * remaining))
        speed = max(speed, MIN_SPEED)
        return self._command(speed, curvature * speed, cross, remaining)

    def _command(self, speed: float, turn: float, cross: float, remaining: float) -> Steering:
        turn = max(-self.p.max_turn_rate, min(self.p.max_turn_rate, turn))
        linear = max(-1.0, min(1.0, speed / self.p.full_speed))
        angular = max(-1.0, min(1.0, turn / self.p.full_turn_rate))
        return Steering(linear, angular, False, cross, remaining)

    def _progress(self, point: XY) -> tuple[float, float]:
        """Advance to the nearest segment (never backwards); (cross-track, remaining length)."""
        best, best_distance = self._segment, math.inf
        for index in range(self._segment, len(self._path) - 1):
            distance, _ = _to_segment(point, self._path[index], self._path[index + 1])
            if distance < best_distance - 1e-9:
                best, best_distance = index, distance
        self._segment = best
        _, t = _to_segment(point, self._path[best], self._path[best + 1])
        a, b = self._path[best], self._path[best + 1]
        remaining = (1.0 - t) * math.dist(a, b) + sum(
            math.dist(p, q)
            for p, q in zip(self._path[best + 1 :], self._path[best + 2 :], strict=False)
        )
        return best_distance, remaining

    def _lookahead(self, point: XY) -> XY:
        """The first point of the path one look-ahead away, from the current segment on."""
        radius = self.p.lookahead_m
        for index in range(self._segment, len(self._path) - 1):
            a, b = self._path[index], self._path[index + 1]
            hit = _leave_circle(point, radius, a, b)
            if hit is not None:
                return hit
        return self._path[-1]


def _to_segment(point: XY, a: XY, b: XY) -> tuple[float, float]:
    """Distance from a point to segment ab, and where along it the nearest point is (0..1)."""
    ax, ay = b[0] - a[0], b[1] - a[1]
    length2 = ax * ax + ay * ay
    if length2 <= 0.0:
        return math.dist(point, a), 0.0
    t = ((point[0] - a[0]) * ax + (point[1] - a[1]) * ay) / length2
    t = max(0.0, min(1.0, t))
    return math.dist(point, (a[0] + t * ax, a[1] + t * ay)), t


def _leave_circle(centre: XY, radius: float, a: XY, b: XY) -> XY | None:
    """Where segment ab leaves the circle (the far intersection), if it does."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    fx, fy = a[0] - centre[0], a[1] - centre[1]
    qa = dx * dx + dy * dy
    if qa <= 0.0:
        return None
    qb = 2.0 * (fx * dx + fy * dy)
    qc = fx * fx + fy * fy - radius * radius
    disc = qb * qb - 4.0 * qa * qc
    if disc < 0.0:
        return None
    t = (-qb + math.sqrt(disc)) / (2.0 * qa)
    if 0.0 <= t <= 1.0:
        return (a[0] + t * dx, a[1] + t * dy)
    return None
