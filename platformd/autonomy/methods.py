"""Signaling methods of the patrol: ``load_map``, ``update_map``, ``get_map``,
``set_waypoints``, ``get_patrol``, ``patrol_start``, ``patrol_stop``, ``go_to``.

A refused map or route is answered -32602 with the reason; the old one stays. Those that
change the patrol are control methods (issue 13): refused to an observer (CONTROL_REFUSED, the
holder's station id), the first caller while nobody holds control claims it.
"""

from __future__ import annotations

from typing import Any

from brasidas.autonomy.route import RouteError, parse_home
from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, Dispatcher, RpcError
from platformd.authority import Authority
from platformd.autonomy.patrol import PatrolActor

CONTROL = ("load_map", "update_map", "set_waypoints", "patrol_start", "patrol_stop", "go_to")
"""The methods that change the map, the route or the patrol: the controlling station's."""


class PatrolMethods:
    def __init__(self, actor: PatrolActor) -> None:
        self.actor = actor

    def register(self, rpc: Dispatcher, authority: Authority) -> None:
        for name in CONTROL:
            rpc.add(name, authority.guard(name, getattr(self, name)))
        for name in ("get_map", "get_patrol"):
            rpc.add(name, getattr(self, name))
        # A large map is counted in its text before it is parsed: a 150,001-vertex one is
        # refused for a scan, not 20 MB of parsed lists (the limit applies exactly after).
        rpc.check_unparsed("load_map", lambda text: _too_many_positions(text, "map refused"))
        rpc.check_unparsed("update_map", lambda text: _too_many_positions(text, "update refused"))

    async def load_map(self, call: CallContext, map: Any) -> dict[str, Any]:
        """Replace the area map (GeoJSON object or text): wipes the waypoints and stops."""
        if not isinstance(map, dict | str):
            raise RpcError(INVALID_PARAMS, "map refused: expected a GeoJSON object or text")
        from brasidas.autonomy.areamap import MapError  # with Shapely: maps need it anyway

        try:
            area = await self.actor.load_map(map)
        except MapError as exc:
            raise RpcError(INVALID_PARAMS, f"map refused: {exc}") from None
        return {"map": area.summary(), "patrol": self.actor.report.as_dict()}

    async def update_map(
        self, call: CallContext, add: Any = None, remove: Any = None
    ) -> dict[str, Any]:
        """Add keep-out zones (GeoJSON features) and remove others (by id)."""
        add = [] if add is None else add
        remove = [] if remove is None else remove
        if not isinstance(add, list) or not all(isinstance(f, dict) for f in add):
            raise RpcError(INVALID_PARAMS, "update refused: 'add' is a list of GeoJSON features")
        if not isinstance(remove, list) or not all(isinstance(r, str) for r in remove):
            raise RpcError(INVALID_PARAMS, "update refused: 'remove' is a list of keep-out ids")
        from brasidas.autonomy.areamap import MapError

        try:
            area = await self.actor.update_map(add, remove)
        except MapError as exc:
            raise RpcError(INVALID_PARAMS, f"update refused: {exc}") from None
        return {"map": area.summary(), "patrol": self.actor.report.as_dict()}

    def get_map(self, call: CallContext) -> dict[str, Any]:
        """The map as GeoJSON (null when none), its revision (telemetry's ``map_rev``) and the
        route, for the console."""
        area = self.actor.core.area
        return {
            "map": area.geojson() if area is not None else None,
            "map_rev": self.actor.core.map_revision,
            "route": self.actor.core.route.as_list(),
            "closed": self.actor.core.route.closed,
            "laps": self.actor.core.route.laps,
            "home": self.actor.core.route.home,
        }

    async def set_waypoints(
        self, call: CallContext, waypoints: Any, laps: Any = None, home: Any = None
    ) -> dict[str, Any]:
        """Replace the waypoints on the fly: "LAT,LON", point names, [lat, lon] or {lat, lon
        [, speed]}; ``laps``: stop after that many laps (once at an open route's end); ``home``:
        [lat, lon], a mission file's home (what an export says)."""
        if not isinstance(waypoints, list):
            raise RpcError(INVALID_PARAMS, "waypoints refused: expected a list")
        if laps is not None and (isinstance(laps, bool) or not isinstance(laps, int) or laps < 1):
            raise RpcError(INVALID_PARAMS, "waypoints refused: 'laps' is a whole number ≥ 1")
        try:
            route = await self.actor.set_waypoints(waypoints, laps, parse_home(home))
        except RouteError as exc:
            raise RpcError(INVALID_PARAMS, f"waypoints refused: {exc}") from None
        return {
            "waypoints": route.as_list(),
            "closed": route.closed,
            "laps": route.laps,
            "patrol": self.actor.report.as_dict(),
        }

    def get_patrol(self, call: CallContext) -> dict[str, Any]:
        """The patrol's state, target, distance, lap, reason and planned path."""
        return self.actor.report.as_dict()

    async def patrol_start(self, call: CallContext) -> dict[str, Any]:
        try:
            self.actor.start_patrol()
        except RouteError as exc:
            raise RpcError(INVALID_PARAMS, f"cannot start: {exc}") from None
        return self.actor.report.as_dict()

    async def go_to(
        self, call: CallContext, latitude: Any, longitude: Any, label: Any = "go to"
    ) -> dict[str, Any]:
        """Drive to one point through the planner (around keep-outs) and stop there: the
        console's click on the map, the CLI's ``goto``; arms through the pre-arm checks as a
        start does. The route is kept: ``patrol_start`` goes back to it."""
        point = [latitude, longitude]
        if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in point):
            raise RpcError(INVALID_PARAMS, "go to refused: latitude and longitude are numbers")
        if not (-90 <= latitude <= 90 and -180 <= longitude <= 180):
            raise RpcError(INVALID_PARAMS, f"go to refused: {latitude}, {longitude} is no place")
        if not isinstance(label, str) or not 0 < len(label) <= 40:
            raise RpcError(INVALID_PARAMS, "go to refused: 'label' is a short text")
        try:
            await self.actor.go_to_point(float(latitude), float(longitude), label)
        except RouteError as exc:
            raise RpcError(INVALID_PARAMS, f"go to refused: {exc}") from None
        return self.actor.report.as_dict()

    async def patrol_stop(self, call: CallContext) -> dict[str, Any]:
        self.actor.stop_patrol()
        if self.actor.settle is not None:  # answered once the stop is on disk (issue 27)
            await self.actor.settle()
        return self.actor.report.as_dict()


def _too_many_positions(text: str, what: str) -> str | None:
    """(A worker thread.) A request whose text holds more positions than a map may: refused."""
    from brasidas.autonomy.areamap import MAX_VERTICES
    from brasidas.mapfiles.precount import positions_in

    count = positions_in(text)
    if count <= MAX_VERTICES:
        return None
    return f"{what}: about {count} vertices, more than {MAX_VERTICES} (not read)"
