"""Counting a map or route file's vertices and items in its text, before parsing it
(issue 26, defects 3 and 4): a 150,001-vertex boundary or a 25,000-item plan is refused for
the price of a scan, not seconds of parsing and geometry with the GIL held.

The counts are upper bounds (every JSON array that starts with a number, every KML
coordinate tuple, every OSM node reference, every line of a text file): a file under them
is then parsed and held to the exact limits.
"""

from __future__ import annotations

import re

from brasidas.mapfiles.errors import FileRefused

JSON_POSITION = re.compile(rb"\[\s*[-+0-9.]")
"""An array that starts with a number: a GeoJSON position, a plan item's params, a bbox."""
KML_COORDINATES = re.compile(r"<(?:\w+:)?coordinates\b[^>]*>([^<]*)<", re.IGNORECASE)
XML_POINT = re.compile(r"<(?:\w+:)?(?:nd|node|rtept|trkpt|wpt|gx:coord)\b", re.IGNORECASE)
PLAN_ITEM = re.compile(rb'"command"\s*:')


def positions_in(body: str) -> int:
    """An upper bound of the vertices (or waypoints) in a map or route file's text."""
    if body.startswith("<"):
        tuples = sum(len(block.split()) for block in KML_COORDINATES.findall(body))
        return tuples + len(XML_POINT.findall(body))
    if body.startswith(("{", "[")):
        return len(JSON_POSITION.findall(body.encode("utf-8", "surrogatepass")))
    return body.count("\n") + 1


def plan_items_in(body: str) -> int:
    """An upper bound of a QGC plan's mission items (each has a ``command``)."""
    return len(PLAN_ITEM.findall(body.encode("utf-8", "surrogatepass")))


def check_positions(body: str, limit: int, what: str) -> None:
    """Refuse a file with more than ``limit`` vertices (or waypoints), counted unparsed."""
    count = positions_in(body)
    if count > limit:
        raise FileRefused(f"{what}: about {count} {_noun(what)}, more than {limit} (not read)")


def _noun(what: str) -> str:
    return "waypoints" if "route" in what else "vertices"
