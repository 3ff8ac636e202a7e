"""The patrol's decisions, sans-IO: map, route, override and pose in; a velocity and a state out.

:class:`Patrol` is stepped by its actor ten times a second with the current pose; every
other input (a new map or route, start/stop, the manual override) is a method call. It
plans with :class:`~brasidas.autonomy.planner.Planner`, follows with
:class:`~brasidas.autonomy.follower.PurePursuit` and holds still, saying why, when it cannot
drive safely: no fix or a stale one, the pose outside the boundary or inside a keep-out.

A pose inside one of the map's keep-out zones (a building) is not held on for ever: the
robot cannot have driven through a wall its lidar stops it short of, so either the estimate
slipped (a starved machine dead-reckoning through a turn) or the zone is not a wall. Either
way the way out a user expects is the way it came: the patrol keeps a trail of its recent
positions outside the map's keep-outs and backs along it, slowly (the lidar guards what is
behind), to the last one clear of the zone, then plans again from there. Inside a zone the
lidar drew it first yields (a person about to cross its way), then backs out the same way.
Driving forward without headway (stopped by the lidar short of an obstacle on its path) it
backs a little the way it came, or turns on the spot when boxed in, and plans again.

Shapely (and NumPy under it) is imported only once there is a map: a platform without one
does not pay ~17 MB for them.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

from brasidas.autonomy.follower import FollowerParameters, PurePursuit
from brasidas.autonomy.geo import wrap
from brasidas.autonomy.localization import Estimate
from brasidas.autonomy.route import Cursor, Route, RouteError
from brasidas.messages import PatrolState, PatrolStatus
from brasidas.perception.messages import SEEN_KEEPOUT_PREFIX

if TYPE_CHECKING:
    from brasidas.autonomy.areamap import AreaMap
    from brasidas.autonomy.planner import Path, Planner

XY = tuple[float, float]


@dataclass(frozen=True)
class PatrolParameters:
    follower: FollowerParameters
    clearance_m: float = 4.5
    fix_stale_s: float = 2.0
    """A pose whose last fix is older than this is not trusted: hold."""
    corridor_m: float = 3.0
    """Replan when the robot is further than this from its planned path."""
    align_speed: float = 0.3
    """Normalized forward command while the heading is not known yet (driving straight)."""
    align_room_m: float = 3.0
    """Room needed straight ahead to drive for a heading."""
    trail_step_m: float = 0.5
    """The trail of positions outside the map's keep-outs keeps one every this far ..."""
    trail_length: int = 60
    """... this many (30 m: the way back out of a zone the pose slipped into)."""
    back_out_margin_m: float = 1.0
    """Backing out of a keep-out ends at a trail point at least this far from it."""
    back_out_max_m: float = 15.0
    """Backed out this far and still inside: held (the pose is not to be trusted)."""
    yield_s: float = 5.0
    """Inside a zone the lidar saw this long (not a person about to cross, who passes): it
    backs out the way it came."""
    stuck_s: float = 3.0
    """Driving forward and not :data:`STUCK_MOVE_M` further in this long (the lidar stops it
    short of an obstacle on the path: one seen late, hugged by a way out of its zone's
    clearance) ..."""
    unstick_m: float = 1.5
    """... it backs this far the way it came and plans again."""
    boxed_in_s: float = 60.0
    """Inside a keep-out and boxed in both ways this long (obstacles ahead and behind that do
    not go): the patrol stops, saying so, and the operator decides (not a wait for ever)."""


@dataclass(frozen=True)
class PatrolEvent:
    """Something the operator should hear about: arrived, skipped (unreachable), replanned."""

    kind: str
    waypoint: int
    message: str


@dataclass(frozen=True)
class PlanRequest:
    """A path the patrol waits for, from a planner elsewhere (:meth:`Patrol.set_plan`)."""

    id: int
    revision: int
    """The map revision it is for: an answer for another one is dropped."""
    start: XY
    goal: XY
    waypoint: int = -1
    """The target's index."""
    origin: int = -1
    """A leg asked ahead: the waypoint it starts from (-1: from where the robot was)."""


STUCK_MOVE_M = 0.3
"""Headway: this much further along while driving forward."""
ARRIVED_BACK_M = 0.3
"""Backing to a point ends this near it."""
SPIN_TURN = 0.5
"""Normalized turn on the spot when boxed in."""
BACK_OUT_TURN_RAD = math.radians(45.0)
"""A heading error this large turns at the full rate (backing out)."""
BUILDING = "the map changed: waiting for the new plan (being built)"
SEEN_IN_THE_WAY = "no waypoint can be reached past the obstacles the lidar sees: waiting for them"


@dataclass(frozen=True)
class Command:
    linear: float
    angular: float


STOP = Command(0.0, 0.0)


INSIDE = "inside keep-out zone"


class Patrol:
    def __init__(self, parameters: PatrolParameters) -> None:
        self.p = parameters
        self.area: AreaMap | None = None
        self.map_revision = 0
        """Counts the map's changes (a console redraws the map when it moves)."""
        self.route = Route()
        self.cursor = Cursor()
        self.state = PatrolState.IDLE
        self.reason = ""
        self.enabled = True
        self._running = False
        """The operator wants it to patrol (start), as against stop."""
        self._override = False
        self.pose_hold = ""
        """Why the localization's pose must not be driven on (the platform sets it): the
        reason held for instead of "no GPS fix"."""
        self._unreachable_revision: int | None = None
        """Every waypoint was unreachable past seen obstacles at this map revision: held."""
        self.blocked: tuple[bool, bool] = (False, False)
        """The lidar stops the robot (ahead, behind): set by the platform before each step.
        Finding a lost heading then backs away instead of asking for what it cannot have."""
        self._planner: Planner | None = None
        self._follower = PurePursuit(parameters.follower)
        self._path: Path | None = None
        self._needs_plan = True
        self._distance: float | None = None
        self.events: list[PatrolEvent] = []
        """Drained by the actor."""
        self.remote = False
        """Plans come from elsewhere (a planner process): :attr:`plan_requests` out,
        :meth:`planner_ready` and :meth:`set_plan` in; the patrol holds while it waits."""
        self.plan_requests: list[PlanRequest] = []
        """Drained by the actor (remote planning)."""
        self.stale_plans = 0
        """Answers dropped: for another map revision or a request since given up."""
        self._ready_revision: int | None = None
        self._planner_down = ""
        self._waiting: PlanRequest | None = None
        self._ahead: PlanRequest | None = None
        """The next leg, asked when the current one is planned (from its waypoint to the
        next): at the waypoint the patrol goes on without holding for it."""
        self._ahead_answer: tuple[list[XY] | None, str] | None = None
        self._next_request = 0
        self._skips = 0
        self._completed = False
        """The route's laps are driven (a mission's end): start begins it again."""
        self._trail: deque[XY] = deque(maxlen=parameters.trail_length)
        """Recent positions outside the map's keep-outs (the way back out of one)."""
        self._backing: tuple[XY, float] | None = None
        """Backing out of a keep-out: to this trail point, and how far it has gone so far."""
        self._backed_from: XY | None = None
        self._inside_seen = False
        """The keep-out the pose is in is one the lidar saw (yielded to first)."""
        self._inside_since: float | None = None
        """Since when the pose is inside a zone the lidar saw."""
        self._progress: tuple[XY, float, float] | None = None
        """Driving forward: where and when it last made headway, and the last step's time."""
        self._unsticking: tuple[XY, XY] | None = None
        """Stuck: backing to this point (the trail's) from that one, then planning again."""
        self._spun: tuple[float, float] | None = None
        """Boxed in, turning on the spot: the last yaw and how far it has turned."""
        self._boxed_since: float | None = None
        """Since when it waits inside a keep-out, boxed in both ways."""

    # ------------------------------------------------------------------ inputs

    def set_map(self, area: AreaMap | None, *, build: bool = True) -> None:
        """A new map: the waypoints are wiped and the patrol stops (R-5.3.3.5). Without
        ``build`` the planner comes later (:meth:`set_planner`, built off the event loop)."""
        self.area = area
        self.map_revision += 1
        self._planner = self._build(area) if area is not None and build else None
        self.route = Route()
        self.cursor = Cursor()
        self._running = False
        self._path = None
        self._forget_plans()
        self._trail.clear()  # another map, perhaps another frame
        self._backing = None
        if area is None:  # said at once, not only from the next step
            self._settle(PatrolState.IDLE, "no map")
        else:
            self._settle(PatrolState.STOPPED, "map loaded: waypoints cleared")

    def update_map(self, area: AreaMap, *, build: bool = True) -> None:
        """Keep-out zones changed: same route, a new plan. Without ``build`` the patrol holds
        until :meth:`set_planner` brings the planner for this map."""
        self.area = area
        self.map_revision += 1
        self._planner = self._build(area) if build else None
        self._needs_plan = True
        self._forget_plans()

    def planner_ready(self, revision: int) -> bool:
        """(Remote planning.) The planner has the graph of map ``revision``; False (ignored)
        when the map has changed since."""
        if revision != self.map_revision:
            return False
        self._ready_revision = revision
        self._planner_down = ""
        self._needs_plan = True
        self._forget_plans()
        return True

    def planner_lost(self, reason: str) -> None:
        """(Remote planning.) The planner is gone (``reason``): hold until it is back."""
        self._ready_revision = None
        self._planner_down = reason
        self._forget_plans()

    def plan_not_sent(self, request: PlanRequest) -> None:
        """(Remote planning.) ``request`` could not be sent: asked again at the next step."""
        if self._waiting is request:
            self._waiting = None
        if self._ahead is request:
            self._ahead = None

    @property
    def planner_is_ready(self) -> bool:
        """A plan can be had for the current map (built here, or ready elsewhere)."""
        if self.remote:
            return self._ready_revision == self.map_revision
        return self._planner is not None

    def set_plan(
        self, revision: int, request: int, points: list[XY] | None, unreachable: str = ""
    ) -> bool:
        """(Remote planning.) The answer to request ``request``: a path, or why the waypoint
        cannot be reached (it is skipped). Dropped (False) when it is not the one waited for
        (another map revision, a route or start since)."""
        ahead = self._ahead
        if ahead is not None and (ahead.id, ahead.revision) == (request, revision):
            self._ahead_answer = (points, unreachable)
            return True
        waiting = self._waiting
        if waiting is None or (waiting.id, waiting.revision) != (request, revision):
            self.stale_plans += 1
            return False
        self._waiting = None
        if revision != self.map_revision or waiting.waypoint != self.cursor.index:
            # (cleared on every map change; the target changed without saying so: a guard)
            self.stale_plans += 1
            return False
        if points is None:
            index = self.cursor.index
            self.events.append(
                PatrolEvent("skipped", index, f"{self._label(index)} skipped: {unreachable}")
            )
            self.cursor = self.cursor.advance(self.route)
            self._path = None
            self._skips += 1
            if self._skips >= self.route.stops:
                self._skips = 0
                self._none_reachable()
            return True
        from brasidas.autonomy.planner import Path

        self._skips = 0
        self._use(Path(tuple(points)))
        self._ask_ahead()
        return True

    def _forget_plans(self) -> None:
        """The plans asked (and the next leg's) are of no use any more: their answers are
        dropped."""
        self._waiting = None
        self._ahead = None
        self._ahead_answer = None

    def set_planner(self, area: AreaMap, planner: Planner) -> bool:
        """The planner built for ``area``; ignored (False) when the map has changed since."""
        if area is not self.area:
            return False
        self._planner = planner
        self._needs_plan = True
        return True

    @property
    def planner(self) -> Planner | None:
        """The planner of the current map (None while it is being built)."""
        return self._planner

    def set_route(self, route: Route) -> None:
        """New waypoints, on the fly: the patrol goes on toward the waypoint it was heading for
        when the new route keeps it, else the next kept one of the old route (a loop goes on,
        it does not restart from the first waypoint)."""
        self._unreachable_revision = None  # other waypoints: tried again
        lap = self.cursor.lap
        old = self.route.waypoints[: self.route.stops]
        start = self.cursor.index if self.cursor.index < len(old) else 0
        self.route = route
        self.cursor = Cursor()
        stops = route.waypoints[: route.stops]
        # A mission with an end (laps, a return home) is driven from its first waypoint: going
        # on toward a kept waypoint could be its last, and end it at once.
        for step in range(len(old) if route.laps is None else 0):
            wanted = old[(start + step) % len(old)]
            kept = [i for i, waypoint in enumerate(stops) if waypoint.same_place(wanted)]
            if kept:
                self.cursor = Cursor(kept[0], True, lap, kept[0] != 0)
                break
        self._needs_plan = True
        self._forget_plans()
        self._skips = 0
        self._completed = False
        if not route.waypoints:
            self._path = None
        if not self._running:
            self.reason = "not started" if route.waypoints else "no waypoints"

    def start(self) -> None:
        if self._completed:  # a finished mission starts again from its first waypoint
            self.cursor = Cursor()
            self._completed = False
        self._running = True
        self._needs_plan = True
        self._forget_plans()
        self._skips = 0
        self._unreachable_revision = None

    def stop(self, reason: str = "stopped by the operator") -> None:
        self._running = False
        self._path = None
        self._settle(PatrolState.STOPPED, reason)

    def set_enabled(self, enabled: bool) -> None:
        """The patrol automation switched on or off (R-3): off stops it and refuses start."""
        self.enabled = enabled
        if not enabled:
            self.stop("patrol switched off")

    def set_override(self, engaged: bool) -> None:
        if engaged == self._override:
            return
        self._override = engaged
        if not engaged:
            self._needs_plan = True  # from wherever the operator left the robot
            self._forget_plans()

    # ------------------------------------------------------------------ stepping

    def step(self, estimate: Estimate | None, fix_age: float | None) -> Command:
        """The command for now: ``estimate`` in the map's frame, ``fix_age`` seconds since the
        last GPS fix (None: never)."""
        if not self.enabled:
            return self._settle(PatrolState.STOPPED, "patrol switched off")
        if self.area is None:
            return self._settle(PatrolState.IDLE, "no map")
        if not self._running:
            return self._settle(PatrolState.STOPPED, self.reason or "stopped")
        if not self.route.waypoints:
            return self._settle(PatrolState.IDLE, "no waypoints")
        if self._override:
            return self._settle(PatrolState.SUSPENDED, "manual override engaged")
        if not self.planner_is_ready:
            self._needs_plan = True
            if self._planner_down:
                return self._settle(PatrolState.HOLDING, self._planner_down)
            return self._settle(PatrolState.HOLDING, BUILDING)
        hold = self._hazard(estimate, fix_age)
        if hold.startswith(INSIDE) and estimate is not None:
            if not self._inside_seen:
                return self._back_out(estimate, hold)
            # One the lidar saw: a person about to cross is yielded to; one that stays (a post
            # it came too near, its zone drawn over the robot) is backed out of.
            if self._inside_since is None:
                self._inside_since = estimate.time
            if estimate.time - self._inside_since >= self.p.yield_s:
                return self._back_out(estimate, hold)
        else:
            self._inside_since = None
        self._backing = None
        self._boxed_since = None
        if hold:
            self._needs_plan = True
            self._waiting = None  # replanned from where the robot is when it may go on
            return self._settle(PatrolState.HOLDING, hold)
        assert estimate is not None
        self._remember(estimate)
        if self._unreachable_revision == self.map_revision:
            return self._settle(PatrolState.HOLDING, SEEN_IN_THE_WAY)
        here = (estimate.x, estimate.y)
        if not estimate.heading_known:
            return self._align(here)
        if self._unsticking is not None:
            backing = self._unstick(estimate)
            if backing is not None:
                return backing
        for _ in range(self.route.stops):
            if self._needs_plan or self._path is None:
                if self._planner is None:
                    return self._ask(here)  # remote: ask, and hold until the answer
                if not self._plan(here):
                    continue
            steering = self._follower.step(here[0], here[1], estimate.yaw)
            self._distance = steering.remaining_m
            if steering.arrived:
                index = self.cursor.index
                self.events.append(PatrolEvent("arrived", index, f"reached {self._label(index)}"))
                self.cursor = self.cursor.advance(self.route)
                self._needs_plan = True
                if self._finished(index):
                    # Stays at the last waypoint reached (what MISSION_CURRENT shows).
                    self.cursor = Cursor(index, self.cursor.forward, self.cursor.lap, True)
                    self._running = False
                    self._completed = True
                    self._path = None
                    self.events.append(PatrolEvent("finished", index, "mission complete"))
                    return self._settle(
                        PatrolState.STOPPED, f"mission complete at {self._label(index)}"
                    )
                if self.route.stops == 1:
                    return self._settle(PatrolState.PATROLLING, "at the only waypoint")
                if self._planner is None:
                    self._take_ahead(index)
                continue
            if steering.cross_track_m > self.p.corridor_m:
                self._needs_plan = True
                continue
            self._settle(PatrolState.PATROLLING, "")
            command = Command(steering.linear, steering.angular)
            if self._stuck(estimate, command):
                return self._start_unsticking(estimate)
            return command
        return self._none_reachable()

    def _none_reachable(self) -> Command:
        """Every waypoint skipped: stopped, unless obstacles the lidar saw are in the way,
        which move or go (a person, a parked car): then held until the map changes."""
        area = self.area
        if area is not None and any(k.startswith(SEEN_KEEPOUT_PREFIX) for k in area.keepouts):
            self._unreachable_revision = self.map_revision
            return self._settle(PatrolState.HOLDING, SEEN_IN_THE_WAY)
        self._running = False
        return self._settle(PatrolState.STOPPED, "no waypoint can be reached")

    @property
    def active(self) -> bool:
        return self.state in (PatrolState.PATROLLING, PatrolState.SUSPENDED, PatrolState.HOLDING)

    @property
    def planned_path(self) -> tuple[XY, ...]:
        """The path being followed, in the map's local frame (metres); empty when none."""
        return self._path.points if self._path is not None and self.active else ()

    def status(self) -> PatrolStatus:
        distance = self._distance if self.active else None
        frame = self.area.frame if self.area is not None else None
        return PatrolStatus(
            state=self.state,
            enabled=self.enabled,
            waypoint=self.cursor.index if self.route.waypoints else None,
            distance_m=round(distance, 1) if distance is not None else None,
            lap=self.cursor.lap,
            reason=self.reason,
            waypoints=len(self.route.waypoints),
            path=tuple(frame.to_geo(x, y) for x, y in self.planned_path) if frame else (),
        )

    def go_to(self, index: int) -> None:
        """The next waypoint is ``index`` (a ground station's MISSION_SET_CURRENT): the patrol
        heads there at once, or from there once started; direction and lap go on. Raises
        RouteError for a waypoint the route does not have."""
        stops = self.route.stops
        if not 0 <= index < stops:
            raise RouteError(
                f"no waypoint {index + 1}: the route has {stops}" if stops else "no waypoints"
            )
        cursor = self.cursor
        self.cursor = Cursor(index, cursor.forward, cursor.lap, cursor.departed or index != 0)
        self._needs_plan = True
        self._forget_plans()  # a plan asked for the old target (or the leg after it) is dropped

    # ------------------------------------------------------------------ helpers

    def _build(self, area: AreaMap) -> Planner:
        from brasidas.autonomy.planner import Planner

        return Planner(area.boundary, area.keepouts, self.p.clearance_m)

    def _settle(self, state: PatrolState, reason: str) -> Command:
        self.state, self.reason = state, reason
        return STOP

    def _hazard(self, estimate: Estimate | None, fix_age: float | None) -> str:
        if estimate is None or fix_age is None:
            return self.pose_hold or "no GPS fix"
        if fix_age > self.p.fix_stale_s:
            return f"GPS fix lost or stale ({fix_age:.1f} s old)"
        assert self.area is not None
        if not self.area.inside(estimate.x, estimate.y):
            return "outside the map's boundary"
        zone = self.area.keepout_at(estimate.x, estimate.y)
        if zone is not None:
            self._inside_seen = zone.startswith(SEEN_KEEPOUT_PREFIX)
            return f"{INSIDE} {zone!r}"
        return ""

    def _remember(self, estimate: Estimate) -> None:
        """The trail: where the robot was, outside the map's keep-outs (checked just now)."""
        here = (estimate.x, estimate.y)
        trail = self._trail
        if not trail or math.dist(trail[-1], here) >= self.p.trail_step_m:
            trail.append(here)

    def _back_out(self, estimate: Estimate, inside: str) -> Command:
        """Back along the trail to its last point clear of the keep-out the pose is in."""
        from shapely import Point

        assert self.area is not None
        here = (estimate.x, estimate.y)
        self._needs_plan = True  # from wherever it comes out
        self._waiting = None
        if self._backing is None:
            target = next(
                (
                    point
                    for point in reversed(self._trail)
                    if not self.area.meets_keepout(
                        Point(point).buffer(self.p.back_out_margin_m, quad_segs=4),
                        seen_too=self._inside_seen,
                    )
                ),
                self._trail[-1] if self._trail else None,
            )
            if target is None:
                return self._settle(PatrolState.HOLDING, f"{inside}: no way it came to back out by")
            self._backing = (target, 0.0)
            self._backed_from = here
        target, backed = self._backing
        if self._backed_from is not None:
            backed += math.dist(self._backed_from, here)
        self._backed_from = here
        self._backing = (target, backed)
        if backed > self.p.back_out_max_m:
            return self._settle(
                PatrolState.HOLDING,
                f"{inside}: backed out {backed:.0f} m and still inside (the pose is doubtful)",
            )
        command = self._back_to(estimate, target)
        if command is not None:
            self._boxed_since = None
            self._settle(PatrolState.PATROLLING, f"{inside}: backing out the way it came")
            return command
        if self._inside_seen:
            # A zone the lidar drew over a post it came too near, the way it came blocked (by
            # that post, when it turned towards it): waiting would be for ever.
            command = self._leave_seen(estimate)
            if command is not None:
                self._boxed_since = None
                self._settle(PatrolState.PATROLLING, f"{inside}: leaving it the nearest way")
                return command
        if self._boxed_since is None:
            self._boxed_since = estimate.time
        waited = estimate.time - self._boxed_since
        if waited >= self.p.boxed_in_s:
            self._boxed_since = None
            self.stop(
                f"{inside}: boxed in for {waited:.0f} s (obstacles ahead and behind): "
                "patrol stopped, the operator decides"
            )
            return STOP
        return self._settle(
            PatrolState.HOLDING, f"{inside}: an obstacle in the way it came (waiting)"
        )

    def _leave_seen(self, estimate: Estimate) -> Command | None:
        """Out of the lidar's zone the robot is in, the shortest way: towards the zone's
        nearest edge, or else straight the way the lidar leaves free if it leads away from
        the zone's middle; None when neither can be driven (something that moves will)."""
        from shapely import Point
        from shapely.ops import nearest_points

        assert self.area is not None
        zone_id = self.area.keepout_at(estimate.x, estimate.y)
        if zone_id is None:
            return None
        zone = self.area.keepouts[zone_id]
        here = Point(estimate.x, estimate.y)
        middle = zone.centroid
        edge = nearest_points(zone.boundary, here)[0]
        dx, dy = edge.x - here.x, edge.y - here.y
        length = math.hypot(dx, dy)
        if length < 1e-6:  # on the edge: straight away from the middle
            dx, dy = here.x - middle.x, here.y - middle.y
            length = math.hypot(dx, dy) or 1.0
        reach = length + self.p.back_out_margin_m
        command = self._back_to(
            estimate, (here.x + dx / length * reach, here.y + dy / length * reach)
        )
        if command is not None:
            return command
        ahead, behind = self.blocked
        # > 0: driving forward leads away from the zone's middle, < 0: reversing does.
        outward = (here.x - middle.x) * math.cos(estimate.yaw) + (here.y - middle.y) * math.sin(
            estimate.yaw
        )
        if outward > 0 and not ahead:
            return Command(self.p.align_speed, 0.0)
        if outward < 0 and not behind:
            return Command(-self.p.align_speed, 0.0)
        return None

    def _back_to(self, estimate: Estimate, target: XY) -> Command | None:
        """Slowly to ``target``, reversing when it is behind (the way it came); None when the
        lidar stops that way."""
        ahead, behind = self.blocked
        bearing = math.atan2(target[1] - estimate.y, target[0] - estimate.x)
        error = wrap(bearing - estimate.yaw)
        forward = abs(error) < math.pi / 2  # the point is ahead (backed past it): drive to it
        if not forward:
            error = wrap(error - math.pi)  # the rear's heading error, reversing
        if (behind and not forward) or (ahead and forward):
            return None
        turn = max(-1.0, min(1.0, error / BACK_OUT_TURN_RAD))
        speed = self.p.align_speed * max(0.0, math.cos(error))
        return Command(speed if forward else -speed, turn)

    def _stuck(self, estimate: Estimate, command: Command) -> bool:
        """Driving forward without headway for :attr:`PatrolParameters.stuck_s`."""
        here, now = (estimate.x, estimate.y), estimate.time
        progress = self._progress
        area = self.area
        planned_around = area is not None and any(
            k.startswith(SEEN_KEEPOUT_PREFIX) for k in area.keepouts
        )  # what stops it is in the plan (without, a new plan would lead it back the same way)
        if command.linear <= 0.05 or not planned_around:
            self._progress = None
            return False
        if (
            progress is None
            or now - progress[2] > 1.0  # not driving since (held, turned on the spot)
            or math.dist(progress[0], here) > STUCK_MOVE_M
        ):
            self._progress = (here, now, now)
            return False
        self._progress = (progress[0], progress[1], now)
        return now - progress[1] >= self.p.stuck_s

    def _start_unsticking(self, estimate: Estimate) -> Command:
        """Back the way it came (the trail; straight back without one) for a fresh plan."""
        here = (estimate.x, estimate.y)
        self._progress = None
        target = next(
            (
                point
                for point in reversed(self._trail)
                if math.dist(point, here) >= self.p.unstick_m
            ),
            (
                here[0] - self.p.unstick_m * math.cos(estimate.yaw),
                here[1] - self.p.unstick_m * math.sin(estimate.yaw),
            ),
        )
        self._unsticking = (target, here)
        self.events.append(
            PatrolEvent("stuck", self.cursor.index, "no headway: backing away to plan again")
        )
        command = self._unstick(estimate)
        return command if command is not None else STOP

    def _unstick(self, estimate: Estimate) -> Command | None:
        """Backing away while stuck; None when done (or the way back is blocked too): the
        patrol plans again from here."""
        assert self._unsticking is not None
        target, start = self._unsticking
        here = (estimate.x, estimate.y)
        command = None
        if math.dist(here, start) < self.p.unstick_m and math.dist(here, target) > ARRIVED_BACK_M:
            command = self._back_to(estimate, target)
            if command is None and self.blocked == (True, True):
                return self._spin(estimate)
        if command is None:
            self._unsticking = None
            self._spun = None
            self._needs_plan = True
            return None
        self._settle(PatrolState.PATROLLING, "no headway: backing away to plan again")
        return command

    def _spin(self, estimate: Estimate) -> Command | None:
        """Boxed in (an obstacle beside it is in the way both ahead and behind): turn on the
        spot, which is never limited, until the way ahead is clear, at most half a turn."""
        if self._spun is None:
            self._spun = (estimate.yaw, 0.0)
        last, turned = self._spun
        turned += abs(wrap(estimate.yaw - last))
        self._spun = (estimate.yaw, turned)
        if turned >= math.pi:
            self._unsticking = None
            self._spun = None
            self._needs_plan = True
            return None
        self._settle(PatrolState.PATROLLING, "no headway, boxed in: turning on the spot")
        return Command(0.0, SPIN_TURN)

    def _align(self, here: XY) -> Command:
        """Drive straight ahead for a course over ground (the heading is unknown at start)."""
        from shapely import Point

        assert self.area is not None
        # The heading is unknown, so "ahead" is unknown: need room all round. Obstacles the
        # lidar saw do not count: it stops the robot short of them (a robot that lost its
        # heading standing at a lidar stop is among them).
        room = Point(here).buffer(self.p.align_room_m, quad_segs=4)
        blocked = not self.area.boundary.contains(room) or self.area.meets_keepout(
            room, seen_too=False
        )
        if blocked:
            return self._settle(
                PatrolState.HOLDING,
                f"heading unknown and no {self.p.align_room_m:g} m of room to drive for one",
            )
        ahead, behind = self.blocked
        if ahead and behind:
            return self._settle(
                PatrolState.HOLDING, "heading unknown and obstacles ahead and behind"
            )
        if ahead:  # a course over ground reversing gives the heading as well
            self._settle(PatrolState.PATROLLING, "finding the heading (backing away)")
            return Command(-self.p.align_speed, 0.0)
        self._settle(PatrolState.PATROLLING, "finding the heading (driving straight)")
        return Command(self.p.align_speed, 0.0)

    def _plan(self, here: XY) -> bool:
        """Plan to the current target; an unreachable one is skipped (False)."""
        from brasidas.autonomy.planner import Unreachable

        assert self.area is not None and self._planner is not None
        index = self.cursor.index
        waypoint = self.route.waypoints[index]
        goal = self.area.local(waypoint.latitude, waypoint.longitude)
        try:
            path = self._planner.plan(here, goal)
        except Unreachable as exc:
            self.events.append(
                PatrolEvent("skipped", index, f"{self._label(index)} skipped: {exc}")
            )
            self.cursor = self.cursor.advance(self.route)
            self._path = None
            return False
        self._use(path)
        return True

    def _finished(self, arrived: int) -> bool:
        """The route's laps are done on arriving at waypoint ``arrived`` (cursor advanced)."""
        laps = self.route.laps
        if laps is None:
            return False
        if self.route.closed:
            return self.cursor.lap >= laps
        return arrived == self.route.stops - 1

    def _use(self, path: Path) -> None:
        self._path = path
        self._follower.set_path(path.points)
        self._follower.set_speed(self.route.waypoints[self.cursor.index].speed)
        self._needs_plan = False
        self._distance = path.length

    def _take_ahead(self, arrived: int) -> bool:
        """(Remote planning.) At waypoint ``arrived``: the leg asked ahead from it to the new
        target, answered with a path, is followed now (True); asked and not answered yet, it
        is waited for (not asked again)."""
        ahead, answer = self._ahead, self._ahead_answer
        self._ahead = self._ahead_answer = None
        if (
            ahead is None
            or (ahead.origin, ahead.waypoint) != (arrived, self.cursor.index)
            or self._waiting is not None
        ):
            return False
        if answer is None:  # on its way: the patrol holds for it instead of asking again
            self._waiting = ahead
            return False
        points, _ = answer
        if points is None:  # unreachable from the waypoint: asked again from here
            return False
        from brasidas.autonomy.planner import Path

        self._use(Path(tuple(points)))
        self._ask_ahead()
        return True

    def _ask_ahead(self) -> None:
        """(Remote planning.) Ask for the leg after the current target's, from its waypoint."""
        if self.area is None or self.route.stops <= 1:
            return
        here = self.route.waypoints[self.cursor.index]
        after = self.cursor.advance(self.route).index
        there = self.route.waypoints[after]
        self._next_request += 1
        self._ahead = PlanRequest(
            self._next_request,
            self.map_revision,
            self.area.local(here.latitude, here.longitude),
            self.area.local(there.latitude, there.longitude),
            after,
            self.cursor.index,
        )
        self._ahead_answer = None
        self.plan_requests.append(self._ahead)

    def _ask(self, here: XY) -> Command:
        """(Remote planning.) Ask for a path to the current target, once; hold meanwhile."""
        assert self.area is not None
        index = self.cursor.index
        if self._waiting is not None and self._waiting.waypoint != index:
            self._waiting = None  # another target since it was asked: its answer is dropped
        if self._waiting is None:
            waypoint = self.route.waypoints[index]
            goal = self.area.local(waypoint.latitude, waypoint.longitude)
            self._next_request += 1
            self._waiting = PlanRequest(self._next_request, self.map_revision, here, goal, index)
            self.plan_requests.append(self._waiting)
        return self._settle(PatrolState.HOLDING, f"planning the path to {self._label(index)}")

    def _label(self, index: int) -> str:
        return self.route.waypoints[index].label(index)
