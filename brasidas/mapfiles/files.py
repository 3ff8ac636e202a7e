"""Map and route files: the readers and the writer (sans-IO).

:func:`read_map` turns GeoJSON (with or without our roles), KML, OpenStreetMap exports,
ArduPilot fence and rally files and QGC ``.plan`` geofences into the platform's canonical map
GeoJSON; :func:`read_route` reads route files (text lines, JSON lists, GeoJSON, KML
LineStrings, QGC ``.plan`` and ``QGC WPL 110`` missions); :func:`write_route` writes a route
as ``.plan`` or ``.waypoints``. Refusals are :class:`FileRefused`, naming the feature, row or
line and why; what was assumed or left aside is in the result's ``notes``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import PurePath
from typing import Any

from shapely import Point, Polygon

from brasidas.autonomy.geo import LocalFrame
from brasidas.autonomy.route import MAX_WAYPOINTS
from brasidas.mapfiles import qgc
from brasidas.mapfiles.errors import MAX_FILE_BYTES, FileRefused
from brasidas.mapfiles.geojson import geojson_shapes, is_geojson, loads
from brasidas.mapfiles.mission import MavCmd, MissionRoute
from brasidas.mapfiles.precount import map_text, route_text
from brasidas.mapfiles.shapes import MapImport, MapOptions, assemble_map
from brasidas.mapfiles.shapes import plain_json as _plain
from brasidas.mapfiles.xmlfiles import (
    is_overpass,
    kml_shapes,
    local,
    osm_xml_shapes,
    overpass_shapes,
    parse_xml,
)

__all__ = [
    "MAX_FILE_BYTES",
    "FileRefused",
    "MapImport",
    "MapOptions",
    "RouteImport",
    "check_map_order",
    "check_route_order",
    "read_map",
    "read_route",
    "write_route",
]

NEAR_M = 50_000.0
"""A route within this distance of the robot is where it is (when there is no map)."""
EXPORT_FORMATS = ("plan", "waypoints")
FORMATS_HELP = (
    "GeoJSON, KML, OpenStreetMap (.osm, Overpass JSON), QGC .plan, QGC WPL 110, "
    "ArduPilot fence/rally text"
)


@dataclass
class RouteImport:
    """A file read as a route: items for the platform's ``set_waypoints`` ({lat, lon} or a
    named point's name), keep-outs from a plan's fence, and notes."""

    waypoints: list[Any]
    format: str
    notes: list[str] = field(default_factory=list)
    keepouts: list[dict[str, Any]] = field(default_factory=list)
    home: tuple[float, float] | None = None
    laps: int | None = None
    """A mission's end (:attr:`brasidas.autonomy.route.Route.laps`)."""

    def positions(self) -> list[tuple[float, float]]:
        return [
            (w["lat"], w["lon"]) for w in self.waypoints if isinstance(w, Mapping) and "lat" in w
        ]


def read_map(text: str, filename: str = "", options: MapOptions | None = None) -> MapImport:
    """A map file's canonical GeoJSON (format from the content), or FileRefused."""
    options = options or MapOptions()
    stem = PurePath(filename).stem if filename else ""
    body = map_text(text)
    if qgc.is_wpl(body):
        return assemble_map(qgc.wpl_shapes(body), options, "QGC WPL 110 fence", name=stem)
    if body.startswith("<"):
        root = parse_xml(body, filename or "the file")
        kind = local(root.tag)
        if kind == "kml":
            shapes, lines, notes = kml_shapes(root)
            if lines:
                notes.append(f"{len(lines)} LineStrings not used (a route: load it with 'route')")
            return assemble_map(shapes, options, "KML", notes=notes, name=stem)
        if kind == "osm":
            shapes, bounds, notes = osm_xml_shapes(root)
            return assemble_map(
                shapes, options, "OpenStreetMap XML", bounds=bounds, notes=notes, name=stem
            )
        raise FileRefused(f"XML with a <{kind}> root is neither KML nor OpenStreetMap")
    if body.startswith(("{", "[")):
        data = loads(body, filename or "the file")
        if qgc.is_plan(data):
            notes = ["the plan's mission items not used (load them with 'route')"]
            return assemble_map(qgc.plan_shapes(data), options, "QGC plan", notes=notes, name=stem)
        if is_overpass(data):
            shapes, bounds, notes = overpass_shapes(data)
            return assemble_map(
                shapes, options, "Overpass JSON", bounds=bounds, notes=notes, name=stem
            )
        if is_geojson(data):
            shapes, notes, name = geojson_shapes(data)
            return assemble_map(shapes, options, "GeoJSON", name=name or stem, notes=notes)
        raise FileRefused(f"JSON that is neither GeoJSON, a QGC plan nor Overpass; {FORMATS_HELP}")
    if qgc.is_rally_or_old_fence(body):
        return assemble_map(qgc.old_fence_shapes(body), options, "ArduPilot fence/rally", name=stem)
    raise FileRefused(f"not a map format this station reads ({FORMATS_HELP})")


def read_route(
    text: str, filename: str = "", *, fence: bool = False, skip_unsupported: bool = False
) -> RouteImport:
    """A route file's waypoints, or FileRefused. ``fence``: a plan's exclusion fences too;
    ``skip_unsupported``: a mission's commands a rover cannot do are left out (named)."""
    body = route_text(text)
    if qgc.is_wpl(body):
        items = qgc.wpl_items(body)
        fences = [item for item in items[1:] if item.command >= MavCmd.NAV_FENCE_RETURN_POINT]
        if fences and len(fences) == len(items) - 1:
            raise FileRefused("a fence or rally file, not a mission: load it with 'map'")
        mission = qgc.wpl_route(body, skip_unsupported=skip_unsupported)
        return _mission_import(mission, "QGC WPL 110")
    if qgc.is_rally_or_old_fence(body) and any(
        line.split()[:1] == ["RALLY"] for line in body.upper().splitlines()
    ):
        raise FileRefused(
            "an ArduPilot rally file, not a route: load it with 'map' (its rally points become "
            "the map's named points rally-1, rally-2, ..., which a route can name)"
        )
    if body.startswith("<"):
        root = parse_xml(body, filename or "the file")
        if local(root.tag) != "kml":
            raise FileRefused(f"XML with a <{local(root.tag)}> root is not a KML route")
        _, lines, _ = kml_shapes(root)
        if len(lines) != 1:
            raise FileRefused(f"a KML route is one LineString (this file has {len(lines)})")
        if len(lines[0]) > MAX_WAYPOINTS:
            raise FileRefused(f"{len(lines[0])} waypoints, more than {MAX_WAYPOINTS}")
        return RouteImport([_waypoint(lat, lon) for lat, lon in lines[0]], "KML")
    if body.startswith(("{", "[")):
        data = loads(body, filename or "the file")
        if qgc.is_plan(data):
            result = _mission_import(
                qgc.plan_route(data, skip_unsupported=skip_unsupported), "QGC plan"
            )
            if fence:
                _plan_fence(data, result)
            return result
        if qgc.is_old_mission(data):
            plan = qgc.old_mission_as_plan(data)
            return _mission_import(
                qgc.plan_route(plan, skip_unsupported=skip_unsupported), "QGC mission (old)"
            )
        if fence:
            raise FileRefused("--fence reads a QGC .plan's geofence; this file is not a plan")
        if isinstance(data, list):
            return _json_list(data)
        return _geojson_route(data)
    if fence:
        raise FileRefused("--fence reads a QGC .plan's geofence; this file is not a plan")
    return _text_route(body)


def write_route(
    fmt: str,
    route: Sequence[Mapping[str, Any]],
    home: tuple[float, float] | None,
    area: Mapping[str, Any] | None = None,
    laps: int | None = None,
) -> str:
    """The platform's route (``get_map``'s list) as a ``plan`` or ``waypoints`` file. Home is
    the mission file's (``home``: the station passes it, else the robot's position), else the
    first waypoint; a closed route ends with a DO_JUMP (``laps`` its repeat count)."""
    positions = [(float(w["lat"]), float(w["lon"])) for w in route]
    if not positions:
        raise FileRefused("the platform has no route to export")
    home = home or positions[0]
    if fmt == "plan":
        return qgc.plan_text(positions, home, area, laps)
    if fmt == "waypoints":
        return qgc.wpl_text(positions, home, laps)
    raise FileRefused(f"export format {fmt!r}: {' or '.join(EXPORT_FORMATS)}")


def check_map_order(found: MapImport, robot: tuple[float, float] | None) -> None:
    """Refuse a map whose boundary holds the robot only with latitude and longitude swapped."""
    if robot is None:
        found.notes.append("latitude/longitude order not checked: the robot's position unknown")
        return
    ring = found.boundary_ring()
    given = _inside(ring, [robot])
    swapped = _inside([(lon, lat) for lat, lon in ring], [robot])
    if swapped and not given:
        raise FileRefused(
            "latitude and longitude look swapped: the robot "
            f"({robot[0]:.6f}, {robot[1]:.6f}) is inside the boundary only with them swapped"
        )
    if swapped and given:
        raise FileRefused(
            "latitude/longitude order ambiguous: the robot "
            f"({robot[0]:.6f}, {robot[1]:.6f}) is inside the boundary either way"
        )


def check_route_order(
    found: RouteImport,
    boundary: Sequence[tuple[float, float]] | None,
    robot: tuple[float, float] | None,
) -> None:
    """Refuse waypoints that fit the map (or lie near the robot) only with latitude and
    longitude swapped, or fit both ways (ambiguous). ``boundary``: (lat, lon) ring."""
    points = found.positions()
    if not points:
        return
    swapped_points = [(lon, lat) for lat, lon in points]
    if boundary:
        given = _inside(boundary, points)
        swapped = _inside(boundary, swapped_points)
        reference = "the map's boundary"
    elif robot is not None:
        given = _near(robot, points)
        swapped = _near(robot, swapped_points)
        reference = f"the robot's position (within {NEAR_M / 1000:.0f} km)"
    else:
        found.notes.append("latitude/longitude order not checked: no map, position unknown")
        return
    if swapped and not given:
        raise FileRefused(
            f"latitude and longitude look swapped: the waypoints fit {reference} only with "
            "them swapped"
        )
    if swapped and given and points != swapped_points:
        raise FileRefused(
            f"latitude/longitude order ambiguous: the waypoints fit {reference} either way"
        )


# ---------------------------------------------------------------------------- helpers


def _inside(ring: Sequence[tuple[float, float]], points: Sequence[tuple[float, float]]) -> bool:
    if any(abs(lat) > 90 for lat, _ in ring) or any(abs(lat) > 90 for lat, _ in points):
        return False
    area = Polygon([(lon, lat) for lat, lon in ring])
    return all(area.covers(Point(lon, lat)) for lat, lon in points)


def _near(robot: tuple[float, float], points: Sequence[tuple[float, float]]) -> bool:
    frame = LocalFrame(*robot)
    for lat, lon in points:
        if abs(lat) > 90:
            return False
        x, y = frame.to_local(lat, lon)
        if math.hypot(x, y) > NEAR_M:
            return False
    return True


def _waypoint(lat: float, lon: float, name: str = "") -> dict[str, Any]:
    plain: dict[str, Any] = {"lat": lat, "lon": lon}
    if name:
        plain["name"] = name
    return plain


def _mission_import(mission: MissionRoute, fmt: str) -> RouteImport:
    if len(mission.waypoints) > MAX_WAYPOINTS:
        raise FileRefused(f"{len(mission.waypoints)} waypoints, more than {MAX_WAYPOINTS}")
    return RouteImport(
        list(mission.waypoint_items()), fmt, mission.notes, [], mission.home, mission.laps
    )


def _plan_fence(data: Mapping[str, Any], found: RouteImport) -> None:
    """A plan's exclusion fences as keep-outs; its inclusion fences must hold every waypoint
    (the map's boundary is not changed by a route)."""
    from shapely.geometry import mapping

    shapes = qgc.plan_shapes(data, rally=False)
    for shape in shapes:
        if shape.role == "inclusion":
            outside = [
                index
                for index, (lat, lon) in enumerate(found.positions())
                if not shape.geometry.covers(Point(lon, lat))
            ]
            if outside:
                raise FileRefused(f"waypoint {outside[0]} is outside the plan's {shape.label}")
            found.notes.append(f"{shape.label} holds every waypoint (the map's boundary stays)")
            continue
        geometry = _plain(mapping(shape.geometry))
        found.keepouts.append(
            {
                "type": "Feature",
                "id": shape.ident,
                "properties": {"role": "keepout", "name": shape.label},
                "geometry": geometry,
            }
        )
    found.notes.append(f"{len(found.keepouts)} keep-outs from the plan's geofence")


def _json_list(data: list[Any]) -> RouteImport:
    """``[lat, lon(, alt)]`` lists, ``{lat, lon}`` objects, "LAT,LON" or point names."""
    waypoints: list[Any] = []
    altitudes = False
    if len(data) > MAX_WAYPOINTS:
        raise FileRefused(f"{len(data)} waypoints, more than {MAX_WAYPOINTS}")
    for index, item in enumerate(data):
        where = f"waypoint {index}"
        if isinstance(item, list):
            if len(item) not in (2, 3) or not all(_is_number(v) for v in item):
                raise FileRefused(f"{where}: a list is [lat, lon] or [lat, lon, alt]")
            altitudes = altitudes or len(item) == 3
            waypoints.append(_checked(float(item[0]), float(item[1]), where))
        elif isinstance(item, Mapping):
            lat, lon = item.get("lat"), item.get("lon")
            if "lat" in item or "lon" in item:
                if not (_is_number(lat) and _is_number(lon)):
                    raise FileRefused(f"{where}: 'lat' and 'lon' are numbers")
                assert isinstance(lat, int | float) and isinstance(lon, int | float)
                name = item.get("name", "")
                checked = _checked(float(lat), float(lon), where)
                waypoints.append(
                    checked | ({"name": name} if isinstance(name, str) and name else {})
                )
            elif isinstance(item.get("name"), str) and item["name"]:
                waypoints.append({"name": item["name"]})  # a named point of the platform's map
            else:
                raise FileRefused(f'{where}: an object is {{"lat", "lon"}} or {{"name"}}')
        elif isinstance(item, str):
            waypoints.append(item)
        else:
            raise FileRefused(f'{where}: expected [lat, lon], {{"lat", "lon"}} or a name')
    notes = ["altitudes ignored (a ground robot)"] if altitudes else []
    return RouteImport(waypoints, "JSON list", notes)


def _geojson_route(data: Any) -> RouteImport:
    from brasidas.autonomy.route import RouteError, geojson_route_items

    try:
        items = geojson_route_items(data)
    except RouteError as exc:
        raise FileRefused(str(exc)) from None
    found = _json_list(items)
    found.format = "GeoJSON"
    return found


def _text_route(body: str) -> RouteImport:
    """One waypoint a line: ``lat,lon``, ``lat lon``, ``lat<TAB>lon``, ``lat,lon,alt``,
    ``[lat, lon, alt]``, or a named point's name; ``#`` starts a comment."""
    waypoints: list[Any] = []
    altitudes = False
    for number, line in enumerate(body.splitlines(), start=1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        where = f"line {number}"
        if len(waypoints) >= MAX_WAYPOINTS:
            raise FileRefused(f"{where}: more than {MAX_WAYPOINTS} waypoints")
        fields = [f for f in re.split(r"[\s,\[\]]+", text) if f]
        values = _floats(fields)
        if values is not None:
            if len(values) not in (2, 3):
                raise FileRefused(
                    f"{where}: {len(values)} numbers; a waypoint is LAT,LON or LAT,LON,ALT"
                )
            altitudes = altitudes or len(values) == 3
            waypoints.append(_checked(values[0], values[1], where))
        else:
            waypoints.append(text)
    if not waypoints:
        raise FileRefused("no waypoints in the file")
    notes = ["altitudes ignored (a ground robot)"] if altitudes else []
    return RouteImport(waypoints, "text", notes)


def _floats(fields: list[str]) -> list[float] | None:
    """The fields as numbers (nan and inf included, to be refused by name), or None."""
    try:
        return [float(f) for f in fields]
    except ValueError:
        return None


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _checked(lat: float, lon: float, where: str) -> dict[str, Any]:
    if not (math.isfinite(lat) and math.isfinite(lon)) or abs(lat) > 90 or abs(lon) > 180:
        raise FileRefused(f"{where}: {lat}, {lon} is not a latitude, longitude")
    return _waypoint(lat, lon)
