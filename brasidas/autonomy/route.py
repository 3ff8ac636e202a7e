"""Waypoint routes: parsing, the order they are driven in, and their file on the platform.

A route whose last waypoint is its first is *closed*: it loops (0, 1, ..., n-2, 0, ...). An
open route is driven to its end and back in reverse order (0, ..., n-1, n-2, ..., 0, 1, ...).
A lap is counted each time the route comes back to its first waypoint.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from brasidas.limits import ROUTE_MAX_WAYPOINTS

if TYPE_CHECKING:
    from brasidas.autonomy.areamap import AreaMap

MAX_WAYPOINTS = ROUTE_MAX_WAYPOINTS
SAME_POINT_DEG = 1e-7
"""Waypoints closer than this (about 1 cm) are the same place."""


class RouteError(ValueError):
    """Waypoints refused; the message is the reason, for the operator."""


@dataclass(frozen=True)
class Waypoint:
    latitude: float
    longitude: float
    name: str = ""
    """The map's named point it came from, if any."""
    speed: float | None = None
    """m/s on the leg to it (a mission's DO_CHANGE_SPEED); None: the cruise speed."""

    def same_place(self, other: Waypoint) -> bool:
        return (
            abs(self.latitude - other.latitude) < SAME_POINT_DEG
            and abs(self.longitude - other.longitude) < SAME_POINT_DEG
        )

    def as_dict(self) -> dict[str, Any]:
        plain: dict[str, Any] = {"lat": self.latitude, "lon": self.longitude}
        if self.name:
            plain["name"] = self.name
        if self.speed is not None:
            plain["speed"] = self.speed
        return plain

    def label(self, index: int) -> str:
        """How operators number it: from 1, as the console and the CLI show it."""
        return f"waypoint {index + 1}" + (f" ({self.name})" if self.name else "")


@dataclass(frozen=True)
class Route:
    waypoints: tuple[Waypoint, ...] = ()
    laps: int | None = None
    """Stop after this many laps of a closed route, or once at the end of an open one (a
    mission's DO_JUMP count, or its RETURN_TO_LAUNCH); None: patrol until stopped."""
    home: tuple[float, float] | None = None
    """A mission file's home (lat, lon), kept so an export says the file's, not the robot's."""

    @property
    def closed(self) -> bool:
        """The last waypoint is the first: the route loops."""
        return len(self.waypoints) >= 3 and self.waypoints[0].same_place(self.waypoints[-1])

    @property
    def stops(self) -> int:
        """How many distinct waypoints are driven to (a closed route's last is its first)."""
        return len(self.waypoints) - 1 if self.closed else len(self.waypoints)

    def as_list(self) -> list[dict[str, Any]]:
        return [waypoint.as_dict() for waypoint in self.waypoints]


@dataclass(frozen=True)
class Cursor:
    """Where on a route the patrol is: the target's index, the direction and the lap."""

    index: int = 0
    forward: bool = True
    lap: int = 0
    """Completed laps: returns to the first waypoint."""
    departed: bool = False
    """The first waypoint has been left once (arriving there again completes a lap)."""

    def advance(self, route: Route) -> Cursor:
        """The next target after arriving at (or skipping) this one."""
        stops = route.stops
        if stops <= 1:
            return self
        lap = self.lap + (1 if self.index == 0 and self.departed else 0)
        if route.closed:
            return Cursor((self.index + 1) % stops, True, lap, True)
        forward = self.forward
        index = self.index + (1 if forward else -1)
        if not 0 <= index < stops:  # an end: turn back
            forward = not forward
            index = self.index + (1 if forward else -1)
        return Cursor(index, forward, lap, True)


def parse_waypoints(
    items: Iterable[Any], points: Mapping[str, tuple[float, float]] | None = None
) -> Route:
    """Waypoints from "LAT,LON" strings, named points of the map, [lat, lon] pairs or
    {"lat", "lon"[, "name"]} / {"name"} objects. Raises RouteError with the item's index."""
    points = points or {}
    waypoints = []
    for index, item in enumerate(items):
        if index >= MAX_WAYPOINTS:
            raise RouteError(f"more than {MAX_WAYPOINTS} waypoints")
        waypoints.append(_waypoint(item, points, f"waypoint {index + 1}"))
    return Route(tuple(waypoints))


def parse_route_file(text: str, points: Mapping[str, tuple[float, float]] | None = None) -> Route:
    """A route file (see :func:`route_items`) as a route."""
    return parse_waypoints(route_items(text), points)


def route_items(text: str) -> list[Any]:
    """The waypoints of a route file, unchecked: GeoJSON (a LineString, or Point features in
    order), a JSON list of waypoints, or text with one waypoint ("LAT,LON" or a point name)
    per line (``#`` starts a comment)."""
    stripped = text.strip()
    if stripped.startswith(("{", "[")):
        try:
            data = json.loads(stripped)
        except ValueError as exc:
            raise RouteError(f"not JSON: {exc}") from None
        return data if isinstance(data, list) else _geojson_waypoints(data)
    lines = [line.split("#", 1)[0].strip() for line in stripped.splitlines()]
    return [line for line in lines if line]


def geojson_route_items(data: Any) -> list[Any]:
    """The waypoints of decoded GeoJSON (a LineString, or Point features in order), unchecked."""
    return _geojson_waypoints(data)


class RouteStore:
    """The route's file on the platform: JSON, replaced atomically so a crash keeps one."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def load(self) -> Route:
        """The stored route (empty when there is no file). Raises RouteError when unreadable."""
        try:
            text = self.path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return Route()
        except OSError as exc:
            raise RouteError(f"cannot read {self.path}: {exc}") from None
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise RouteError(f"{self.path}: not JSON: {exc}") from None
        if not isinstance(data, Mapping) or not isinstance(data.get("waypoints"), list):
            raise RouteError(f"{self.path}: no 'waypoints' list")
        laps = data.get("laps")
        route = parse_waypoints(data["waypoints"])
        if not (isinstance(laps, int) and not isinstance(laps, bool) and laps >= 1):
            laps = None
        return Route(route.waypoints, laps, parse_home(data.get("home")))

    def map_id(self) -> str | None:
        """The ``load_id`` of the map the stored route was set on ("" when the file does not
        say; None when there is no file or it cannot be read)."""
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        found = data.get("map", "") if isinstance(data, Mapping) else ""
        return found if isinstance(found, str) else ""

    def save(self, route: Route, map_id: str = "") -> None:
        """Store the route, with the ``load_id`` of the map it belongs to."""
        plain: dict[str, Any] = {"waypoints": route.as_list()}
        if route.laps is not None:
            plain["laps"] = route.laps
        if route.home is not None:
            plain["home"] = list(route.home)
        if map_id:
            plain["map"] = map_id
        write_atomically(self.path, json.dumps(plain, indent=1, allow_nan=False))


def write_atomically(path: Path, text: str) -> None:
    """Write a file so a crash leaves the old or the new one: a temporary file beside it,
    fsync, rename over, fsync the folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, temporary = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as file:
            file.write(text + "\n")
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)


def remove_stale_temporaries(path: Path) -> list[Path]:
    """Remove the temporary files :func:`write_atomically` left beside ``path`` when a crash
    came before their rename (``.NAME.`` and a random suffix); the ones removed."""
    removed = []
    for candidate in path.parent.glob(f".{path.name}.*"):
        suffix = candidate.name[len(path.name) + 2 :]
        if len(suffix) == 8 and candidate.is_file():  # mkstemp's 8 random characters
            candidate.unlink(missing_ok=True)
            removed.append(candidate)
    return removed


# --------------------------------------------------------------------------- helpers


def _waypoint(item: Any, points: Mapping[str, tuple[float, float]], where: str) -> Waypoint:
    if isinstance(item, str):
        text = item.strip()
        if text in points:
            lat, lon = points[text]
            return Waypoint(lat, lon, text)
        parts = text.split(",")
        if len(parts) != 2:
            known = ", ".join(sorted(points)) or "none"
            raise RouteError(f"{where}: {text!r} is neither LAT,LON nor a named point ({known})")
        try:
            lat, lon = float(parts[0]), float(parts[1])
        except ValueError:
            raise RouteError(f"{where}: {text!r} is not LAT,LON in degrees") from None
        return _checked(lat, lon, "", where)
    if isinstance(item, list | tuple) and len(item) == 2:
        return _checked(_number(item[0], where), _number(item[1], where), "", where)
    if isinstance(item, Mapping):
        name = item.get("name", "")
        if not isinstance(name, str):
            raise RouteError(f"{where}: 'name' must be a string")
        if "lat" not in item and "lon" not in item:
            if name not in points:
                raise RouteError(f"{where}: no named point {name!r} on the map")
            lat, lon = points[name]
            return Waypoint(lat, lon, name)
        waypoint = _checked(
            _number(item.get("lat"), where), _number(item.get("lon"), where), name, where
        )
        speed = item.get("speed")
        if speed is None:
            return waypoint
        if not _positive(speed):
            raise RouteError(f"{where}: 'speed' must be a positive number of m/s")
        return Waypoint(waypoint.latitude, waypoint.longitude, name, float(speed))
    raise RouteError(f'{where}: expected "LAT,LON", a point name, [lat, lon] or {{lat, lon}}')


def parse_home(value: Any) -> tuple[float, float] | None:
    """A route's home: [lat, lon] in range, else None (no home)."""
    if (
        isinstance(value, list | tuple)
        and len(value) == 2
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
        and math.isfinite(value[0])
        and math.isfinite(value[1])
        and abs(value[0]) <= 90
        and abs(value[1]) <= 180
    ):
        return float(value[0]), float(value[1])
    return None


def _positive(value: Any) -> bool:
    return (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and math.isfinite(value)
        and value > 0
    )


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise RouteError(f"{where}: latitude and longitude must be numbers")
    return float(value)


def _checked(lat: float, lon: float, name: str, where: str) -> Waypoint:
    if not (math.isfinite(lat) and math.isfinite(lon)) or abs(lat) > 90 or abs(lon) > 180:
        raise RouteError(f"{where}: {lat}, {lon} is not a latitude, longitude")
    return Waypoint(lat, lon, name)


def _geojson_waypoints(data: Any) -> list[Any]:
    if not isinstance(data, Mapping):
        raise RouteError("expected GeoJSON or a list of waypoints")
    kind = data.get("type")
    if kind == "FeatureCollection":
        features = data.get("features")
        if not isinstance(features, list):
            raise RouteError("a FeatureCollection needs a 'features' list")
        lines = [f for f in features if _geometry_type(f) == "LineString"]
        if len(lines) == 1:
            return _geojson_waypoints(lines[0])
        items: list[Any] = []
        for feature in features:
            if _geometry_type(feature) == "Point":
                items.extend(_geojson_waypoints(feature))
        return items
    if kind == "Feature":
        geometry = data.get("geometry")
        properties = data.get("properties")
        name = properties.get("name", "") if isinstance(properties, Mapping) else ""
        items = _geojson_waypoints(geometry)
        if _geometry_type(data) == "Point" and isinstance(name, str) and name:
            items = [dict(items[0], name=name)]
        return items
    coordinates = data.get("coordinates")
    if kind == "Point":
        return [_lonlat(coordinates)]
    if kind == "LineString" and isinstance(coordinates, list):
        return [_lonlat(position) for position in coordinates]
    raise RouteError(f"GeoJSON {kind!r}: a route is a LineString or Point features")


def _geometry_type(feature: Any) -> str | None:
    if not isinstance(feature, Mapping):
        return None
    geometry = feature.get("geometry")
    kind = geometry.get("type") if isinstance(geometry, Mapping) else None
    return kind if isinstance(kind, str) else None


def _lonlat(position: Any) -> dict[str, Any]:
    if not isinstance(position, list) or len(position) not in (2, 3):
        raise RouteError("a GeoJSON position is [longitude, latitude]")
    return {"lat": position[1], "lon": position[0]}


def check_route(route: Route, area: AreaMap | None) -> None:
    """Raise RouteError when a waypoint is outside the map's boundary or in a keep-out zone."""
    if area is None:
        return
    from brasidas.autonomy.areamap import MapError  # loaded with the map already

    for index, waypoint in enumerate(route.waypoints):
        try:
            area.check_position(waypoint.latitude, waypoint.longitude, waypoint.label(index))
        except MapError as exc:
            raise RouteError(str(exc)) from None
