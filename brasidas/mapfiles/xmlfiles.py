"""KML (Google Earth, QGroundControl's geofence import) and OpenStreetMap exports (``.osm`` XML,
Overpass JSON): polygons, named points, routes (KML LineStrings). Sans-IO.

XML is parsed by the standard library after refusing any document type declaration: entities
(the "billion laughs") and external references cannot be declared, so a hostile file is
refused before it can grow, and the caller bounds the file's size.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from shapely import Polygon
from shapely.errors import GEOSException

from brasidas.mapfiles.errors import FileRefused
from brasidas.mapfiles.shapes import Shape, check_position, multipolygon_shape, polygon_shape


def parse_xml(text: str, what: str) -> ET.Element:
    """The root element; refuses DTDs and entities."""
    if "<!DOCTYPE" in text or "<!ENTITY" in text:
        raise FileRefused(f"{what}: document type declarations and entities are refused")
    try:
        return ET.fromstring(text)
    except ET.ParseError as exc:
        raise FileRefused(f"{what}: not well-formed XML: {exc}") from None


def local(tag: str) -> str:
    """The tag without its namespace (KML 2.1, 2.2, gx: all read the same)."""
    return tag.rsplit("}", 1)[-1]


# ---------------------------------------------------------------------------- KML


def kml_shapes(root: ET.Element) -> tuple[list[Shape], list[list[tuple[float, float]]], list[str]]:
    """A KML document's placemarks: polygons and named points as shapes, LineStrings as
    routes ((lat, lon) lists), and notes."""
    shapes: list[Shape] = []
    lines: list[list[tuple[float, float]]] = []
    notes: list[str] = []
    for number, placemark in enumerate(_descendants(root, "Placemark")):
        name = _child_text(placemark, "name")
        ident = placemark.get("id", "") or name
        label = f"KML placemark {number}" + (f" ({name!r})" if name else "")
        polygons = []
        for geometry in _geometries(placemark):
            kind = local(geometry.tag)
            if kind == "Polygon":
                polygons.append(_kml_polygon(geometry, label))
            elif kind == "Point":
                positions = _coordinates(geometry, label)
                if not positions:
                    raise FileRefused(f"{label}: a Point with no coordinates")
                lon, lat = positions[0]
                shapes.append(Shape.point(label, len(shapes), name, lat, lon))
            elif kind == "LineString":
                lines.append([(lat, lon) for lon, lat in _coordinates(geometry, label)])
            else:
                notes.append(f"{label}: a {kind} is not used")
        if len(polygons) == 1:
            shapes.append(polygon_shape(label, len(shapes), polygons[0], ident=ident, name=name))
        elif polygons:
            shapes.append(multipolygon_shape(label, len(shapes), polygons, ident=ident, name=name))
    return shapes, lines, notes


def _descendants(root: ET.Element, name: str) -> Iterator[ET.Element]:
    return (element for element in root.iter() if local(element.tag) == name)


def _child_text(element: ET.Element, name: str) -> str:
    for child in element:
        if local(child.tag) == name:
            return (child.text or "").strip()
    return ""


def _geometries(placemark: ET.Element) -> Iterator[ET.Element]:
    for child in placemark:
        kind = local(child.tag)
        if kind == "MultiGeometry":
            yield from _geometries(child)
        elif kind in ("Polygon", "Point", "LineString", "LinearRing", "Model", "Track"):
            yield child


def _kml_polygon(polygon: ET.Element, label: str) -> list[list[tuple[float, float]]]:
    outer: list[list[tuple[float, float]]] = []
    inner: list[list[tuple[float, float]]] = []
    for child in polygon:
        kind = local(child.tag)
        if kind in ("outerBoundaryIs", "innerBoundaryIs"):
            for ring in child:
                if local(ring.tag) == "LinearRing":
                    (outer if kind == "outerBoundaryIs" else inner).append(
                        _coordinates(ring, label)
                    )
    if len(outer) != 1:
        raise FileRefused(f"{label}: a Polygon needs one outerBoundaryIs ring")
    return outer + inner


def _coordinates(element: ET.Element, label: str) -> list[tuple[float, float]]:
    """``lon,lat[,alt]`` tuples separated by white space."""
    text = ""
    for child in element.iter():
        if local(child.tag) == "coordinates":
            text = child.text or ""
            break
    positions = []
    for item in text.split():
        fields = item.split(",")
        try:
            lon, lat = float(fields[0]), float(fields[1])
        except (ValueError, IndexError):
            raise FileRefused(f"{label}: {item[:40]!r} is not lon,lat[,alt]") from None
        check_position(lon, lat, label)
        positions.append((lon, lat))
    return positions


# ---------------------------------------------------------------------------- OpenStreetMap


def osm_xml_shapes(
    root: ET.Element,
) -> tuple[list[Shape], tuple[float, float, float, float] | None, list[str]]:
    """An ``.osm`` export: closed ways as polygons (buildings: keep-outs), its bounds."""
    nodes: dict[str, tuple[float, float]] = {}
    ways: list[tuple[str, list[str], dict[str, str]]] = []
    bounds = None
    relations: list[Relation] = []
    for element in root:
        kind = local(element.tag)
        if kind == "bounds":
            try:
                bounds = tuple(
                    float(element.get(k, "")) for k in ("minlat", "minlon", "maxlat", "maxlon")
                )
            except ValueError:
                raise FileRefused("the <bounds> element is not numbers") from None
        elif kind == "node":
            try:
                nodes[element.get("id", "")] = (
                    float(element.get("lat", "")),
                    float(element.get("lon", "")),
                )
            except ValueError:
                raise FileRefused(f"node {element.get('id')}: lat and lon are numbers") from None
        elif kind == "way":
            refs = [nd.get("ref", "") for nd in element if local(nd.tag) == "nd"]
            tags = {t.get("k", ""): t.get("v", "") for t in element if local(t.tag) == "tag"}
            ways.append((element.get("id", ""), refs, tags))
        elif kind == "relation":
            members = [
                Member(m.get("type", ""), m.get("ref", ""), m.get("role", ""), None)
                for m in element
                if local(m.tag) == "member"
            ]
            tags = {t.get("k", ""): t.get("v", "") for t in element if local(t.tag) == "tag"}
            relations.append(Relation(element.get("id", ""), members, tags))
    geometries = []
    cut: list[str] = []
    for way_id, refs, tags in ways:
        missing = [r for r in refs if r not in nodes]
        if missing:
            cut.append(_cut_way(way_id, missing[0], tags))
            continue
        geometries.append((way_id, [(nodes[r][1], nodes[r][0]) for r in refs], tags, refs))
    shapes, notes = _osm_ways(geometries)
    notes.extend(_cut_ways_note(cut))
    _osm_relations(relations, {g[0]: g[1] for g in geometries}, shapes, notes)
    south_west_north_east = None
    if bounds is not None:
        south, west, north, east = bounds
        south_west_north_east = (south, west, north, east)
    return shapes, south_west_north_east, notes


def is_overpass(data: Any) -> bool:
    return isinstance(data, Mapping) and isinstance(data.get("elements"), list)


def overpass_shapes(
    data: Mapping[str, Any],
) -> tuple[list[Shape], tuple[float, float, float, float] | None, list[str]]:
    """Overpass API JSON (``out geom`` or nodes and ways)."""
    nodes: dict[str, tuple[float, float]] = {}
    raw_ways = []
    relations: list[Relation] = []
    for element in data["elements"]:
        if not isinstance(element, Mapping):
            raise FileRefused("an Overpass element is not an object")
        kind = element.get("type")
        if kind == "node":
            lat, lon = element.get("lat"), element.get("lon")
            if isinstance(lat, int | float) and isinstance(lon, int | float):
                nodes[str(element.get("id"))] = (float(lat), float(lon))
        elif kind == "way":
            raw_ways.append(element)
        elif kind == "relation":
            relations.append(_overpass_relation(element))
    geometries = []
    cut: list[str] = []
    for way in raw_ways:
        way_id = str(way.get("id"))
        raw_tags = way.get("tags")
        tags: Mapping[str, Any] = raw_tags if isinstance(raw_tags, Mapping) else {}
        refs = [str(r) for r in way.get("nodes", [])] if isinstance(way.get("nodes"), list) else []
        geometry = way.get("geometry")
        if isinstance(geometry, list):
            try:
                positions = [(float(p["lon"]), float(p["lat"])) for p in geometry]
            except (TypeError, KeyError, ValueError):
                raise FileRefused(f"way {way_id}: geometry is a list of {{lat, lon}}") from None
        else:
            missing = [r for r in refs if r not in nodes]
            if missing:
                cut.append(_cut_way(way_id, missing[0], {str(k): str(v) for k, v in tags.items()}))
                continue
            positions = [(nodes[r][1], nodes[r][0]) for r in refs]
        closed_refs = refs if refs else [str(p) for p in positions]
        geometries.append(
            (way_id, positions, {str(k): str(v) for k, v in tags.items()}, closed_refs)
        )
    shapes, notes = _osm_ways(geometries)
    notes.extend(_cut_ways_note(cut))
    _osm_relations(relations, {g[0]: g[1] for g in geometries}, shapes, notes)
    bounds = None
    raw_bounds = data.get("bounds")
    if isinstance(raw_bounds, Mapping):
        try:
            bounds = (
                float(raw_bounds["minlat"]),
                float(raw_bounds["minlon"]),
                float(raw_bounds["maxlat"]),
                float(raw_bounds["maxlon"]),
            )
        except (KeyError, TypeError, ValueError):
            raise FileRefused("'bounds' has minlat, minlon, maxlat, maxlon") from None
    return shapes, bounds, notes


CUT_WAYS_NAMED = 5
"""Ways cut at an export's edge named in the note (the rest counted)."""


def _cut_way(way_id: str, node: str, tags: Mapping[str, str]) -> str:
    kind = next((f"{k}={tags[k]}" for k in ("building", "highway", "boundary") if k in tags), "")
    return f"way {way_id}" + (f" ({kind})" if kind else "") + f": node {node} not in the file"


def _cut_ways_note(cut: list[str]) -> list[str]:
    """A box export cuts the ways crossing its edge (their nodes outside it are not in the
    file): each is left out, and said, whatever it is (a building cut there is not a keep-out
    of this map)."""
    if not cut:
        return []
    named = "; ".join(cut[:CUT_WAYS_NAMED])
    more = f"; and {len(cut) - CUT_WAYS_NAMED} more" if len(cut) > CUT_WAYS_NAMED else ""
    return [f"{len(cut)} ways cut at the export's edge left out: {named}{more}"]


@dataclass(frozen=True)
class Member:
    kind: str
    ref: str
    role: str
    positions: list[tuple[float, float]] | None
    """Its geometry when the file has it (Overpass ``out geom``), else found by ``ref``."""


@dataclass(frozen=True)
class Relation:
    ident: str
    members: list[Member]
    tags: Mapping[str, str]


def _overpass_relation(element: Mapping[str, Any]) -> Relation:
    ident = str(element.get("id"))
    raw_tags = element.get("tags")
    tags = {str(k): str(v) for k, v in raw_tags.items()} if isinstance(raw_tags, Mapping) else {}
    members = []
    raw_members = element.get("members")
    for member in raw_members if isinstance(raw_members, list) else []:
        if not isinstance(member, Mapping):
            raise FileRefused(f"relation {ident}: a member is not an object")
        geometry = member.get("geometry")
        positions = None
        if isinstance(geometry, list):
            try:
                positions = [(float(p["lon"]), float(p["lat"])) for p in geometry]
            except (TypeError, KeyError, ValueError):
                raise FileRefused(f"relation {ident}: member geometry is {{lat, lon}}s") from None
        members.append(
            Member(
                str(member.get("type", "")),
                str(member.get("ref", "")),
                str(member.get("role", "")),
                positions,
            )
        )
    return Relation(ident, members, tags)


def _osm_relations(
    relations: Sequence[Relation],
    ways: Mapping[str, list[tuple[float, float]]],
    shapes: list[Shape],
    notes: list[str],
) -> None:
    """Multipolygon relations (large buildings, courtyards): their outer and inner ways joined
    into rings; one whose ways are not all in the file, or do not close, is named in a note."""
    others = 0
    for relation in relations:
        if relation.tags.get("type") != "multipolygon":
            others += 1
            continue
        name = relation.tags.get("name", "")
        building = "building" in relation.tags
        label = (
            f"relation {relation.ident}"
            + (f" ({name!r})" if name else "")
            + (" (building)" if building else "")
        )
        outer: list[list[tuple[float, float]]] = []
        inner: list[list[tuple[float, float]]] = []
        missing = []
        for member in relation.members:
            if member.kind != "way":
                continue
            positions = member.positions or ways.get(member.ref)
            if not positions:
                missing.append(member.ref)
                continue
            (inner if member.role == "inner" else outer).append(positions)
        outer_rings = _join_rings(outer)
        inner_rings = _join_rings(inner)
        if missing or outer_rings is None or inner_rings is None or not outer_rings:
            why = f"way {missing[0]} is not in the file" if missing else "its ways do not close"
            notes.append(f"{label} not used: {why} (draw it as a keep-out)")
            continue
        try:
            polygons = [
                [ring, *(hole for hole in inner_rings if Polygon(ring).covers(Polygon(hole)))]
                for ring in outer_rings
            ]
        except GEOSException as exc:
            raise FileRefused(f"{label}: its rings are not polygons ({exc})") from None
        shape = polygon_shape if len(polygons) == 1 else multipolygon_shape
        arguments: Any = polygons[0] if len(polygons) == 1 else polygons
        shapes.append(
            shape(
                label,
                len(shapes),
                arguments,
                role="keepout" if building else "other",
                ident=f"relation/{relation.ident}",
                name=name,
                properties=dict(relation.tags),
            )
        )
    if others:
        notes.append(f"{others} relations other than multipolygons not used")


def _join_rings(
    segments: list[list[tuple[float, float]]],
) -> list[list[tuple[float, float]]] | None:
    """Ways joined end to end (either direction) into closed rings; None when one stays open."""
    pending = [list(segment) for segment in segments if len(segment) >= 2]
    rings = []
    while pending:
        ring = pending.pop(0)
        while ring[0] != ring[-1]:
            for index, segment in enumerate(pending):
                if segment[0] == ring[-1]:
                    ring += segment[1:]
                elif segment[-1] == ring[-1]:
                    ring += segment[-2::-1]
                else:
                    continue
                del pending[index]
                break
            else:
                return None
        if len(ring) < 4:
            return None
        rings.append(ring)
    return rings


def _osm_ways(
    ways: Sequence[tuple[str, list[tuple[float, float]], Mapping[str, str], list[str]]],
) -> tuple[list[Shape], list[str]]:
    shapes: list[Shape] = []
    open_ways = 0
    for way_id, positions, tags, refs in ways:
        if len(refs) < 4 or refs[0] != refs[-1]:
            open_ways += 1
            continue
        name = tags.get("name", "")
        building = "building" in tags
        label = (
            f"way {way_id}" + (f" ({name!r})" if name else "") + (" (building)" if building else "")
        )
        shapes.append(
            polygon_shape(
                label,
                len(shapes),
                [positions],
                role="keepout" if building else "other",
                ident=f"way/{way_id}",
                name=name,
                properties=dict(tags),
            )
        )
    notes = [f"{open_ways} open ways (roads, paths) not used"] if open_ways else []
    return shapes, notes
