"""The patrol actor: the route on the area map, driven from ``POSE`` to ``CMD_VEL`` (R-5, R-12).

Ten times a second (``autonomy.rate_hz``) it steps :class:`~brasidas.autonomy.patrol.Patrol`
with the latest pose and, while patrolling, publishes the command on ``CMD_VEL`` (one zero
when it stops). The manual override suspends it inside the ``OVERRIDE_STATE`` delivery (the
arbiter stops obeying ``CMD_VEL`` in the same delivery); releasing it replans from where the
operator left the robot. Nothing here needs a station (R-0.4).

The map and the route are files on the platform (``map.file``, ``autonomy.route_file``),
replaced atomically; they survive a restart. Shapely and NumPy (~17 MB) are imported when a
map is, never on a platform without one.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from brasidas import topics
from brasidas.actor import Actor
from brasidas.autonomy.localization import Estimate
from brasidas.autonomy.patrol import STOP, Patrol, PatrolParameters
from brasidas.autonomy.route import (
    Route,
    RouteError,
    RouteStore,
    check_route,
    parse_waypoints,
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
from platformd.automation import report_switch
from platformd.commands import CommandRouter, SystemCommand

if TYPE_CHECKING:
    from brasidas.autonomy.areamap import AreaMap

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
        self.core.enabled = enabled
        self.storage = storage
        self.routes = RouteStore(storage.route_file)
        self.period = 1.0 / rate_hz
        self.autostart = autostart
        self.demo = demo
        self._clock = clock
        self._pose: PoseEstimate | None = None
        self._driving = False
        self._reported: PatrolStatus | None = None
        self.loaded = False

    # ------------------------------------------------------------------ lifecycle

    async def run(self) -> None:
        if self._clock is None:
            self._clock = asyncio.get_running_loop().time
        if not self.loaded:
            self.load()
        if self.commands is not None:
            self.on_remove(self.commands.register(self.name, {PATROL: self._command_switch}))
        self.subscribe(topics.POSE, self._on_pose)
        self.subscribe(topics.OVERRIDE_STATE, self._on_override)
        try:
            while True:
                self.tick()
                await asyncio.sleep(self.period)
        finally:
            if self._driving:
                self.bus.publish(topics.CMD_VEL, Velocity(0.0, 0.0))
                self._driving = False

    def load(self) -> None:
        """The stored map and route (the --sim demo when none is stored); start if configured."""
        self.loaded = True
        area, route, stored = self._stored()
        self.core.set_map(area)
        if area is not None:
            self.core.set_route(route)
        report_switch(self.bus, "patrol", self.core.enabled)
        if route.waypoints and stored and self.autostart and self.core.enabled:
            self.core.start()
            _LOGGER.info(
                "patrol: %d waypoints on %r, starting", len(route.waypoints), area and area.name
            )
        self._report()

    def _stored(self) -> tuple[AreaMap | None, Route, bool]:
        area: AreaMap | None = None
        try:
            stored = self.storage.map_file.read_bytes()
        except FileNotFoundError:
            stored = None
        except OSError as exc:
            stored = None
            _LOGGER.error("patrol: map %s refused: %s", self.storage.map_file, exc)
        if stored is not None:
            from brasidas.autonomy.areamap import MapError

            try:
                area = parse_map(stored)
            except MapError as exc:
                _LOGGER.error("patrol: map %s refused: %s", self.storage.map_file, exc)
        try:
            route = self.routes.load()
            check_route(route, area)
        except RouteError as exc:
            _LOGGER.error("patrol: route %s refused: %s", self.routes.path, exc)
            route = Route()
        if area is None and self.demo is not None:
            area = parse_map(self.demo[0])
            _LOGGER.info("patrol: no stored map, the --sim demo map %r", area.name)
            if not route.waypoints:
                return area, parse_waypoints(self.demo[1], area.points), False
        return area, route, bool(route.waypoints)

    # ------------------------------------------------------------------ stepping

    def tick(self) -> None:
        """Step the patrol with the latest pose and publish the command while it drives."""
        estimate, fix_age = self._estimate()
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
        self._report()

    def _estimate(self) -> tuple[Estimate | None, float | None]:
        pose, area = self._pose, self.core.area
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

    def load_map(self, source: str | bytes | Mapping[str, Any]) -> AreaMap:
        """Replace the map (validated first): wipes the waypoints and stops (R-5.3.3.5)."""
        area = parse_map(source)
        position = self.robot_position()
        if position is not None:
            area.check_position(*position)
        write_atomically(self.storage.map_file, json.dumps(area.geojson(), allow_nan=False))
        self.routes.save(Route())
        self.core.set_map(area)
        _LOGGER.warning("patrol: map %r loaded; waypoints cleared, patrol stopped", area.name)
        self.tick()
        return area

    def update_map(self, add: list[Mapping[str, Any]], remove: list[str]) -> AreaMap:
        """Add or remove keep-out zones; the route stays, the path is replanned."""
        if self.core.area is None:
            from brasidas.autonomy.areamap import MapError

            raise MapError("no map loaded")
        area = self.core.area.with_keepouts(add=add, remove=remove)
        position = self.robot_position()
        if position is not None:
            area.check_position(*position)
        write_atomically(self.storage.map_file, json.dumps(area.geojson(), allow_nan=False))
        self.core.update_map(area)
        self.tick()
        return area

    def reshape_map(self, source: Mapping[str, Any]) -> AreaMap:
        """Replace the map's boundary and keep-outs (a ground station's fence) keeping the
        route, which must still be valid on the new map: the checks of ``update_map`` plus the
        route's own."""
        area = parse_map(source)
        position = self.robot_position()
        if position is not None:
            area.check_position(*position)
        check_route(self.core.route, area)
        write_atomically(self.storage.map_file, json.dumps(area.geojson(), allow_nan=False))
        self.core.update_map(area)
        self.tick()
        return area

    def set_waypoints(self, items: list[Any]) -> Route:
        """Replace the waypoints on the fly (R-5.3.3.3); stored before they are used."""
        area = self.core.area
        if area is None:
            raise RouteError("no map loaded: load one first")
        route = parse_waypoints(items, area.points)
        check_route(route, area)
        self.routes.save(route)
        self.core.set_route(route)
        self.tick()
        return route

    def start_patrol(self) -> None:
        if not self.core.enabled:
            raise RouteError("the patrol is switched off (command 10.8)")
        if self.core.area is None:
            raise RouteError("no map loaded")
        if not self.core.route.waypoints:
            raise RouteError("no waypoints")
        self.core.start()
        self.tick()

    def stop_patrol(self) -> None:
        self.core.stop()
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
