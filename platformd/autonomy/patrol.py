"""The patrol actor: the route on the area map, driven from ``POSE`` to ``CMD_VEL`` (R-5, R-12).

Ten times a second (``autonomy.rate_hz``) it steps :class:`~brasidas.autonomy.patrol.Patrol`
with the latest pose and, while patrolling, publishes the command on ``CMD_VEL`` (one zero
when it stops). The manual override suspends it inside the ``OVERRIDE_STATE`` delivery (the
arbiter stops obeying ``CMD_VEL`` in the same delivery); releasing it replans from where the
operator left the robot. Nothing here needs a station (R-0.4).

Plans come from the planner process (:mod:`platformd.autonomy.planner_client`), which holds
the map's graph: the patrol asks and holds, saying why, until the answer; NumPy and Shapely
building a graph there never hold this process's GIL.

The map and the route are files on the platform (``map.file``, ``autonomy.route_file``),
replaced atomically; they survive a restart. Shapely and NumPy (~17 MB) are imported when a
map is, never on a platform without one.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import secrets
import time
from collections import deque
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import orjson

from brasidas import topics
from brasidas.actor import Actor
from brasidas.autonomy.localization import Estimate
from brasidas.autonomy.patrol import STOP, Patrol, PatrolParameters
from brasidas.autonomy.route import (
    Route,
    RouteError,
    RouteStore,
    Waypoint,
    check_route,
    parse_waypoints,
    remove_stale_temporaries,
    write_atomically,
)
from brasidas.bus import Bus
from brasidas.codecs.commands import PATROL, PayloadError, parse_switch
from brasidas.messages import (
    CommandResult,
    OverrideState,
    PatrolState,
    PatrolStatus,
    PoseEstimate,
    Velocity,
)
from brasidas.perception.messages import PoseHold
from platformd.automation import report_switch
from platformd.autonomy.planner_client import PlannerProcess
from platformd.commands import CommandRouter, SystemCommand

if TYPE_CHECKING:
    from brasidas.autonomy.areamap import AreaMap

ROOM_FRACTION = 0.25
"""A map whose boundary, shrunk by the clearance, keeps less than this of its area is said
to leave no room (at load, in the answer's notes)."""
PLAN_TIMES_KEPT = 1000
"""Plans whose times are kept (for the benchmark and diagnostics)."""

_LOGGER = logging.getLogger(__name__)


@dataclass(frozen=True)
class Storage:
    map_file: Path
    route_file: Path


class PatrolActor(Actor):
    name = "patrol"

    def __init__(
        self,
        bus: Bus,
        parameters: PatrolParameters,
        storage: Storage,
        *,
        rate_hz: float,
        enabled: bool = True,
        autostart: bool = True,
        demo: tuple[Mapping[str, Any], list[str]] | None = None,
        commands: CommandRouter | None = None,
        clock: Callable[[], float] | None = None,
    ) -> None:
        super().__init__(bus)
        self.commands = commands
        self.core = Patrol(parameters)
        self.core.remote = True
        self.core.enabled = enabled
        self.storage = storage
        self.routes = RouteStore(storage.route_file)
        self.detour: str | None = None
        """Driving to one point (``go_to_point``'s label), the route kept aside; None: the
        route is the patrol's own."""
        self._kept_route = Route()
        self.period = 1.0 / rate_hz
        self.autostart = autostart
        self.demo = demo
        self._clock = clock
        self._pose: PoseEstimate | None = None
        self._driving = False
        self._reported: PatrolStatus | None = None
        self.loaded = False
        self.resumable = False
        """A route (stored, or the --sim demo's) on an enabled patrol: what autostart resumes
        after an operator's start (platformd.arming)."""
        self.start_check: Callable[[], str | None] | None = None
        """Before any start (platformd.arming): the refusal (pre-arm), or None (armed)."""
        self.on_stop: Callable[[], None] | None = None
        """After an operator's stop (platformd.arming keeps it as the last word)."""
        self.settle: Callable[[], Awaitable[None]] | None = None
        """Awaits the last word's write (platformd.arming): a stop is answered once kept."""
        self.map_error = ""
        """Why the stored map was refused at start ("" when it was not): in telemetry."""
        self.last_build_s: float | None = None
        """How long the last planner took to build (in the planner process), seconds."""
        self._changing = asyncio.Lock()
        """One map change at a time: each starts from the map the one before left."""
        self.plan_times: deque[tuple[float, float]] = deque(maxlen=PLAN_TIMES_KEPT)
        """The last plans' (round trip, time in the planner process), seconds."""
        self._asked: dict[int, float] = {}
        """Plans asked and not yet answered: when (perf_counter)."""
        self.planner = PlannerProcess(self._on_planner_answer, self._on_planner_lost)
        """The process that holds the map's graph and answers plans (started with the actor:
        NumPy and Shapely there never hold the event loop's GIL)."""

    # ------------------------------------------------------------------ lifecycle

    async def run(self) -> None:
        if self._clock is None:
            self._clock = asyncio.get_running_loop().time
        if not self.loaded:
            await self.load()
        if self.commands is not None:
            self.on_remove(self.commands.register(self.name, {PATROL: self._command_switch}))
        self.subscribe(topics.POSE, self._on_pose)
        self.subscribe(topics.POSE_HOLD, self._on_pose_hold)
        self.subscribe(topics.OVERRIDE_STATE, self._on_override)
        try:
            async with asyncio.TaskGroup() as group:
                group.create_task(self.planner.run(), name="patrol:planner")
                while True:
                    self.tick()
                    await asyncio.sleep(self.period)
        finally:
            if self._driving:
                self.bus.publish(topics.CMD_VEL, Velocity(0.0, 0.0))
                self._driving = False

    async def load(self) -> None:
        """The stored map and route (the --sim demo when none is stored); start if configured.
        Files and geometry in a worker thread."""
        self.loaded = True
        area, text, route, stored, refused = await asyncio.to_thread(self._stored)
        self.map_error = refused
        self.core.set_map(area, build=False)
        self._replan(text)
        if area is not None:
            self.core.set_route(route)
        report_switch(self.bus, "patrol", self.core.enabled)
        self.resumable = bool(route.waypoints and self.core.enabled)
        if self.resumable and stored and self.autostart:
            self.core.start()
            _LOGGER.info(
                "patrol: %d waypoints on %r, starting", len(route.waypoints), area and area.name
            )
        self._report()

    def _stored(self) -> tuple[AreaMap | None, bytes, Route, bool, str]:
        """(Worker thread.) The stored map, its GeoJSON for the planner, its route, whether
        the route was stored, and why the stored map was refused ("" when it was not); stale
        temporary files removed."""
        refused = ""
        for path in (self.storage.map_file, self.routes.path):
            for removed in remove_stale_temporaries(path):
                _LOGGER.info("patrol: removed %s (left by a crash during a write)", removed)
        area: AreaMap | None = None
        try:
            stored = self.storage.map_file.read_bytes()
        except FileNotFoundError:
            stored = None
        except OSError as exc:
            stored = None
            refused = f"cannot read {self.storage.map_file}: {exc}"
        if stored is not None:
            from brasidas.autonomy.areamap import MapError

            try:
                area = parse_map(stored)
                area.keepout_index()
            except MapError as exc:
                refused = f"{self.storage.map_file} refused: {exc}"
        if refused:
            # Not only in the log: telemetry's autonomy.map_error, a warning at the station.
            _LOGGER.error("patrol: map.file %s", refused)
        try:
            route = Route()
            map_id = self.routes.map_id()
            if area is not None and map_id is not None and map_id != area.load_id:
                # The map was replaced and the crash came before its empty route was stored.
                _LOGGER.warning(
                    "patrol: route %s was set on another map: dropped", self.routes.path
                )
            else:
                route = self.routes.load()
                check_route(route, area)
        except RouteError as exc:
            _LOGGER.error("patrol: route %s refused: %s", self.routes.path, exc)
            route = Route()
        if area is None and self.demo is not None:
            area = parse_map(self.demo[0])
            _LOGGER.info("patrol: no stored map, the --sim demo map %r", area.name)
            if not route.waypoints:
                demo_route = parse_waypoints(self.demo[1], area.points)
                return area, _map_bytes(area), demo_route, False, refused
        if area is not None:
            for note in area.notes:
                _LOGGER.warning("patrol: map %r: %s", area.name, note)
        text = _map_bytes(area) if area is not None else b""
        return area, text, route, bool(route.waypoints), f"map.file {refused}" if refused else ""

    def _replan(self, geojson: bytes, changes: bytes | None = None) -> None:
        """The map changed: its graph is built in the planner process (the patrol holds
        until it is ready); a build for an older map there is stopped. With ``changes`` (the
        keep-outs added and removed, as JSON) only those are sent."""
        if self.core.area is None:
            return
        revision, clearance = self.core.map_revision, self.core.p.clearance_m
        if changes is None:
            self.planner.set_map(revision, geojson, clearance)
        else:
            self.planner.edit_map(revision, revision - 1, changes, geojson, clearance)

    @property
    def planner_ready(self) -> bool:
        """The planner process has the graph of the current map."""
        return self.core.planner_is_ready

    def _on_planner_answer(self, answer: dict[str, Any]) -> None:
        op, revision = answer.get("op"), answer.get("revision")
        if not isinstance(revision, int):
            return
        if op == "ready":
            build_s = float(answer.get("build_s", 0.0))
            if self.core.planner_ready(revision):
                self.last_build_s = build_s
                _LOGGER.info(
                    "patrol: planner for map revision %d ready in %.2f s (%s nodes, %s edges%s)",
                    revision, build_s, answer.get("nodes"), answer.get("edges"),
                    ", changed" if answer.get("incremental") else "",
                )  # fmt: skip
                self.tick()
        elif op == "dropped":
            _LOGGER.info("patrol: planner for map revision %d dropped: a new map came", revision)
        elif op == "failed":
            _LOGGER.error("patrol: planner for map revision %d failed: %s", revision, answer)
            self.planner.resend(revision)
        elif op == "resend":
            self.planner.resend(revision)
        elif op in ("path", "unreachable", "stale"):
            request = answer.get("id")
            points = answer.get("points") if op == "path" else None
            path = [(float(x), float(y)) for x, y in points] if isinstance(points, list) else None
            if not isinstance(request, int) or (op == "path" and path is None):
                return
            asked = self._asked.pop(request, None)
            if asked is not None:
                spent = answer.get("plan_s")
                inside = float(spent) if isinstance(spent, int | float) else 0.0
                self.plan_times.append((time.perf_counter() - asked, inside))
            reason = str(answer.get("reason", "")) if op == "unreachable" else ""
            if op == "stale" or not self.core.set_plan(revision, request, path, reason):
                _LOGGER.debug("patrol: plan %s for map revision %d dropped", request, revision)
                return
            self.tick()

    def _on_planner_lost(self, reason: str) -> None:
        self.core.planner_lost(f"{reason}: waiting for it to start again")
        self.tick()

    # ------------------------------------------------------------------ stepping

    def tick(self) -> None:
        """Step the patrol with the latest pose and publish the command while it drives."""
        estimate, fix_age = self._estimate()
        limits = self.bus.last(topics.PROXIMITY)
        self.core.blocked = (
            (limits.forward_limit == 0.0, limits.reverse_limit == 0.0) if limits else (False, False)
        )
        command = self.core.step(estimate, fix_age)
        if self.core.state is PatrolState.PATROLLING:
            self.bus.publish(topics.CMD_VEL, Velocity(command.linear, command.angular))
            self._driving = command != STOP or self._driving
        elif self._driving:
            self.bus.publish(topics.CMD_VEL, Velocity(0.0, 0.0))
            self._driving = False
        for event in self.core.events:
            log = _LOGGER.warning if event.kind == "skipped" else _LOGGER.info
            log("patrol: %s", event.message)
        self.core.events.clear()
        for request in self.core.plan_requests:
            if not self.planner.request_plan(
                request.revision, request.id, request.start, request.goal
            ):  # no process right now: the patrol holds and asks again at its next step
                self.core.plan_not_sent(request)
            else:
                if len(self._asked) >= PLAN_TIMES_KEPT:  # answers lost with a dead process
                    self._asked.clear()
                self._asked[request.id] = time.perf_counter()
        self.core.plan_requests.clear()
        self._report()

    def _estimate(self) -> tuple[Estimate | None, float | None]:
        pose, area = self._pose, self.core.area
        if self.core.pose_hold:  # the last pose was in a place no longer trusted
            return None, None
        if pose is None or area is None or pose.fix_age_s is None:
            return None, None
        assert self._clock is not None
        now = self._clock()
        x, y = area.local(pose.latitude, pose.longitude)
        estimate = Estimate(
            time=pose.time,
            x=x,
            y=y,
            yaw=pose.yaw_rad,
            speed=pose.speed_mps,
            sigma_xy=pose.sigma_xy_m,
            sigma_yaw=math.radians(pose.sigma_heading_deg),
        )
        return estimate, pose.fix_age_s + max(0.0, now - pose.time)

    def _on_pose(self, pose: PoseEstimate) -> None:
        self._pose = pose

    def _on_pose_hold(self, hold: PoseHold) -> None:
        self.core.pose_hold = hold.reason

    def _on_override(self, state: OverrideState) -> None:
        self.core.set_override(state.engaged)
        self.tick()  # suspended (or resumed) now, not at the next period

    def _report(self) -> PatrolStatus:
        report = self.core.status()
        # distance_m changes every tick: publish on state changes and at most ~1 Hz otherwise.
        last = self._reported
        if last is None or _differs(last, report):
            self._reported = report
            self.bus.publish(topics.PATROL_STATUS, report)
        return report

    @property
    def report(self) -> PatrolStatus:
        return self._report()

    # ------------------------------------------------------------------ operator requests

    def robot_position(self) -> tuple[float, float] | None:
        pose = self._pose
        return (pose.latitude, pose.longitude) if pose is not None else None

    async def load_map(self, source: str | bytes | Mapping[str, Any]) -> AreaMap:
        """Replace the map (validated first): wipes the waypoints and stops (R-5.3.3.5).
        Parsing, checks and files in a worker thread; the planner is built after."""
        async with self._changing:
            position = self.robot_position()
            area, text = await asyncio.to_thread(self._new_map, source, position)
            self.core.set_map(area, build=False)
            self.map_error = ""
            self._replan(text)
        _LOGGER.warning("patrol: map %r loaded; waypoints cleared, patrol stopped", area.name)
        self.tick()
        return area

    def _new_map(
        self, source: str | bytes | Mapping[str, Any], position: tuple[float, float] | None
    ) -> tuple[AreaMap, bytes]:
        """(Worker thread.) Parse, check and store a new map with its empty route."""
        from dataclasses import replace

        area = parse_map(source)
        if position is not None:
            area.check_position(*position)
        area = replace(area, load_id=secrets.token_hex(8), notes=(*area.notes, *self._room(area)))
        area.keepout_index()
        # The map's rename is the one step: the old route names the old map's load_id, so a
        # crash before the new empty route is stored cannot pair it with the new map.
        text = _map_bytes(area)
        write_atomically(self.storage.map_file, text.decode())
        self.routes.save(Route(), area.load_id)
        return area, text

    def _room(self, area: AreaMap) -> list[str]:
        """(Worker thread.) A note when the clearance leaves (almost) no room in the boundary:
        every waypoint must be that far from its edges."""
        from brasidas.autonomy.areamap import room_to_drive

        clearance = self.core.p.clearance_m
        left = area.boundary.buffer(-clearance).area
        if left >= ROOM_FRACTION * area.boundary.area:
            return []
        most = room_to_drive(area)
        note = (
            f"autonomy.clearance_m {clearance:g} m leaves {left:.0f} m² of this map's "
            f"{area.boundary.area:.0f} m² to drive in (waypoints must be that far from the "
            f"edges and keep-outs); a clearance of {most / 2:.1f} m or less would leave room"
        )
        _LOGGER.warning("patrol: map %r: %s", area.name, note)
        return [note]

    async def update_map(
        self, add: Sequence[Mapping[str, Any]], remove: list[str], *, store: bool = True
    ) -> AreaMap:
        """Add or remove keep-out zones; the route stays; the patrol holds until the path is
        replanned. Geometry and the file in a worker thread; ``store=False``: not written to
        ``map.file`` (the lidar's temporary keep-outs, platformd.obstacle_zones)."""
        async with self._changing:
            if self.core.area is None:
                from brasidas.autonomy.areamap import MapError

                raise MapError("no map loaded")
            base, position = self.core.area, self.robot_position()
            area, text, changes = await asyncio.to_thread(
                self._changed_map, base, add, remove, position, store
            )
            self.core.update_map(area, build=False)
            self._replan(text, changes)
        self.tick()
        return area

    async def reshape_map(self, source: Mapping[str, Any]) -> AreaMap:
        """Replace the map's boundary and keep-outs (a ground station's fence) keeping the
        route, which must still be valid on the new map: the checks of ``update_map`` plus the
        route's own. Geometry and the file in a worker thread; the patrol holds until the
        path is replanned."""
        async with self._changing:
            base, route, position = self.core.area, self.core.route, self.robot_position()
            area, text = await asyncio.to_thread(self._reshaped_map, source, base, route, position)
            self.core.update_map(area, build=False)
            self._replan(text)
        self.tick()
        return area

    def _reshaped_map(
        self,
        source: Mapping[str, Any],
        base: AreaMap | None,
        route: Route,
        position: tuple[float, float] | None,
    ) -> tuple[AreaMap, bytes]:
        """(Worker thread.) The new shape, checked with the route it keeps, and stored under
        the map's load id (the stored route stays paired with it)."""
        from dataclasses import replace

        area = parse_map(source)
        if position is not None:
            area.check_position(*position)
        check_route(route, area)
        area = replace(area, load_id=base.load_id if base is not None else secrets.token_hex(8))
        area.keepout_index()
        text = _map_bytes(area)
        write_atomically(self.storage.map_file, text.decode())
        if base is None:
            self.routes.save(Route(), area.load_id)
        return area, text

    def _changed_map(
        self,
        base: AreaMap,
        add: Sequence[Mapping[str, Any]],
        remove: list[str],
        position: tuple[float, float] | None,
        store: bool = True,
    ) -> tuple[AreaMap, bytes, bytes]:
        """(Worker thread.) The map with keep-outs changed, checked and stored; its text and
        the changes' (for the planner process)."""
        if not store and position is not None:
            from platformd.obstacle_zones import clear_of_robot

            add = clear_of_robot(add, base, *position)
        area = base.with_keepouts(add=add, remove=remove)
        area.keepout_index()  # here, not at the patrol's next step on the event loop
        if position is not None:
            # The lidar's zones it is in already are the patrol's to leave (back out): they
            # must not keep other obstacles out of the plan.
            area.check_position(*position, seen_too=store)
        text = _map_bytes(area)
        if store:
            write_atomically(self.storage.map_file, text.decode())
        return area, text, orjson.dumps({"add": add, "remove": remove})

    async def set_waypoints(
        self, items: list[Any], laps: int | None = None, home: tuple[float, float] | None = None
    ) -> Route:
        """Replace the waypoints on the fly (R-5.3.3.3); stored before they are used (checks
        and the file in a worker thread). ``laps``, ``home``: :attr:`Route.laps`,
        :attr:`Route.home` (a mission's)."""
        async with self._changing:
            area = self.core.area
            if area is None:
                raise RouteError("no map loaded: load one first")
            route = await asyncio.to_thread(self._new_route, area, items, laps, home)
            self.detour = None
            self.core.set_route(route)
        self.tick()
        return route

    def _new_route(
        self,
        area: AreaMap,
        items: list[Any],
        laps: int | None = None,
        home: tuple[float, float] | None = None,
    ) -> Route:
        """(Worker thread.) Parse, check and store waypoints on ``area``."""
        route = dataclasses.replace(parse_waypoints(items, area.points), laps=laps, home=home)
        check_route(route, area)
        self.routes.save(route, area.load_id)
        return route

    @property
    def route(self) -> Route:
        """The route driven now (a go-to's while driving to one point)."""
        return self.core.route

    @property
    def area(self) -> AreaMap | None:
        """The map, None before one is loaded."""
        return self.core.area

    @property
    def map_revision(self) -> int:
        """Counts the map's changes (a fence upload is tied to the revision it made)."""
        return self.core.map_revision

    @property
    def state(self) -> PatrolState:
        return self.core.state

    @property
    def own_route(self) -> Route:
        """The patrol's own route: the one kept aside while driving to one point."""
        return self.core.route if self.detour is None else self._kept_route

    async def go_to_point(self, latitude: float, longitude: float, label: str) -> Route:
        """Drive to one point through the planner (around keep-outs) and stop there: a ground
        station's GUIDED go-to or RTL. The route is kept, not stored over: ``start_patrol``
        goes back to it. Raises RouteError (no map, a point the map refuses)."""
        area = self.core.area
        if area is None:
            raise RouteError("no map loaded")
        if not self.core.enabled:
            raise RouteError("the patrol is switched off (command 10.8)")
        route = Route((Waypoint(latitude, longitude, label),), laps=1)
        await asyncio.to_thread(check_route, route, area)
        # Moving needs arming: a go-to arms through the pre-arm checks as a start does.
        refusal = self.start_check() if self.start_check is not None else None
        if refusal is not None:
            raise RouteError(refusal)
        if self.detour is None:
            self._kept_route = self.core.route
        self.detour = label
        self.core.set_route(route)
        self.core.start()
        self.tick()
        return route

    def start_patrol(self) -> None:
        if self.detour is not None:  # back from a go-to: the patrol's own route again
            self.core.set_route(self._kept_route)
            self.detour = None
        if not self.core.enabled:
            raise RouteError("the patrol is switched off (command 10.8)")
        if self.core.area is None:
            raise RouteError("no map loaded")
        if not self.core.route.waypoints:
            raise RouteError("no waypoints")
        refusal = self.start_check() if self.start_check is not None else None
        if refusal is not None:
            raise RouteError(refusal)
        self.core.start()
        self.tick()

    def stop_patrol(self, *, operator: bool = True) -> None:
        """Stop now; ``operator``: an operator's stop, kept as the last word (``on_stop``);
        else a failsafe's (a lost ground station's hold), whose caller keeps its own."""
        self.core.stop()
        self.tick()
        if operator and self.on_stop is not None:
            self.on_stop()

    def go_to_waypoint(self, index: int) -> None:
        """Head for waypoint ``index`` (from 0) next; RouteError for none such."""
        self.core.go_to(index)
        self.tick()

    def set_enabled(self, enabled: bool) -> None:
        self.core.set_enabled(enabled)
        report_switch(self.bus, "patrol", enabled)
        self.tick()

    async def _command_switch(self, command: SystemCommand) -> CommandResult:
        """10.8: the patrol automation on or off (off stops it and refuses start)."""
        try:
            on = parse_switch(command.payload)
        except PayloadError as err:
            return CommandResult(False, str(err))
        self.set_enabled(on)
        return CommandResult(True, result={"patrol": on, "state": self.core.state.value})


def parse_map(source: str | bytes | Mapping[str, Any]) -> AreaMap:
    """:func:`brasidas.autonomy.areamap.parse_map`, imported (with Shapely) on first use."""
    from brasidas.autonomy.areamap import parse_map

    return parse_map(source)


def _map_bytes(area: AreaMap) -> bytes:
    """The map file's text (and what the planner process is sent). orjson: a town's map in a
    few milliseconds, for the GIL is held while encoding and the event loop waits for it."""
    return orjson.dumps(area.geojson())


def _differs(last: PatrolStatus, report: PatrolStatus) -> bool:
    if (last.state, last.waypoint, last.lap, last.reason, last.enabled, last.waypoints) != (
        report.state,
        report.waypoint,
        report.lap,
        report.reason,
        report.enabled,
        report.waypoints,
    ) or last.path != report.path:
        return True
    if last.distance_m is None or report.distance_m is None:
        return last.distance_m != report.distance_m
    return abs(last.distance_m - report.distance_m) >= 1.0
