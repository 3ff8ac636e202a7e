"""Counting a map or route file's vertices and items in its text, before parsing it
(issue 26, defects 3 and 4): a 150,001-vertex boundary or a 25,000-item plan is refused for
the price of a scan, not seconds of parsing and geometry with the GIL held.

The counts are upper bounds (every JSON array that starts with a number, every KML
coordinate tuple, every OSM node reference, every line of a text file): a file under them
is then parsed and held to the exact limits.
"""

from __future__ import annotations

import re
import time

from brasidas.limits import MAP_MAX_VERTICES, ROUTE_MAX_WAYPOINTS
from brasidas.mapfiles.errors import MAX_FILE_BYTES, FileRefused

MAX_PLAN_ITEMS = 2 * ROUTE_MAX_WAYPOINTS
"""Mission items a route file may hold (commands besides waypoints: speed changes, jumps)."""

JSON_POSITION = re.compile(r"\[(?=\s*[-+0-9.])")
"""An array that starts with a number: a GeoJSON position, a plan item's params, a bbox."""
KML_COORDINATES = re.compile(r"<(?:\w+:)?coordinates\b[^>]*>([^<]*)<", re.IGNORECASE)
XML_POINT = re.compile(r"<(?:\w+:)?(?:nd|node|rtept|trkpt|wpt|gx:coord)\b", re.IGNORECASE)
PLAN_ITEM = re.compile(r'"command"\s*:')
ESCAPED_PLAN_ITEM = re.compile(r'\\"command\\"\s*:')
"""A plan item's ``command`` inside a request, the file being a JSON string there."""
FILENAME = re.compile(r'"filename"\s*:\s*"([^"\\]{0,200})"')
TUPLE = re.compile(r"\S+")
"""A KML coordinate tuple (``lon,lat[,alt]``, separated by whitespace)."""
AFTER_COMMA = re.compile(",")
AFTER_TAG = re.compile(">")
AFTER_SPACE = re.compile(r"\s")
SCAN_CHUNK = 64 * 1024
"""Characters scanned at a time: the matches of one scan stay small (a 150,001-vertex file
costs no 150,001-item list), and between scans the worker thread hands the GIL over."""


def positions_in(body: str) -> int:
    """An upper bound of the vertices (or waypoints) in a map or route file's text."""
    if body.startswith("<"):
        tuples = sum(
            _count(TUPLE, body, AFTER_SPACE, *block.span(1))
            for block in KML_COORDINATES.finditer(body)
        )
        return tuples + _count(XML_POINT, body, AFTER_TAG)
    if body.startswith(("{", "[")):
        return _count(JSON_POSITION, body, AFTER_COMMA)
    return body.count("\n") + 1


def plan_items_in(body: str) -> int:
    """An upper bound of a QGC plan's mission items (each has a ``command``)."""
    return _count(PLAN_ITEM, body, AFTER_COMMA)


def _count(
    pattern: re.Pattern[str], body: str, boundary: re.Pattern[str], start: int = 0, end: int = -1
) -> int:
    """Matches of ``pattern`` in ``body[start:end]``, scanned a chunk at a time without a copy;
    each chunk ends just after a ``boundary`` character, which no match spans."""
    end = len(body) if end < 0 else end
    total = 0
    while start < end:
        cut = boundary.search(body, min(start + SCAN_CHUNK, end), end)
        stop = cut.end() if cut is not None else end
        total += len(pattern.findall(body, start, stop))
        start = stop
        # The GIL to whoever waits for it (the event loop's thread) now, not after the
        # interpreter's switch interval (5 ms): one chunk's scan is a fraction of that.
        time.sleep(0)
    return total


def map_request_refusal(request: str) -> str | None:
    """A ``map_import`` request's text, unparsed (the file inside it as a JSON string): why
    it is refused, or None. Counted as :func:`positions_in` counts a file (a tuple or an item
    its escaping hides is not counted: the exact limits apply once it is parsed)."""
    count = _positions_anywhere(request)
    if count <= MAP_MAX_VERTICES:
        return None
    return (
        f"map refused: {_filename(request)}the map: about {count} vertices, more than "
        f"{MAP_MAX_VERTICES} (not read)"
    )


def route_request_refusal(request: str) -> str | None:
    """A ``route_import`` request's text, unparsed: why it is refused, or None."""
    items = _count(ESCAPED_PLAN_ITEM, request, AFTER_COMMA)
    if items > MAX_PLAN_ITEMS:
        return (
            f"waypoints refused: {_filename(request)}{items} mission items, more than "
            f"{MAX_PLAN_ITEMS} (not read)"
        )
    count = _positions_anywhere(request)
    if count <= MAP_MAX_VERTICES + MAX_PLAN_ITEMS:
        return None
    return (
        f"waypoints refused: {_filename(request)}the route: about {count} waypoints, more "
        f"than {MAP_MAX_VERTICES + MAX_PLAN_ITEMS} (not read)"
    )


def _positions_anywhere(text: str) -> int:
    tuples = sum(
        _count(TUPLE, text, AFTER_SPACE, *block.span(1)) for block in KML_COORDINATES.finditer(text)
    )
    return _count(JSON_POSITION, text, AFTER_COMMA) + tuples + _count(XML_POINT, text, AFTER_TAG)


def _filename(request: str) -> str:
    """``NAME: `` for the request's ``filename`` (the operator's command sends it last)."""
    found = FILENAME.search(request, max(0, len(request) - 1024))
    return f"{found[1]}: " if found is not None and found[1] else ""


def map_text(text: str) -> str:
    """A map file's text, stripped, or FileRefused when it is too large or holds too many
    vertices (counted, not parsed: a refused file never loads the parsers or Shapely)."""
    body = file_body(text)
    check_positions(body, MAP_MAX_VERTICES, "the map")
    return body


def route_text(text: str) -> str:
    """A route file's text, stripped, or FileRefused (too large, too many mission items or
    positions), counted without parsing it."""
    body = file_body(text)
    plan_items = plan_items_in(body) if body.startswith("{") else 0
    if plan_items > MAX_PLAN_ITEMS:
        raise FileRefused(f"{plan_items} mission items, more than {MAX_PLAN_ITEMS} (not read)")
    # A plan's fence (or a KML's other shapes) may add a map's worth of vertices.
    check_positions(body, MAP_MAX_VERTICES + MAX_PLAN_ITEMS, "the route")
    return body


def file_body(text: str) -> str:
    """A file's text without its byte-order mark and surrounding blanks; FileRefused when too
    large or a zip archive."""
    if len(text) > MAX_FILE_BYTES:
        raise FileRefused(f"the file is larger than {MAX_FILE_BYTES // (1024 * 1024)} MiB")
    if text.startswith("PK\x03\x04"):
        raise FileRefused("a zip archive (a KMZ?): unzip it and give the .kml inside")
    return text.lstrip("\ufeff").strip()


def check_positions(body: str, limit: int, what: str) -> None:
    """Refuse a file with more than ``limit`` vertices (or waypoints), counted unparsed."""
    count = positions_in(body)
    if count > limit:
        raise FileRefused(f"{what}: about {count} {_noun(what)}, more than {limit} (not read)")


def _noun(what: str) -> str:
    return "waypoints" if "route" in what else "vertices"
