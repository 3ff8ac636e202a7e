"""The station's local API for map and route files (issues 21 and 22): the CLI and the browser
console upload a file's text; it is read here by :mod:`brasidas.mapfiles` (one parser for both),
checked against the robot's position and the platform's map, and sent to the platform as its
canonical map or waypoints. ``route_export`` writes the platform's route back as a file.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, TypeVar

from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, RpcError
from brasidas.config import SignalingSection
from brasidas.mapfiles import FileRefused
from brasidas.mapfiles.precount import map_request_refusal, route_request_refusal
from stationd.context import StationContext

if TYPE_CHECKING:
    from brasidas.mapfiles.files import MapImport, RouteImport

METHODS = ("map_import", "route_import", "route_export")
ENVELOPE_BYTES = 1024
"""The JSON-RPC request around a map (method, id, session), generously."""
T = TypeVar("T")


class MapFilesApi:
    def __init__(self, ctx: StationContext) -> None:
        self.ctx = ctx

    async def api_map_import(
        self,
        call: CallContext,
        platform_id: str,
        text: str,
        filename: str = "",
        boundary: str = "",
        keepouts: str = "",
        boundary_bbox: bool = False,
        union: bool = False,
    ) -> dict[str, Any]:
        """Read a map file (any format :func:`read_map` knows) and load it on the platform."""
        connection = await self.ctx.connection(platform_id)
        robot = await self._robot(platform_id)
        options = (boundary, keepouts, boundary_bbox, union)
        limit = _request_limit(connection.parameters)
        found = await _refusing(
            f"map refused: {filename}", _read_map, text, filename, options, robot, limit
        )
        answer = await connection.call("load_map", map=found.geojson)
        return dict(answer) | {"format": found.format, "notes": found.notes}

    async def api_route_import(
        self,
        call: CallContext,
        platform_id: str,
        text: str,
        filename: str = "",
        fence: bool = False,
        skip_unsupported: bool = False,
    ) -> dict[str, Any]:
        """Read a route file and set it as the platform's waypoints (``fence``: a plan's
        exclusion fences are added as keep-outs first; ``skip_unsupported``: a mission's
        commands a rover cannot do are left out, each named in the notes)."""
        connection = await self.ctx.connection(platform_id)
        robot = await self._robot(platform_id)
        area = await connection.call("get_map")
        boundary = _boundary(area.get("map") if isinstance(area, Mapping) else None)
        limit = _request_limit(connection.parameters)
        found = await _refusing(
            f"waypoints refused: {filename}",
            _read_route,
            text,
            filename,
            (fence, skip_unsupported),
            boundary,
            robot,
            limit,
        )
        added = [str(f["id"]) for f in found.keepouts]
        if added:
            await connection.call("update_map", add=found.keepouts, remove=[])
        try:
            extra: dict[str, Any] = {}
            if found.laps is not None:
                extra["laps"] = found.laps
            if found.home is not None:
                extra["home"] = list(found.home)
            answer = await connection.call("set_waypoints", waypoints=found.waypoints, **extra)
        except RpcError:
            if added:  # all or nothing: the fence's keep-outs go with the refused route
                await connection.call("update_map", add=[], remove=added)
            raise
        return dict(answer) | {
            "format": found.format,
            "notes": found.notes,
            "keepouts_added": added,
        }

    async def api_route_export(
        self, call: CallContext, platform_id: str, format: str
    ) -> dict[str, Any]:
        """The platform's route as a file's text: ``plan`` (QGC, with the map as its geofence)
        or ``waypoints`` (QGC WPL 110, row 0 home: the robot's position)."""
        connection = await self.ctx.connection(platform_id)
        robot = await self._robot(platform_id)
        area = await connection.call("get_map")
        area = area if isinstance(area, Mapping) else {}
        route = area.get("route", [])
        home = area.get("home")  # the mission file's, when the route came from one
        if isinstance(home, list) and len(home) == 2:
            robot = (float(home[0]), float(home[1]))
        text = await _refusing(
            f"export refused ({format})",
            _write_route,
            format,
            route,
            robot,
            area.get("map"),
            area.get("laps"),
        )
        return {"text": text, "format": format, "waypoints": len(route)}

    async def _robot(self, platform_id: str) -> tuple[float, float] | None:
        """The robot's position from its telemetry, when known."""
        try:
            report = await self.ctx.api.call_local("get_telemetry", platform_id=platform_id)
            snapshot = report["snapshot"]
        except (RpcError, KeyError, TypeError):
            return None
        for section in ("pose", "gps"):
            values = snapshot.get(section) if isinstance(snapshot, Mapping) else None
            if isinstance(values, Mapping):
                lat, lon = values.get("lat"), values.get("lon")
                if isinstance(lat, int | float) and isinstance(lon, int | float):
                    return (float(lat), float(lon))
        return None


async def _refusing(what: str, function: Callable[..., T], *args: Any) -> T:
    """``function(*args)`` in a thread (files can be big); a refusal as the API's error."""
    try:
        return await asyncio.to_thread(function, *args)
    except FileRefused as exc:
        raise RpcError(INVALID_PARAMS, f"{what}: {exc}") from None


# In a worker thread: Shapely is loaded with the first file (not by a station without one).


def _read_map(
    text: str,
    filename: str,
    options: tuple[str, str, bool, bool],
    robot: tuple[float, float] | None,
    limit: int,
) -> MapImport:
    from brasidas.mapfiles.precount import map_text

    map_text(text)  # counted before the parsers and Shapely load: a refusal costs a scan
    from brasidas.mapfiles.files import MapOptions, check_map_order, read_map

    found = read_map(text, filename, MapOptions(*options))
    check_map_order(found, robot)
    _check_size(found.geojson, limit, "the map", "choose fewer keep-outs (--keepouts)")
    return found


def _check_size(payload: Any, limit: int, what: str, advice: str) -> None:
    """Refuse what the platform would not take in one request (it drops the connection)."""
    size = len(json.dumps(payload, separators=(",", ":"), allow_nan=False))
    if size + ENVELOPE_BYTES > limit:
        raise FileRefused(
            f"{what} read is {size / 1024:.0f} KiB, more than the platform takes in one "
            f"request ({limit / 1024:.0f} KiB, its signaling.max_request_bytes): {advice}"
        )


def _request_limit(parameters: Mapping[str, Any]) -> int:
    """What the platform takes in one signaling request: as it announces it
    (``limits.max_request_bytes``), else the platform's default."""
    limits = parameters.get("limits")
    announced = limits.get("max_request_bytes") if isinstance(limits, Mapping) else None
    if isinstance(announced, int) and announced > 0:
        return announced
    return SignalingSection().max_request_bytes


def _read_route(
    text: str,
    filename: str,
    options: tuple[bool, bool],
    boundary: list[tuple[float, float]] | None,
    robot: tuple[float, float] | None,
    limit: int,
) -> RouteImport:
    from brasidas.mapfiles.precount import route_text

    route_text(text)  # counted before the parsers and Shapely load: a refusal costs a scan
    from brasidas.mapfiles.files import check_route_order, read_route

    fence, skip_unsupported = options
    found = read_route(text, filename, fence=fence, skip_unsupported=skip_unsupported)
    check_route_order(found, boundary, robot)
    _check_size(found.waypoints, limit, "the route", "fewer waypoints")
    _check_size(found.keepouts, limit, "the plan's fence", "fewer fence polygons and circles")
    return found


def _write_route(
    fmt: str, route: Any, home: tuple[float, float] | None, area: Any, laps: Any = None
) -> str:
    from brasidas.mapfiles.files import write_route

    if not isinstance(route, list) or not all(isinstance(w, Mapping) for w in route):
        raise FileRefused("the platform's route is not a list of waypoints")
    laps = laps if isinstance(laps, int) and not isinstance(laps, bool) and laps >= 1 else None
    return write_route(fmt, route, home, area if isinstance(area, Mapping) else None, laps)


def _boundary(area: Any) -> list[tuple[float, float]] | None:
    """The map's boundary ring as (lat, lon), from the platform's GeoJSON."""
    if not isinstance(area, Mapping):
        return None
    for feature in area.get("features", []):
        if feature.get("properties", {}).get("role") == "boundary":
            ring = feature["geometry"]["coordinates"][0]
            return [(float(lat), float(lon)) for lon, lat, *_ in ring]
    return None


async def async_setup(ctx: StationContext) -> None:
    api = MapFilesApi(ctx)
    for name in METHODS:
        ctx.api.add(name, getattr(api, f"api_{name}"), session_required=False)
    # A hostile file is refused counted in the request's text: never parsed, never copied.
    ctx.api.check_unparsed("map_import", map_request_refusal)
    ctx.api.check_unparsed("route_import", route_request_refusal)
