"""GeoJSON as users have it: a FeatureCollection with or without our ``role`` properties, one
Feature, a bare geometry; Polygons, MultiPolygons and named Points (RFC 7946, lon/lat)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from brasidas.mapfiles.errors import FileRefused
from brasidas.mapfiles.shapes import Shape, check_position, multipolygon_shape, polygon_shape

GEOMETRIES = ("Point", "MultiPoint", "LineString", "MultiLineString", "Polygon", "MultiPolygon")


MAX_INTEGER_DIGITS = 20
"""Longer integers are refused (64-bit ids fit; no coordinate needs more)."""


def loads(text: str, what: str) -> Any:
    """JSON, refusing NaN and Infinity (not JSON, and never a position)."""

    def constant(name: str) -> Any:
        raise FileRefused(f"{what}: {name} is not a number JSON allows")

    def integer(digits: str) -> int:
        # A 4,000-digit integer is no coordinate: refused here, not an OverflowError later.
        if len(digits) > MAX_INTEGER_DIGITS:
            raise FileRefused(f"{what}: a number of {len(digits)} digits")
        return int(digits)

    try:
        value = json.loads(text, parse_constant=constant, parse_int=integer)
    except RecursionError:
        raise FileRefused(f"{what}: nested too deeply") from None
    except ValueError as exc:
        if isinstance(exc, FileRefused):
            raise
        raise FileRefused(f"{what}: not JSON: {exc}") from None
    return value


def is_geojson(data: Any) -> bool:
    return isinstance(data, Mapping) and data.get("type") in (
        "FeatureCollection",
        "Feature",
        "GeometryCollection",
        *GEOMETRIES,
    )


def geojson_shapes(data: Mapping[str, Any]) -> tuple[list[Shape], list[str], str]:
    """The shapes of a GeoJSON object, notes on what was left aside, and its name."""
    kind = data.get("type")
    notes: list[str] = []
    shapes: list[Shape] = []
    _check_crs(data.get("crs"))
    if kind == "FeatureCollection":
        features = data.get("features")
        if not isinstance(features, list):
            raise FileRefused("a FeatureCollection needs a 'features' list")
        for index, feature in enumerate(features):
            _feature(feature, index, f"feature {index}", shapes, notes)
        name = data.get("name", "")
        return shapes, notes, name if isinstance(name, str) else ""
    if kind == "Feature":
        _feature(data, 0, "the feature", shapes, notes)
        return shapes, notes, ""
    if kind == "GeometryCollection":
        geometries = data.get("geometries")
        if not isinstance(geometries, list):
            raise FileRefused("a GeometryCollection needs a 'geometries' list")
        for index, geometry in enumerate(geometries):
            _geometry(geometry, index, f"geometry {index}", {}, shapes, notes)
        return shapes, notes, ""
    _geometry(data, 0, f"the {kind}", {}, shapes, notes)
    return shapes, notes, ""


WGS84_NAMES = ("CRS84", "EPSG::4326", "EPSG:4326", "WGS84")


def _check_crs(crs: Any) -> None:
    """The 2008 GeoJSON's ``crs`` member: only WGS-84 longitude, latitude is read."""
    if crs is None:
        return
    properties = crs.get("properties") if isinstance(crs, Mapping) else None
    name = properties.get("name") if isinstance(properties, Mapping) else None
    if not isinstance(name, str) or not name.upper().endswith(WGS84_NAMES):
        raise FileRefused(
            f"coordinates in {name or crs!r}: only WGS-84 longitude, latitude (CRS84) is read; "
            "export the file as EPSG:4326"
        )


def _feature(feature: Any, index: int, where: str, shapes: list[Shape], notes: list[str]) -> None:
    if not isinstance(feature, Mapping) or feature.get("type") != "Feature":
        raise FileRefused(f"{where}: not a GeoJSON Feature")
    properties = feature.get("properties")
    properties = dict(properties) if isinstance(properties, Mapping) else {}
    name = properties.get("name")
    fid = feature.get("id")
    label = where + (f" ({name!r})" if isinstance(name, str) and name else "")
    if isinstance(fid, str | int) and not isinstance(fid, bool):
        properties.setdefault("id", str(fid))
    _geometry(feature.get("geometry"), index, label, properties, shapes, notes)


def _geometry(
    geometry: Any,
    index: int,
    label: str,
    properties: dict[str, Any],
    shapes: list[Shape],
    notes: list[str],
) -> None:
    if not isinstance(geometry, Mapping):
        notes.append(f"{label}: no geometry, not used")
        return
    kind = geometry.get("type")
    coordinates = geometry.get("coordinates")
    name = properties.get("name")
    name = name if isinstance(name, str) else ""
    ident = str(properties.get("id", "")) or name
    role = properties.get("role", "")
    role = role if isinstance(role, str) else ""
    if role not in ("", "boundary", "keepout", "point"):
        raise FileRefused(f"{label}: unknown role {role!r} (boundary, keepout or point)")
    at = len(shapes)
    if kind == "Polygon":
        shapes.append(
            polygon_shape(
                label,
                at,
                _rings(coordinates, label),
                role=role,
                ident=ident,
                name=name,
                properties=properties,
            )
        )
    elif kind == "MultiPolygon":
        if not isinstance(coordinates, list):
            raise FileRefused(f"{label}: a MultiPolygon's coordinates are a list of polygons")
        shapes.append(
            multipolygon_shape(
                label,
                at,
                [_rings(polygon, label) for polygon in coordinates],
                role=role,
                ident=ident,
                name=name,
                properties=properties,
            )
        )
    elif kind == "Point":
        lon, lat = _position(coordinates, label)
        shapes.append(Shape.point(label, at, name, lat, lon, properties))
    elif kind in GEOMETRIES:
        notes.append(f"{label}: a {kind} is not part of a map, not used")
    else:
        raise FileRefused(f"{label}: {kind!r} is not a GeoJSON geometry")


def _rings(value: Any, label: str) -> list[list[tuple[float, float]]]:
    if not isinstance(value, list) or not value:
        raise FileRefused(f"{label}: a polygon's coordinates are a list of rings")
    rings = []
    for ring in value:
        if not isinstance(ring, list):
            raise FileRefused(f"{label}: a ring is a list of positions")
        rings.append([_position(p, label) for p in ring])
    return rings


def _position(position: Any, label: str) -> tuple[float, float]:
    if (
        not isinstance(position, list)
        or len(position) not in (2, 3)
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in position)
    ):
        raise FileRefused(f"{label}: a position is [longitude, latitude]")
    lon, lat = float(position[0]), float(position[1])
    check_position(lon, lat, label)
    return lon, lat
