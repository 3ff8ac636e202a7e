"""Shapes read from any file (polygons, circles, points; degrees, ``(lon, lat)`` like GeoJSON)
and how they become the platform's canonical map: a boundary, keep-outs and named points.

Every file format reads into a list of :class:`Shape`; :func:`assemble_map` chooses the boundary
and the keep-outs (from the shapes' roles, or the operator's selectors) and refuses anything
it would otherwise have to guess.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from shapely import MultiPolygon, Point, Polygon, box, intersection_all, unary_union
from shapely.geometry import mapping
from shapely.geometry.base import BaseGeometry
from shapely.validation import explain_validity

from brasidas.autonomy.geo import LocalFrame
from brasidas.mapfiles.errors import FileRefused

Ring = Sequence[tuple[float, float]]
"""(longitude, latitude) positions."""
ROLES = ("boundary", "inclusion", "keepout", "point", "other", "")
"""boundary/inclusion: the boundary (inclusions intersected); keepout; point: named place;
other: used only when selected; "": a polygon nobody said what it is (a selector must)."""
CIRCLE_VERTICES = 32
"""A circle becomes a polygon of this many corners on it (the polygon lies inside the circle)."""
LISTED_MAX = 12
"""Candidates named in a refusal at most."""


@dataclass(frozen=True)
class Shape:
    label: str
    """How messages name it: "feature 2 ('barn')", "KML placemark 'field'"."""
    index: int
    """Its position among the file's shapes (a selector's number)."""
    ident: str
    name: str
    geometry: BaseGeometry
    """Polygon, MultiPolygon or Point in degrees (x longitude, y latitude)."""
    role: str = ""
    properties: Mapping[str, Any] = field(default_factory=dict)

    @property
    def polygonal(self) -> bool:
        return isinstance(self.geometry, Polygon | MultiPolygon)

    @classmethod
    def point(
        cls,
        label: str,
        index: int,
        name: str,
        latitude: float,
        longitude: float,
        properties: Mapping[str, Any] | None = None,
    ) -> Shape:
        check_position(longitude, latitude, label)
        return cls(label, index, name, name, Point(longitude, latitude), "point", properties or {})

    def describe(self) -> str:
        kind = "polygon" if self.polygonal else "point"
        extra = f" id {self.ident!r}" if self.ident and self.ident != self.name else ""
        return f"{self.index}: {kind} {self.name or '(no name)'}{extra}"


@dataclass(frozen=True)
class MapOptions:
    """The operator's choices (``map ID FILE --boundary ... --keepouts ...``)."""

    boundary: str = ""
    """Selector of the boundary's shapes (several: their intersection)."""
    keepouts: str = ""
    """Selector of the keep-outs; "rest": every other polygon; "none"."""
    boundary_bbox: bool = False
    """The boundary is the bounding box of everything in the file (or of its stated bounds)."""
    union: bool = False
    """Several boundary polygons make their union (ArduPilot's ``FENCE_OPTIONS`` bit 1, value 2), not
    their intersection (its default); the union must be one area."""


@dataclass
class MapImport:
    """A file read as a map: the canonical GeoJSON, the format, and what the operator should
    know (what was left aside, what was assumed and why)."""

    geojson: dict[str, Any]
    format: str
    notes: list[str] = field(default_factory=list)

    def boundary_ring(self) -> list[tuple[float, float]]:
        """The boundary's outer ring as (lat, lon) (for the order check)."""
        ring = self.geojson["features"][0]["geometry"]["coordinates"][0]
        return [(float(lat), float(lon)) for lon, lat in ring]


def check_position(longitude: float, latitude: float, where: str) -> None:
    if (
        not (math.isfinite(longitude) and math.isfinite(latitude))
        or abs(latitude) > 90
        or abs(longitude) > 180
    ):
        raise FileRefused(f"{where}: {latitude}, {longitude} is not a latitude, longitude")


def polygon_shape(
    label: str,
    index: int,
    rings: Sequence[Ring],
    *,
    role: str = "",
    ident: str = "",
    name: str = "",
    properties: Mapping[str, Any] | None = None,
) -> Shape:
    """A polygon (outer ring, then holes), checked: closed, finite, valid."""
    return Shape(label, index, ident or name, name, _polygon(rings, label), role, properties or {})


def multipolygon_shape(
    label: str,
    index: int,
    polygons: Sequence[Sequence[Ring]],
    *,
    role: str = "",
    ident: str = "",
    name: str = "",
    properties: Mapping[str, Any] | None = None,
) -> Shape:
    parts = [_polygon(rings, f"{label} part {n}") for n, rings in enumerate(polygons)]
    if not parts:
        raise FileRefused(f"{label}: a MultiPolygon with no polygons")
    geometry = MultiPolygon(parts)
    if not geometry.is_valid:
        raise FileRefused(f"{label}: its polygons overlap ({explain(geometry)})")
    return Shape(label, index, ident or name, name, geometry, role, properties or {})


def circle(
    label: str,
    index: int,
    latitude: float,
    longitude: float,
    radius_m: float,
    *,
    role: str,
    ident: str,
    vertices: int = CIRCLE_VERTICES,
) -> Shape:
    """A circle as a polygon of ``vertices`` corners: a keep-out's polygon holds the circle
    (circumscribed: corners at r / cos(π/n), so no point of the circle is left out), an
    inclusion's lies inside it (inscribed: corners on it), each erring on the safe side."""
    check_position(longitude, latitude, label)
    if not (math.isfinite(radius_m) and 0.5 <= radius_m <= 10_000):
        raise FileRefused(f"{label}: radius {radius_m} m is not between 0.5 m and 10 km")
    frame = LocalFrame(latitude, longitude)
    corner_m = radius_m / math.cos(math.pi / vertices) if role == "keepout" else radius_m
    ring = []
    for k in range(vertices):
        angle = 2 * math.pi * k / vertices
        lat, lon = frame.to_geo(corner_m * math.cos(angle), corner_m * math.sin(angle))
        ring.append((lon, lat))
    ring.append(ring[0])
    properties = {"circle_radius_m": radius_m, "circle_vertices": vertices}
    return Shape(
        f"{label} (circle of {radius_m:g} m as {vertices} vertices)",
        index,
        ident,
        ident,
        Polygon(ring),
        role,
        properties,
    )


def explain(geometry: BaseGeometry) -> str:
    """Shapely's reason, its position said as latitude, longitude."""
    reason = explain_validity(geometry)
    what, _, rest = reason.partition("[")
    try:
        lon, lat = (float(v) for v in rest.rstrip("]").split())
    except ValueError:
        return reason
    return f"{what.strip().lower()} at {lat:.7f}, {lon:.7f}"


def select(shapes: Sequence[Shape], selector: str, what: str) -> list[Shape]:
    """The shapes a selector names: comma-separated numbers (the file's order), ids or names,
    ``KEY=VALUE`` properties (``KEY=*``: any value); ``none``; ``rest`` (all of them)."""
    chosen: dict[int, Shape] = {}
    for term in (t.strip() for t in selector.split(",")):
        if not term:
            continue
        if term == "none":
            continue
        if term == "rest":
            chosen.update((s.index, s) for s in shapes)
            continue
        matches = [s for s in shapes if _matches(s, term)]
        if not matches:
            raise FileRefused(f"{what} {term!r} matches nothing; the file has: {listing(shapes)}")
        chosen.update((s.index, s) for s in matches)
    return [chosen[i] for i in sorted(chosen)]


def listing(shapes: Iterable[Shape]) -> str:
    items = [s.describe() for s in shapes]
    more = f" and {len(items) - LISTED_MAX} more" if len(items) > LISTED_MAX else ""
    return "; ".join(items[:LISTED_MAX]) + more if items else "nothing usable"


def assemble_map(
    shapes: Sequence[Shape],
    options: MapOptions,
    fmt: str,
    *,
    name: str = "",
    bounds: tuple[float, float, float, float] | None = None,
    notes: Iterable[str] = (),
) -> MapImport:
    """The canonical map of the shapes (``bounds``: the file's stated south, west, north, east)."""
    notes = list(notes)
    polygons = [s for s in shapes if s.polygonal]
    if options.boundary and options.boundary_bbox:
        raise FileRefused("give --boundary or --boundary-bbox, not both")
    if options.boundary:
        chosen = select(polygons, options.boundary, "--boundary")
        boundary = combined_boundary(chosen, options.union)
        how = " (their union)" if options.union else " (their intersection)"
        notes.append(f"boundary: {_names(chosen)}" + (how if len(chosen) > 1 else ""))
    elif options.boundary_bbox:
        chosen = []
        boundary = _bbox(shapes, bounds)
        south, west, north, east = (
            boundary.bounds[1],
            boundary.bounds[0],
            boundary.bounds[3],
            boundary.bounds[2],
        )
        notes.append(
            f"boundary: the bounding box {south:.6f},{west:.6f} to {north:.6f},{east:.6f}"
            + (" (the file's stated bounds)" if bounds else "")
        )
    else:
        chosen = [s for s in polygons if s.role in ("boundary", "inclusion")]
        if not chosen and len(polygons) == 1 and polygons[0].role == "":
            chosen = polygons
            notes.append(f"boundary: {polygons[0].label}, the file's only polygon")
        if not chosen:
            raise FileRefused(
                "which polygon is the boundary? say --boundary SELECTOR (a number, id, name or "
                f"KEY=VALUE) or --boundary-bbox; the file has: {listing(shapes)}"
            )
        boundary = combined_boundary(chosen, options.union)
        if len(chosen) > 1:
            how = "union" if options.union else "intersection"
            notes.append(f"boundary: the {how} of {_names(chosen)}")
    rest = [s for s in polygons if s not in chosen]
    if options.keepouts:
        keepouts = select(rest, options.keepouts, "--keepouts")
    else:
        unknown = [s for s in rest if s.role in ("", "boundary", "inclusion")]
        if unknown:
            raise FileRefused(
                f"{_names(unknown)}: polygons without a role; say --keepouts rest (all of "
                "them), --keepouts none, or which (numbers, ids, names or KEY=VALUE)"
            )
        keepouts = [s for s in rest if s.role == "keepout"]
        others = [s for s in rest if s.role == "other"]
        if others:
            notes.append(
                f"{len(others)} other areas not used (choose them with --keepouts KEY=VALUE): "
                + _names(others)
            )
    features: list[dict[str, Any]] = [
        {
            "type": "Feature",
            "properties": {"role": "boundary", "name": name or _names(chosen) or "bounding box"},
            "geometry": plain_json(mapping(boundary)),
        }
    ]
    used: set[str] = set()
    for shape in keepouts:
        ident = _unique(shape.ident or shape.name or f"zone-{shape.index}", used)
        properties = {"role": "keepout"} | ({"name": shape.name} if shape.name else {})
        features.append(
            {
                "type": "Feature",
                "id": ident,
                "properties": properties,
                "geometry": plain_json(mapping(shape.geometry)),
            }
        )
    unnamed = 0
    names: set[str] = set()
    far: list[str] = []
    for shape in shapes:
        if shape.polygonal:
            continue
        if not shape.name:
            unnamed += 1
            continue
        point_name = _unique(shape.name, names)
        outside_m = _outside_m(boundary, shape.geometry)
        if outside_m > FAR_POINT_M:
            far.append(f"{point_name!r} {_distance_text(outside_m)}")
        features.append(
            {
                "type": "Feature",
                "properties": {"role": "point", "name": point_name},
                "geometry": plain_json(mapping(shape.geometry)),
            }
        )
    if unnamed:
        notes.append(f"{unnamed} points without a name not used (a named point needs a name)")
    if far:
        notes.append(
            "named points far outside the boundary (kept; a route cannot use them): "
            + ", ".join(far[:LISTED_MAX])
            + (f" and {len(far) - LISTED_MAX} more" if len(far) > LISTED_MAX else "")
        )
    return MapImport({"type": "FeatureCollection", "name": name, "features": features}, fmt, notes)


FAR_POINT_M = 1000.0
"""A named point further than this outside the boundary is said in a note (a typo'd
coordinate, or a point of another site)."""


def _outside_m(boundary: BaseGeometry, point: BaseGeometry) -> float:
    """About how far (metres) ``point`` lies outside ``boundary`` (0 inside), in the local
    frame of the boundary's own point."""
    if not isinstance(point, Point) or boundary.covers(point):
        return 0.0
    hull = boundary if isinstance(boundary, Polygon) else boundary.convex_hull
    if not isinstance(hull, Polygon):
        return 0.0
    anchor = hull.representative_point()
    frame = LocalFrame(anchor.y, anchor.x)
    ring = Polygon([frame.to_local(lat, lon) for lon, lat, *_ in hull.exterior.coords])
    return float(ring.distance(Point(frame.to_local(point.y, point.x))))


def _distance_text(metres: float) -> str:
    return f"{metres / 1000:.0f} km out" if metres >= 10_000 else f"{metres:.0f} m out"


def _names(shapes: Sequence[Shape]) -> str:
    return ", ".join(s.label for s in shapes[:LISTED_MAX]) + (
        f" and {len(shapes) - LISTED_MAX} more" if len(shapes) > LISTED_MAX else ""
    )


def _unique(base: str, used: set[str]) -> str:
    candidate, n = base, 1
    while candidate in used:
        n += 1
        candidate = f"{base}-{n}"
    used.add(candidate)
    return candidate


def combined_boundary(chosen: Sequence[Shape], union: bool) -> Polygon:
    """The boundary of several polygons: their intersection, or with ``union`` their union
    (one area: separate pieces are refused, naming them)."""
    if not union or len(chosen) < 2:
        return _intersection(chosen)
    merged = unary_union([shape.geometry for shape in chosen])
    if not isinstance(merged, Polygon):
        raise FileRefused(
            f"the union of {_names(chosen)} is {len(getattr(merged, 'geoms', []))} separate "
            "areas: a boundary is one (choose polygons that overlap or touch)"
        )
    return merged


def _intersection(chosen: Sequence[Shape]) -> Polygon:
    if not chosen:
        raise FileRefused("no boundary chosen")
    for shape in chosen:
        geometry = shape.geometry
        if isinstance(geometry, MultiPolygon) and len(geometry.geoms) > 1:
            raise FileRefused(
                f"{shape.label}: a boundary is one area, this MultiPolygon has "
                f"{len(geometry.geoms)} separate parts (choose one, or --boundary-bbox and the "
                "parts' gaps as keep-outs)"
            )
    area = intersection_all([s.geometry for s in chosen])
    if isinstance(area, MultiPolygon) and len(area.geoms) == 1:
        area = area.geoms[0]
    if area.is_empty or not isinstance(area, Polygon) or area.area == 0:
        raise FileRefused(
            f"the inclusion areas {_names(chosen)} do not overlap in one area "
            "(ArduPilot's rule: the robot may be where all of them overlap)"
        )
    return area


def _bbox(shapes: Sequence[Shape], bounds: tuple[float, float, float, float] | None) -> Polygon:
    if bounds is not None:
        south, west, north, east = bounds
        return box(west, south, east, north)
    if not shapes:
        raise FileRefused("--boundary-bbox: nothing in the file to bound")
    xs: list[float] = []
    ys: list[float] = []
    for shape in shapes:
        minx, miny, maxx, maxy = shape.geometry.bounds
        xs += [minx, maxx]
        ys += [miny, maxy]
    if max(xs) - min(xs) <= 0 or max(ys) - min(ys) <= 0:
        raise FileRefused("--boundary-bbox: the file's shapes have no extent")
    return box(min(xs), min(ys), max(xs), max(ys))


def _matches(shape: Shape, term: str) -> bool:
    if term.isdigit():
        return shape.index == int(term)
    key, equals, value = term.partition("=")
    if equals:
        if key in ("id", "name") and key not in shape.properties:
            return (shape.ident if key == "id" else shape.name) == value
        if key not in shape.properties:
            return False
        return value == "*" or str(shape.properties[key]) == value
    return term in (shape.ident, shape.name)


def _polygon(rings: Sequence[Ring], label: str) -> Polygon:
    if not rings:
        raise FileRefused(f"{label}: a polygon with no rings")
    closed: list[list[tuple[float, float]]] = []
    for n, ring in enumerate(rings):
        positions = [(float(lon), float(lat)) for lon, lat in ring]
        for lon, lat in positions:
            check_position(lon, lat, label)
        if positions and positions[0] != positions[-1]:
            positions.append(positions[0])
        if len(set(positions)) < 3:
            raise FileRefused(f"{label}: ring {n} has fewer than 3 corners")
        closed.append(positions)
    from brasidas.autonomy.areamap import local_polygon

    first_lon, first_lat = closed[0][0]
    _local, problem = local_polygon(closed, LocalFrame(first_lat, first_lon))
    if problem:
        raise FileRefused(f"{label}: {problem}")
    return Polygon(closed[0], closed[1:])


def plain_json(value: Any) -> Any:
    """Shapely's mapping() as JSON: lists for tuples, degrees to 1e-8 (a millimetre: no
    23.652500000000003 in what is sent)."""
    if isinstance(value, tuple | list):
        return [plain_json(v) for v in value]
    if isinstance(value, dict):
        return {k: plain_json(v) for k, v in value.items()}
    if isinstance(value, float):
        return round(value, 8)
    return value
