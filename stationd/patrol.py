"""The station's local API for a platform's patrol (issue 12): map, waypoints, start and stop.

Each call is passed to the platform's signaling method of the same purpose; a refusal comes
back as the platform's error, reason included.
"""

from __future__ import annotations

from typing import Any

from brasidas.codecs.jsonrpc import CallContext
from stationd.context import StationContext

METHODS = (
    "map_load",
    "map_update",
    "map_get",
    "route_set",
    "patrol_get",
    "patrol_start",
    "patrol_stop",
    "goto",
)


class PatrolApi:
    def __init__(self, ctx: StationContext) -> None:
        self.ctx = ctx

    async def _call(self, platform_id: str, method: str, **params: Any) -> Any:
        connection = await self.ctx.connection(platform_id)
        return await connection.call(method, **params)

    async def api_map_load(self, call: CallContext, platform_id: str, map: Any) -> Any:
        """Replace the platform's map (GeoJSON object or text): wipes its waypoints, stops it."""
        return await self._call(platform_id, "load_map", map=map)

    async def api_map_update(
        self, call: CallContext, platform_id: str, add: Any = None, remove: Any = None
    ) -> Any:
        """Add keep-out zones (GeoJSON features) and remove others (by id)."""
        return await self._call(platform_id, "update_map", add=add or [], remove=remove or [])

    async def api_map_get(self, call: CallContext, platform_id: str) -> Any:
        """The platform's map (GeoJSON) and route."""
        return await self._call(platform_id, "get_map")

    async def api_route_set(self, call: CallContext, platform_id: str, waypoints: Any) -> Any:
        """Replace the waypoints on the fly ("LAT,LON", point names, [lat, lon], {lat, lon})."""
        return await self._call(platform_id, "set_waypoints", waypoints=waypoints)

    async def api_patrol_get(self, call: CallContext, platform_id: str) -> Any:
        return await self._call(platform_id, "get_patrol")

    async def api_patrol_start(self, call: CallContext, platform_id: str) -> Any:
        return await self._call(platform_id, "patrol_start")

    async def api_patrol_stop(self, call: CallContext, platform_id: str) -> Any:
        return await self._call(platform_id, "patrol_stop")

    async def api_goto(
        self, call: CallContext, platform_id: str, latitude: Any, longitude: Any
    ) -> Any:
        """Drive to one point through the platform's planner and stop there (the route kept)."""
        return await self._call(platform_id, "go_to", latitude=latitude, longitude=longitude)


async def async_setup(ctx: StationContext) -> None:
    api = PatrolApi(ctx)
    for name in METHODS:
        ctx.api.add(name, getattr(api, f"api_{name}"), session_required=False)
