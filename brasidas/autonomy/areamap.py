"""The area map (R-12): a boundary, keep-out zones and named points, from GeoJSON.

A map is one GeoJSON ``FeatureCollection`` in WGS-84 (``[longitude, latitude]``):

- exactly one ``Polygon`` feature with ``"role": "boundary"`` in its properties: where the
  robot may drive (holes in it are places it may not);
- any number of ``Polygon``/``MultiPolygon`` features with ``"role": "keepout"``: buildings,
  obstacles, no-go zones; named by the feature's ``id`` or its ``name`` property;
- any number of ``Point`` features with a ``name`` property: named places routes can use.

:func:`parse_map` refuses anything else with a :class:`MapError` whose message says what is
wrong and where. Geometry is in a :class:`~brasidas.autonomy.geo.LocalFrame` centred on the
boundary (metres), with Shapely.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from shapely import Point, Polygon, unary_union
from shapely.geometry.base import BaseGeometry
from shapely.validation import explain_validity

from brasidas.autonomy.geo import LocalFrame

MAX_EXTENT_M = 20_000.0
"""A map wider than this is refused: the tangent plane would bend away from the ground."""
MAX_VERTICES = 20_000
"""All polygons together; bounds the planner's work."""


class MapError(ValueError):
    """A map, a map update or a position refused; the message is the reason, for the operator."""


@dataclass(frozen=True)
class AreaMap:
    """A validated map. Geometry in the local frame (metres); ``geojson()`` gives it back."""

    frame: LocalFrame
    boundary: Polygon
    keepouts: Mapping[str, Polygon]
    points: Mapping[str, tuple[float, float]]
    """Named points: (latitude, longitude)."""
    name: str = ""
    _features: Mapping[str, dict[str, Any]] = field(default_factory=dict, repr=False)
    """The keep-outs' GeoJSON features by id, as given (for export)."""
    _boundary_feature: dict[str, Any] = field(default_factory=dict, repr=False)

    def local(self, latitude: float, longitude: float) -> tuple[float, float]:
        return self.frame.to_local(latitude, longitude)

    def inside(self, x: float, y: float) -> bool:
        """The point is within the boundary (its edge included)."""
        return bool(self.boundary.covers(Point(x, y)))

    def keepout_at(self, x: float, y: float) -> str | None:
        """The id of a keep-out zone containing the point, or None."""
        point = Point(x, y)
        for zone_id, zone in self.keepouts.items():
            if zone.covers(point):
                return zone_id
        return None

    def check_position(self, latitude: float, longitude: float, what: str = "the robot") -> None:
        """Raise :class:`MapError` when a position is outside the boundary or in a keep-out."""
        x, y = self.local(latitude, longitude)
        if not self.inside(x, y):
            raise MapError(
                f"{what} ({latitude:.6f}, {longitude:.6f}) is outside the map's boundary "
                f"({self.boundary.exterior.distance(Point(x, y)):.1f} m from it)"
            )
        zone = self.keepout_at(x, y)
        if zone is not None:
            raise MapError(f"{what} ({latitude:.6f}, {longitude:.6f}) is in keep-out zone {zone!r}")

    def with_keepouts(
        self, add: Iterable[Mapping[str, Any]] = (), remove: Iterable[str] = ()
    ) -> AreaMap:
        """A copy with keep-out features added (GeoJSON features) and others removed (by id)."""
        features = dict(self._features)
        for zone_id in remove:
            if zone_id not in features:
                raise MapError(
                    f"no keep-out zone {zone_id!r} (have: {', '.join(features) or 'none'})"
                )
            del features[zone_id]
        for index, feature in enumerate(add):
            zone_id, _ = _keepout(feature, f"added feature {index}", self.frame, len(features))
            if zone_id in features:
                raise MapError(f"keep-out zone {zone_id!r} exists already (remove it first)")
            features[zone_id] = dict(feature) | {"id": zone_id}
        return parse_map(
            {
                "type": "FeatureCollection",
                "name": self.name,
                "features": [self._boundary_feature, *features.values(), *self._point_features()],
            }
        )

    def geojson(self) -> dict[str, Any]:
        """The map as a GeoJSON FeatureCollection (what was loaded, keep-outs with their ids)."""
        return {
            "type": "FeatureCollection",
            "name": self.name,
            "features": [self._boundary_feature, *self._features.values(), *self._point_features()],
        }

    def summary(self) -> dict[str, Any]:
        """Counts and size, for status and answers."""
        return {
            "name": self.name,
            "origin": [self.frame.latitude, self.frame.longitude],
            "area_m2": round(self.boundary.area, 1),
            "keepouts": sorted(self.keepouts),
            "points": sorted(self.points),
        }

    def _point_features(self) -> list[dict[str, Any]]:
        return [
            {
                "type": "Feature",
                "properties": {"name": name},
                "geometry": {"type": "Point", "coordinates": [lon, lat]},
            }
            for name, (lat, lon) in self.points.items()
        ]


def parse_map(source: str | bytes | Mapping[str, Any]) -> AreaMap:
    """Validate a GeoJSON map (text or decoded) into an :class:`AreaMap`, or raise MapError."""
    if isinstance(source, str | bytes):
        try:
            data = json.loads(source)
        except (ValueError, RecursionError) as exc:
            raise MapError(f"not JSON: {exc}") from None
    else:
        data = source
    if not isinstance(data, Mapping) or data.get("type") != "FeatureCollection":
        raise MapError("not a GeoJSON FeatureCollection")
    features = data.get("features")
    if not isinstance(features, list):
        raise MapError("a FeatureCollection needs a 'features' list")
    boundaries: list[dict[str, Any]] = []
    others: list[tuple[int, dict[str, Any]]] = []
    for index, feature in enumerate(features):
        if not isinstance(feature, Mapping) or feature.get("type") != "Feature":
            raise MapError(f"feature {index}: not a GeoJSON Feature")
        if _role(feature) == "boundary":
            boundaries.append(dict(feature))
        else:
            others.append((index, dict(feature)))
    if len(boundaries) != 1:
        raise MapError(
            f"a map needs exactly one Polygon feature with role 'boundary' (found {len(boundaries)})"
        )
    boundary_feature = boundaries[0]
    geometry = boundary_feature.get("geometry")
    if not isinstance(geometry, Mapping) or geometry.get("type") != "Polygon":
        raise MapError("the boundary must be a Polygon")
    rings = _rings(geometry.get("coordinates"), "the boundary")
    lon0, lat0 = _centre(rings[0])
    frame = LocalFrame(lat0, lon0)
    boundary = _polygon(rings, frame, "the boundary")
    minx, miny, maxx, maxy = boundary.bounds
    if max(maxx - minx, maxy - miny) > MAX_EXTENT_M:
        raise MapError(f"the boundary is wider than {MAX_EXTENT_M / 1000:.0f} km")
    keepouts: dict[str, Polygon] = {}
    kept: dict[str, dict[str, Any]] = {}
    points: dict[str, tuple[float, float]] = {}
    vertices = len(boundary.exterior.coords)
    for index, feature in others:
        role = _role(feature)
        where = f"feature {index}"
        if role == "keepout":
            zone_id, zone = _keepout(feature, where, frame, len(keepouts))
            if zone_id in keepouts:
                raise MapError(f"{where}: keep-out id {zone_id!r} used twice")
            keepouts[zone_id] = zone
            kept[zone_id] = feature | {"id": zone_id}
            vertices += len(zone.exterior.coords)
        elif role in ("point", ""):
            name, (lat, lon) = _named_point(feature, where)
            if name in points:
                raise MapError(f"{where}: point name {name!r} used twice")
            points[name] = (lat, lon)
        else:
            raise MapError(f"{where}: unknown role {role!r} (boundary, keepout or point)")
    if vertices > MAX_VERTICES:
        raise MapError(f"too many vertices ({vertices} > {MAX_VERTICES})")
    name = data.get("name", "")
    return AreaMap(
        frame=frame,
        boundary=boundary,
        keepouts=keepouts,
        points=points,
        name=name if isinstance(name, str) else "",
        _features=kept,
        _boundary_feature=boundary_feature,
    )


def obstacles(area: AreaMap) -> BaseGeometry:
    """Every keep-out zone as one geometry (empty when there are none)."""
    return unary_union(list(area.keepouts.values()))


# --------------------------------------------------------------------------- helpers


def _role(feature: Mapping[str, Any]) -> str:
    properties = feature.get("properties")
    if not isinstance(properties, Mapping):
        return ""
    role = properties.get("role", "")
    return role if isinstance(role, str) else "?"


def _keepout(
    feature: Mapping[str, Any], where: str, frame: LocalFrame, count: int
) -> tuple[str, Polygon]:
    properties = feature.get("properties")
    properties = properties if isinstance(properties, Mapping) else {}
    raw_id = feature.get("id", properties.get("name"))
    zone_id = (
        str(raw_id) if isinstance(raw_id, str | int) and raw_id != "" else f"keepout-{count + 1}"
    )
    where = f"{where} (keep-out {zone_id!r})"
    geometry = feature.get("geometry")
    if not isinstance(geometry, Mapping):
        raise MapError(f"{where}: no geometry")
    if geometry.get("type") == "Polygon":
        return zone_id, _polygon(_rings(geometry.get("coordinates"), where), frame, where)
    if geometry.get("type") == "MultiPolygon":
        parts = geometry.get("coordinates")
        if not isinstance(parts, list) or not parts:
            raise MapError(f"{where}: a MultiPolygon needs polygons")
        polygons = [_polygon(_rings(part, where), frame, where) for part in parts]
        merged = unary_union(polygons).convex_hull if len(polygons) > 1 else polygons[0]
        assert isinstance(merged, Polygon)
        return zone_id, merged
    raise MapError(f"{where}: a keep-out must be a Polygon or MultiPolygon")


def _named_point(feature: Mapping[str, Any], where: str) -> tuple[str, tuple[float, float]]:
    geometry = feature.get("geometry")
    properties = feature.get("properties")
    name = properties.get("name") if isinstance(properties, Mapping) else None
    if not isinstance(geometry, Mapping) or geometry.get("type") != "Point":
        raise MapError(f"{where}: only Point features may have no role (or role 'point')")
    if not isinstance(name, str) or not name:
        raise MapError(f"{where}: a named point needs a 'name' property")
    lon, lat = _position(geometry.get("coordinates"), f"{where} ({name!r})")
    return name, (lat, lon)


def _rings(coordinates: Any, where: str) -> list[list[tuple[float, float]]]:
    if not isinstance(coordinates, list) or not coordinates:
        raise MapError(f"{where}: a Polygon needs a list of rings")
    rings = []
    for ring_index, ring in enumerate(coordinates):
        if not isinstance(ring, list) or len(ring) < 4:
            raise MapError(f"{where}: ring {ring_index} needs at least 4 positions (closed)")
        positions = [_position(position, f"{where}, ring {ring_index}") for position in ring]
        if positions[0] != positions[-1]:
            raise MapError(f"{where}: ring {ring_index} is not closed (last position != first)")
        rings.append(positions)
    return rings


def _position(position: Any, where: str) -> tuple[float, float]:
    if (
        not isinstance(position, list | tuple)
        or len(position) not in (2, 3)
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in position)
    ):
        raise MapError(f"{where}: a position is [longitude, latitude]")
    lon, lat = float(position[0]), float(position[1])
    if not (math.isfinite(lon) and math.isfinite(lat)) or abs(lat) > 90 or abs(lon) > 180:
        raise MapError(f"{where}: [{lon}, {lat}] is not a longitude, latitude")
    return lon, lat


def _centre(ring: list[tuple[float, float]]) -> tuple[float, float]:
    lons = [lon for lon, _ in ring[:-1]]
    lats = [lat for _, lat in ring[:-1]]
    return (min(lons) + max(lons)) / 2.0, (min(lats) + max(lats)) / 2.0


def _polygon(rings: list[list[tuple[float, float]]], frame: LocalFrame, where: str) -> Polygon:
    local = [[frame.to_local(lat, lon) for lon, lat in ring] for ring in rings]
    polygon = Polygon(local[0], local[1:])
    if not polygon.is_valid:
        raise MapError(f"{where}: invalid polygon: {_explain(polygon, frame)}")
    if polygon.area <= 0.01:
        raise MapError(f"{where}: the polygon has no area")
    return polygon


def _explain(polygon: Polygon, frame: LocalFrame) -> str:
    reason = explain_validity(polygon)
    # "Self-intersection[x y]" is in local metres: say where on the globe instead.
    what, _, rest = reason.partition("[")
    try:
        x, y = (float(v) for v in rest.rstrip("]").split())
    except ValueError:
        return reason
    lat, lon = frame.to_geo(x, y)
    return f"{what.strip().lower()} at {lat:.6f}, {lon:.6f}"
