"""The area map (R-12): where the robot may drive, keep-out zones and named points, from GeoJSON.

A map is one GeoJSON ``FeatureCollection`` in WGS-84 (``[longitude, latitude]``), the
platform's canonical form (the station's readers turn other formats into it):

- one or more ``Polygon``/``MultiPolygon`` features with ``"role": "boundary"``: where the robot
  may drive. A MultiPolygon's parts are joined (the RFC 7946 form of an area split at the 180°
  meridian is one area again); several boundary features are intersected (ArduPilot's several
  inclusion fences: the robot must be inside all of them). Holes are places it may not go;
- any number of ``Polygon``/``MultiPolygon`` features with ``"role": "keepout"``: buildings,
  obstacles, no-go zones, each part kept as it is; named by the feature's ``id``, else its
  ``name`` property (repeated names are made unique, and the map's ``notes`` say so);
- any number of ``Point`` features with a ``name`` property: named places routes can use.

:func:`parse_map` refuses anything else with a :class:`MapError` whose message says what is
wrong and where. Geometry is in a :class:`~brasidas.autonomy.geo.LocalFrame` at the centre of
the boundary (metres), with Shapely: the frame is exact through Earth-centred coordinates, so
it is continuous across the 180° meridian and up to the poles; :data:`MAX_EXTENT_M` bounds
how far it reaches.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import orjson
import shapely
from shapely import MultiPolygon, Point, Polygon, STRtree, unary_union
from shapely.geometry.base import BaseGeometry
from shapely.validation import explain_validity

from brasidas.autonomy.geo import LocalFrame, centre_of
from brasidas.limits import MAP_MAX_VERTICES
from brasidas.perception.messages import SEEN_KEEPOUT_PREFIX

MAX_EXTENT_M = 20_000.0
"""A map wider than this is refused. Within it the tangent plane's distances are exact to
5 mm (the plane leaves the ground by 7.8 m at 10 km from its origin: heights are not used)."""
MAX_VERTICES = MAP_MAX_VERTICES
"""All polygons together (:data:`brasidas.limits.MAP_MAX_VERTICES`)."""
GRID_M = 1e-6
"""Parts of one area are joined on a micrometre grid (the two halves of an area split at the
180° meridian meet within rounding, not exactly)."""

Area = Polygon | MultiPolygon
"""A boundary or a keep-out in the local frame."""


class MapError(ValueError):
    """A map, a map update or a position refused; the message is the reason, for the operator."""


@dataclass(frozen=True)
class AreaMap:
    """A validated map. Geometry in the local frame (metres); ``geojson()`` gives it back."""

    frame: LocalFrame
    boundary: Area
    """Where the robot may drive: the intersection of the boundary features."""
    keepouts: Mapping[str, Area]
    points: Mapping[str, tuple[float, float]]
    """Named points: (latitude, longitude)."""
    name: str = ""
    notes: tuple[str, ...] = ()
    """What the operator should know about the map as loaded (ids made unique, ...)."""
    load_id: str = ""
    """Names one loading of the map (kept by keep-out updates): a stored route belongs to
    the map it was set on, so a crash between writing a new map and its empty route cannot
    pair the new map with the old route. A GeoJSON foreign member, ``"load_id"``."""
    _features: Mapping[str, dict[str, Any]] = field(default_factory=dict, repr=False)
    """The keep-outs' GeoJSON features by id, as given (for export)."""
    _boundary_features: tuple[dict[str, Any], ...] = field(default=(), repr=False)
    _index: tuple[STRtree, tuple[str, ...]] | None = field(
        default=None, init=False, repr=False, compare=False
    )

    def local(self, latitude: float, longitude: float) -> tuple[float, float]:
        return self.frame.to_local(latitude, longitude)

    def inside(self, x: float, y: float) -> bool:
        """The point is within the boundary (its edge included)."""
        return bool(self.boundary.covers(Point(x, y)))

    @property
    def vertices(self) -> int:
        """Of every polygon together (what :data:`MAX_VERTICES` bounds)."""
        return int(shapely.get_num_coordinates(self.boundary)) + int(
            shapely.get_num_coordinates(list(self.keepouts.values())).sum()
        )

    def keepout_at(self, x: float, y: float) -> str | None:
        """The id of a keep-out zone containing the point, or None."""
        tree, ids = self.keepout_index()
        hits = tree.query(Point(x, y), predicate="intersects")
        return ids[int(min(hits))] if len(hits) else None

    def meets_keepout(self, geometry: BaseGeometry, *, seen_too: bool = True) -> bool:
        """Some keep-out zone touches ``geometry``; ``seen_too=False``: of the map's own,
        not the obstacles the lidar saw (:data:`SEEN_KEEPOUT_PREFIX`), which it guards."""
        tree, ids = self.keepout_index()
        hits = tree.query(geometry, predicate="intersects")
        if seen_too:
            return bool(len(hits))
        return any(not ids[int(i)].startswith(SEEN_KEEPOUT_PREFIX) for i in hits)

    def keepout_index(self) -> tuple[STRtree, tuple[str, ...]]:
        """The keep-outs' spatial index and their ids in its order (built on first use: call
        it in the thread that loads the map)."""
        if self._index is None:
            ids = tuple(self.keepouts)
            object.__setattr__(self, "_index", (STRtree([self.keepouts[i] for i in ids]), ids))
        assert self._index is not None
        return self._index

    def check_position(
        self, latitude: float, longitude: float, what: str = "the robot", *, seen_too: bool = True
    ) -> None:
        """Raise :class:`MapError` when a position is outside the boundary or in a keep-out;
        ``seen_too=False``: one of the map's own, not the lidar's (the patrol leaves those)."""
        x, y = self.local(latitude, longitude)
        if not self.inside(x, y):
            # To the drivable area: a point in a hole is near its edge, not the outer ring's.
            raise MapError(
                f"{what} ({latitude:.6f}, {longitude:.6f}) is outside the map's boundary "
                f"({self.boundary.distance(Point(x, y)):.1f} m from it)"
            )
        zone = self.keepout_at(x, y)
        if zone is not None and not seen_too and zone.startswith(SEEN_KEEPOUT_PREFIX):
            tree, ids = self.keepout_index()
            hits = tree.query(Point(x, y), predicate="intersects")
            zone = next(
                (
                    ids[int(i)]
                    for i in sorted(hits)
                    if not ids[int(i)].startswith(SEEN_KEEPOUT_PREFIX)
                ),
                None,
            )
        if zone is not None:
            raise MapError(f"{what} ({latitude:.6f}, {longitude:.6f}) is in keep-out zone {zone!r}")

    def with_keepouts(
        self, add: Iterable[Mapping[str, Any]] = (), remove: Iterable[str] = ()
    ) -> AreaMap:
        """A copy with keep-out features added (GeoJSON features) and others removed (by id);
        only the changed zones are parsed."""
        add = list(add)
        _check_positions([feature.get("geometry") for feature in add], already=self.vertices)
        features = dict(self._features)
        keepouts = dict(self.keepouts)
        for zone_id in remove:
            if zone_id not in features:
                raise MapError(
                    f"no keep-out zone {zone_id!r} (have: {', '.join(_some(features)) or 'none'})"
                )
            del features[zone_id]
            del keepouts[zone_id]
        notes: list[str] = []
        renamed: list[str] = []
        for index, feature in enumerate(add):
            zone_id, zone, derived = _keepout(feature, f"added feature {index}", self.frame)
            if zone_id in keepouts and not derived:
                raise MapError(f"keep-out zone {zone_id!r} exists already (remove it first)")
            zone_id = _unique(zone_id, keepouts, renamed)
            keepouts[zone_id] = zone
            features[zone_id] = dict(feature) | {"id": zone_id}
        if renamed:
            notes.append(_renamed_note(renamed))
        vertices = _vertices(self.boundary) + sum(map(_vertices, keepouts.values()))
        if vertices > MAX_VERTICES:
            raise MapError(f"too many vertices ({vertices} > {MAX_VERTICES})")
        return replace(self, keepouts=keepouts, _features=features, notes=tuple(notes))

    def geojson(self) -> dict[str, Any]:
        """The map as a GeoJSON FeatureCollection (what was loaded, keep-outs with their ids)."""
        return {
            "type": "FeatureCollection",
            "name": self.name,
            **({"load_id": self.load_id} if self.load_id else {}),
            "features": [
                *self._boundary_features,
                *self._features.values(),
                *self._point_features(),
            ],
        }

    def summary(self) -> dict[str, Any]:
        """Counts and size, for status and answers."""
        return {
            "name": self.name,
            "origin": [round(self.frame.latitude, 7), round(self.frame.longitude, 7)],
            "area_m2": round(self.boundary.area, 1),
            "keepouts": sorted(self.keepouts),
            "points": sorted(self.points),
            "vertices": self.vertices,
            "notes": list(self.notes),
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
    """Validate a GeoJSON map (text or decoded) into an :class:`AreaMap`, or raise MapError.

    Seconds for a map of thousands of buildings: call it from a worker thread."""
    if isinstance(source, str | bytes):
        try:
            # orjson: a few milliseconds for a town, with the GIL held (the loop waits for it).
            data = orjson.loads(source)
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
    if not boundaries:
        raise MapError(
            "a map needs a boundary: a Polygon or MultiPolygon feature with role 'boundary'"
        )
    # Every geometry counted before any is built: the boundary and its holes too.
    _check_positions(feature.get("geometry") for feature in features)
    frame, boundary = _boundary(boundaries)
    keepouts: dict[str, Area] = {}
    kept: dict[str, dict[str, Any]] = {}
    points: dict[str, tuple[float, float]] = {}
    renamed: list[str] = []
    vertices = _vertices(boundary)
    for index, feature in others:
        role = _role(feature)
        where = f"feature {index}"
        if role == "keepout":
            zone_id, zone, derived = _keepout(feature, where, frame)
            if zone_id in keepouts and not derived:
                raise MapError(f"{where}: keep-out id {zone_id!r} used twice")
            zone_id = _unique(zone_id, keepouts, renamed)
            keepouts[zone_id] = zone
            kept[zone_id] = feature | {"id": zone_id}
            vertices += _vertices(zone)
        elif role in ("point", ""):
            name, (lat, lon) = _named_point(feature, where)
            if name in points:
                raise MapError(f"{where}: point name {name!r} used twice")
            points[name] = (lat, lon)
        else:
            raise MapError(f"{where}: unknown role {role!r} (boundary, keepout or point)")
        if vertices > MAX_VERTICES:
            raise MapError(f"too many vertices (more than {MAX_VERTICES})")
    name = data.get("name", "")
    load_id = data.get("load_id", "")
    return AreaMap(
        load_id=load_id if isinstance(load_id, str) else "",
        frame=frame,
        boundary=boundary,
        keepouts=keepouts,
        points=points,
        name=name if isinstance(name, str) else "",
        notes=(_renamed_note(renamed),) if renamed else (),
        _features=kept,
        _boundary_features=tuple(boundaries),
    )


def obstacles(area: AreaMap) -> BaseGeometry:
    """Every keep-out zone as one geometry (empty when there are none)."""
    return unary_union(list(area.keepouts.values()))


def room_to_drive(area: AreaMap) -> float:
    """The largest clearance this map leaves room for (metres): the radius of the largest
    circle inside the boundary and outside every keep-out."""
    free = area.boundary.difference(obstacles(area)) if area.keepouts else area.boundary
    parts = list(free.geoms) if isinstance(free, MultiPolygon) else [free]
    best = 0.0
    for part in parts:
        if isinstance(part, Polygon) and not part.is_empty:
            circle = shapely.maximum_inscribed_circle(part, tolerance=0.05)
            best = max(best, float(circle.length))
    return best


# --------------------------------------------------------------------------- helpers


def count_positions(geometries: Iterable[Any], limit: int) -> int:
    """The positions (arrays that start with a number) in GeoJSON geometries, without building
    any: counting stops once past ``limit``."""
    count = 0
    stack = list(geometries)
    while stack:
        item = stack.pop()
        if isinstance(item, Mapping):
            stack.extend(item.values())
        elif isinstance(item, list | tuple) and item:
            if isinstance(item[0], int | float) and not isinstance(item[0], bool):
                count += 1
                if count > limit:
                    break
            else:
                stack.extend(item)
    return count


def _check_positions(geometries: Iterable[Any], already: int = 0) -> None:
    """Refuse geometries with more than :data:`MAX_VERTICES` positions (with ``already``)
    before Shapely builds any: a 150,000-vertex boundary costs a count, not seconds."""
    count = already + count_positions(geometries, MAX_VERTICES - already)
    if count > MAX_VERTICES:
        raise MapError(f"too many vertices (more than {MAX_VERTICES})")


def _role(feature: Mapping[str, Any]) -> str:
    properties = feature.get("properties")
    if not isinstance(properties, Mapping):
        return ""
    role = properties.get("role", "")
    return role if isinstance(role, str) else "?"


def _keepout(feature: Mapping[str, Any], where: str, frame: LocalFrame) -> tuple[str, Area, bool]:
    """The zone's id, its geometry, and whether the id came from its name (or nothing)."""
    properties = feature.get("properties")
    properties = properties if isinstance(properties, Mapping) else {}
    raw_id = feature.get("id")
    derived = not (isinstance(raw_id, str | int) and not isinstance(raw_id, bool) and raw_id != "")
    if derived:
        raw_id = properties.get("name")
    zone_id = str(raw_id).strip() if isinstance(raw_id, str | int) else ""
    where = f"{where} (keep-out {zone_id or 'without a name'!r})"
    geometry = feature.get("geometry")
    if not isinstance(geometry, Mapping):
        raise MapError(f"{where}: no geometry")
    return zone_id, _area(geometry, frame, where, "a keep-out"), derived


def _unique(zone_id: str, taken: Mapping[str, Any], renamed: list[str]) -> str:
    """``zone_id``, else ``zone_id (2)``, ``(3)``... (noted in ``renamed``); ``keepout-N``
    for a zone with neither an id nor a name."""
    if not zone_id:
        number = len(taken) + 1
        while f"keepout-{number}" in taken:
            number += 1
        return f"keepout-{number}"
    if zone_id not in taken:
        return zone_id
    number = 2
    while f"{zone_id} ({number})" in taken:
        number += 1
    renamed.append(zone_id)
    return f"{zone_id} ({number})"


def _renamed_note(renamed: list[str]) -> str:
    names = sorted(set(renamed))
    shown = ", ".join(repr(n) for n in names[:5]) + (" ..." if len(names) > 5 else "")
    return (
        f"{len(renamed)} keep-outs without an id repeat a name ({shown}): "
        f"their ids are made unique ('{names[0]} (2)', ...)"
    )


def _some(names: Iterable[str], most: int = 20) -> list[str]:
    listed = list(names)
    return listed[:most] + ([f"... {len(listed) - most} more"] if len(listed) > most else [])


def _vertices(geometry: BaseGeometry) -> int:
    return int(shapely.get_num_coordinates(geometry))


def _boundary(features: list[dict[str, Any]]) -> tuple[LocalFrame, Area]:
    """The frame at the centre of the boundary features and their intersection in it."""
    geometries = []
    for index, feature in enumerate(features):
        geometry = feature.get("geometry")
        where = "the boundary" if len(features) == 1 else f"boundary {index}"
        if not isinstance(geometry, Mapping) or geometry.get("type") not in (
            "Polygon",
            "MultiPolygon",
        ):
            raise MapError(f"{where} must be a Polygon or MultiPolygon")
        geometries.append((geometry, where))
    outer = [
        position
        for geometry, where in geometries
        for rings in _polygons(geometry, where)
        for position in rings[0][:-1]
    ]
    try:
        first = LocalFrame(*centre_of(outer))
    except ValueError as exc:
        raise MapError(f"the boundary {exc}") from None
    areas = [_area(geometry, first, where, "the boundary") for geometry, where in geometries]
    minx, miny, maxx, maxy = areas[0].bounds
    if max(maxx - minx, maxy - miny) > MAX_EXTENT_M:
        raise MapError(
            f"the boundary is {max(maxx - minx, maxy - miny) / 1000:.1f} km across: "
            f"the largest map is {MAX_EXTENT_M / 1000:.0f} km across"
        )
    # The origin at the middle of the boundary's extent, as the plane is most exact there.
    frame = LocalFrame(*first.to_geo((minx + maxx) / 2, (miny + maxy) / 2))
    boundary = _area(geometries[0][0], frame, geometries[0][1], "the boundary")
    for geometry, where in geometries[1:]:
        joined = shapely.intersection(
            boundary, _area(geometry, frame, where, "the boundary"), grid_size=GRID_M
        )
        boundary = _polygonal(joined)
    if boundary.is_empty or boundary.area <= 0.01:
        raise MapError("the boundary features have no area in common")
    return frame, boundary


def _polygons(geometry: Mapping[str, Any], where: str) -> list[list[list[tuple[float, float]]]]:
    """Each polygon of a Polygon or MultiPolygon as its rings of (lon, lat)."""
    if geometry.get("type") == "Polygon":
        return [_rings(geometry.get("coordinates"), where)]
    parts = geometry.get("coordinates")
    if not isinstance(parts, list) or not parts:
        raise MapError(f"{where}: a MultiPolygon needs polygons")
    return [_rings(part, f"{where}, polygon {index}") for index, part in enumerate(parts)]


def _area(geometry: Mapping[str, Any], frame: LocalFrame, where: str, what: str) -> Area:
    """A Polygon or MultiPolygon in the frame, its parts joined where they touch."""
    if geometry.get("type") not in ("Polygon", "MultiPolygon"):
        raise MapError(f"{where}: {what} must be a Polygon or MultiPolygon")
    polygons = [_polygon(rings, frame, where) for rings in _polygons(geometry, where)]
    if len(polygons) == 1:
        return polygons[0]
    return _polygonal(shapely.union_all(polygons, grid_size=GRID_M))


def _polygonal(geometry: BaseGeometry) -> Area:
    if isinstance(geometry, Polygon | MultiPolygon):
        return geometry
    parts = [g for g in getattr(geometry, "geoms", ()) if isinstance(g, Polygon)]
    return MultiPolygon(parts)


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


def _polygon(rings: list[list[tuple[float, float]]], frame: LocalFrame, where: str) -> Polygon:
    polygon, problem = local_polygon(rings, frame)
    if problem:
        raise MapError(f"{where}: {problem}")
    return polygon


def local_polygon(
    rings: Iterable[Iterable[tuple[float, float]]], frame: LocalFrame
) -> tuple[Polygon, str]:
    """Rings of (lon, lat) as a polygon in ``frame``'s metres, and what is wrong with it
    ("" when nothing): the one validity check of the platform's map and the station's files,
    made in metres (in degrees a ring across 180° crosses itself, and degrees are not square
    away from the equator)."""
    local = [[frame.to_local(lat, lon) for lon, lat in ring] for ring in rings]
    polygon = Polygon(local[0], local[1:])
    if not polygon.is_valid:
        return polygon, f"invalid polygon: {_explain(polygon, frame)}"
    if polygon.area <= 0.01:
        return polygon, "the polygon has no area"
    return polygon, ""


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
