"""Sizes that must agree end to end: the CLI, the station's local API, the platform's signaling.

A map or a route travels CLI → station (local API, HTTP) → platform (signaling, WebSocket) in
one JSON-RPC request. Each hop accepts at least :data:`MAP_REQUEST_MAX_BYTES` from an
authenticated caller (the station's local API is loopback-only; the platform's signaling
default ``signaling.max_request_bytes`` is this constant), and the CLI refuses a larger request
before sending it, saying its size and this limit. A change here changes every hop.
"""

from __future__ import annotations

MAP_REQUEST_MAX_BYTES = 4 * 1024 * 1024
"""The largest map or route request (JSON-RPC envelope included): 4 MiB, about 60,000
vertices of an OSM export with its properties; the map's vertex cap
(:data:`brasidas.autonomy.areamap.MAX_VERTICES`) bounds what the platform plans on first."""

FILE_MAX_BYTES = MAP_REQUEST_MAX_BYTES
"""The largest map or route file the station reads (CLI and console imports)."""

STATION_API_MAX_BYTES = 2 * FILE_MAX_BYTES + 65536
"""The station's local API takes a file's text as a JSON string (its tabs, newlines and quotes
escaped: up to twice as long) and the call around it (``map_import``, ``route_import``)."""

ANSWER_MAX_BYTES = 2 * MAP_REQUEST_MAX_BYTES
"""The largest answer a station reads from a platform (``get_map`` sends the map back)."""

MAP_MAX_VERTICES = 20_000
"""A map's vertices, all polygons together: bounds the planner's build (its graph grows with
the square of the keep-outs' corners) and the platform's memory. Counted in a file's (or a
request's) text before it is parsed, and exactly after."""

ROUTE_MAX_WAYPOINTS = 1000
"""A route's waypoints."""
