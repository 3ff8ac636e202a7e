"""QGroundControl and ArduPilot mission files: ``QGC WPL 110`` (``.waypoints``; also fence and
rally files), QGC ``.plan`` (JSON), ArduPilot's older fence (``lat lon`` per line) and rally
(``RALLY`` lines) files. Sans-IO: text in, mission items and shapes out; and back.

Formats as documented by mavlink.io ("File formats") and QGC's developer guide ("Plan file
format").
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

from brasidas.autonomy.route import MAX_WAYPOINTS
from brasidas.mapfiles.errors import FileRefused
from brasidas.mapfiles.mission import (
    MissionItem,
    MissionRoute,
    fence_shapes,
    mission_items,
    route_from_items,
)
from brasidas.mapfiles.shapes import Shape, check_position, circle, polygon_shape

WPL_HEADER = "QGC WPL 110"
PLAN_VEHICLE_ROVER = 10
"""MAV_TYPE_GROUND_ROVER."""
PLAN_FIRMWARE_GENERIC = 0
"""MAV_AUTOPILOT_GENERIC: we are not ArduPilot or PX4."""


# ---------------------------------------------------------------------------- WPL 110


def is_wpl(text: str) -> bool:
    return text.lstrip("\ufeff").lstrip().startswith("QGC WPL")


def wpl_items(text: str) -> list[MissionItem]:
    """The rows of a ``QGC WPL 110`` file: INDEX CURRENT FRAME COMMAND P1-P4 LAT LON ALT
    AUTOCONTINUE, tab-separated (spaces are read too; ``#`` lines are comments)."""
    lines = text.lstrip("\ufeff").splitlines()
    header = lines[0].strip() if lines else ""
    if header != WPL_HEADER:
        raise FileRefused(f"line 1: {header[:40]!r} is not {WPL_HEADER!r}")
    items: list[MissionItem] = []
    for number, line in enumerate(lines[1:], start=2):
        fields = line.split()
        if not fields or fields[0].startswith("#"):  # pymavlink writes comments
            continue
        where = f"line {number}"
        if len(fields) != 12:
            raise FileRefused(f"{where}: {len(fields)} fields, a {WPL_HEADER} row has 12")
        try:
            index, _current, frame, command = (int(v) for v in fields[:4])
            p1, p2, p3, p4, lat, lon, alt = (float(v) for v in fields[4:11])
        except ValueError:
            raise FileRefused(f"{where}: not a row of numbers") from None
        if index > MAX_WAYPOINTS:
            raise FileRefused(f"{where}: more than {MAX_WAYPOINTS} items")
        if index != len(items):
            raise FileRefused(f"{where}: sequence {index}, expected {len(items)}")
        items.append(
            MissionItem(f"row {index} ({where})", command, frame, (p1, p2, p3, p4), lat, lon, alt)
        )
    if not items:
        raise FileRefused("no rows after the header")
    return items


def wpl_route(text: str, *, skip_unsupported: bool = False) -> MissionRoute:
    """A ``.waypoints`` mission: row 0 is home, the rest waypoints (a DO_JUMP's param1 is a
    sequence number)."""
    items = wpl_items(text)

    def target(item: MissionItem) -> int | None:
        seq = item.params[0]
        return int(seq) if math.isfinite(seq) and 0 <= seq < len(items) else None

    return route_from_items(
        items, home_first=True, jump_target=target, skip_unsupported=skip_unsupported
    )


def wpl_shapes(text: str) -> list[Shape]:
    """A ``QGC WPL 110`` fence or rally file as shapes."""
    return fence_shapes(wpl_items(text))


def wpl_text(
    route: Sequence[tuple[float, float]], home: tuple[float, float], laps: int | None = None
) -> str:
    """A route as ``QGC WPL 110``: row 0 home, then NAV_WAYPOINT rows (relative altitude 0)."""
    rows = [WPL_HEADER]
    for index, item in enumerate(mission_items(route, home, laps)):
        fields = [
            str(index),
            "1" if index == 0 else "0",
            str(item.frame),
            str(item.command),
            *(f"{p:g}" for p in item.params),
            f"{item.latitude:.8f}",
            f"{item.longitude:.8f}",
            f"{item.altitude:g}",
            "1",
        ]
        rows.append("\t".join(fields))
    return "\n".join(rows) + "\n"


# ---------------------------------------------------------------------------- .plan


def is_plan(data: Any) -> bool:
    return isinstance(data, Mapping) and data.get("fileType") == "Plan"


def is_old_mission(data: Any) -> bool:
    """QGroundControl's ``.mission`` file (before ``.plan``): ``items`` and a planned home at
    the top, no ``fileType``."""
    return (
        isinstance(data, Mapping)
        and "fileType" not in data
        and isinstance(data.get("items"), list)
        and ("plannedHomePosition" in data or data.get("groundStation") == "QGroundControl")
    )


def old_mission_as_plan(data: Mapping[str, Any]) -> dict[str, Any]:
    """A ``.mission`` file as the ``.plan`` layout :func:`plan_route` reads (its items keep
    their older layout, which :func:`plan_route` reads too); its planned home is an item with
    a ``coordinate``."""
    home = data.get("plannedHomePosition")
    coordinate = home.get("coordinate") if isinstance(home, Mapping) else home
    mission: dict[str, Any] = {"items": data["items"]}
    if isinstance(coordinate, list):
        mission["plannedHomePosition"] = coordinate
    return {"fileType": "Plan", "mission": mission}


def plan_route(data: Mapping[str, Any], *, skip_unsupported: bool = False) -> MissionRoute:
    """A ``.plan`` mission: its SimpleItems (home is ``plannedHomePosition``, not an item)."""
    mission = _section(data, "mission")
    raw = mission.get("items", [])
    if not isinstance(raw, list):
        raise FileRefused("mission.items is not a list")
    items = [_plan_item(item, index) for index, item in enumerate(raw)]
    by_jump_id = {item.jump_id: index for index, item in enumerate(items) if item.jump_id}

    def target(item: MissionItem) -> int | None:
        return by_jump_id.get(int(item.params[0])) if math.isfinite(item.params[0]) else None

    home = mission.get("plannedHomePosition")
    planned = (
        (float(home[0]), float(home[1]))
        if isinstance(home, list) and len(home) >= 2 and all(_number(v) for v in home[:2])
        else None
    )
    route = route_from_items(
        items,
        home_first=False,
        jump_target=target,
        skip_unsupported=skip_unsupported,
        home=planned,
    )
    if route.home is not None:
        route.notes.append(
            f"planned home {route.home[0]:.7f}, {route.home[1]:.7f} is not a waypoint"
        )
    return route


def plan_shapes(data: Mapping[str, Any], *, rally: bool = True) -> list[Shape]:
    """A ``.plan``'s geofence (polygons and circles, inclusion or exclusion) and rally points."""
    fence = _section(data, "geoFence")
    shapes: list[Shape] = []
    polygons = fence.get("polygons", [])
    circles = fence.get("circles", [])
    if not isinstance(polygons, list) or not isinstance(circles, list):
        raise FileRefused("geoFence.polygons and geoFence.circles are lists")
    for index, entry in enumerate(polygons):
        where = f"geoFence polygon {index}"
        if not isinstance(entry, Mapping) or not isinstance(entry.get("polygon"), list):
            raise FileRefused(f"{where}: no 'polygon' list")
        inclusion = entry.get("inclusion", True) is not False
        ring = [_latlon(p, where) for p in entry["polygon"]]
        shapes.append(
            polygon_shape(
                f"{where} ({'inclusion' if inclusion else 'exclusion'})",
                len(shapes),
                [[(lon, lat) for lat, lon in ring]],
                role="inclusion" if inclusion else "keepout",
                ident=f"fence-{index + 1}",
            )
        )
    for index, entry in enumerate(circles):
        where = f"geoFence circle {index}"
        shape = entry.get("circle") if isinstance(entry, Mapping) else None
        if not isinstance(shape, Mapping) or not _number(shape.get("radius")):
            raise FileRefused(f"{where}: no 'circle' with 'center' and 'radius'")
        assert isinstance(entry, Mapping)
        inclusion = entry.get("inclusion", True) is not False
        lat, lon = _latlon(shape.get("center"), where)
        shapes.append(
            circle(
                f"{where} ({'inclusion' if inclusion else 'exclusion'})",
                len(shapes),
                lat,
                lon,
                float(shape["radius"]),
                role="inclusion" if inclusion else "keepout",
                ident=f"fence-circle-{index + 1}",
            )
        )
    if rally:
        points = data.get("rallyPoints", {})
        points = points.get("points", []) if isinstance(points, Mapping) else []
        if not isinstance(points, list):
            raise FileRefused("rallyPoints.points is not a list")
        for index, point in enumerate(points):
            lat, lon = _latlon(point, f"rally point {index}")
            shapes.append(
                Shape.point(f"rally point {index}", len(shapes), f"rally-{index + 1}", lat, lon)
            )
    return shapes


def plan_text(
    route: Sequence[tuple[float, float]],
    home: tuple[float, float],
    fence: Mapping[str, Any] | None = None,
    laps: int | None = None,
) -> str:
    """A route (and the map's boundary and keep-outs as its geofence) as a QGC ``.plan``."""
    items = [
        {
            "type": "SimpleItem",
            "autoContinue": True,
            "command": item.command,
            "doJumpId": item.jump_id,
            "frame": item.frame,
            "params": [*item.params[:3], None, item.latitude, item.longitude, item.altitude],
            "AMSLAltAboveTerrain": None,
            "Altitude": item.altitude,
            "AltitudeMode": 1,
        }
        for item in mission_items(route, None, laps)
    ]
    plan = {
        "fileType": "Plan",
        "version": 1,
        "groundStation": "Brasidas",
        "mission": {
            "version": 2,
            "firmwareType": PLAN_FIRMWARE_GENERIC,
            "vehicleType": PLAN_VEHICLE_ROVER,
            "cruiseSpeed": 1,
            "hoverSpeed": 1,
            "globalPlanAltitudeMode": 1,
            "plannedHomePosition": [home[0], home[1], 0],
            "items": items,
        },
        "geoFence": {"version": 2, "circles": [], "polygons": _fence_polygons(fence)},
        "rallyPoints": {"version": 2, "points": _rally(fence)},
    }
    return json.dumps(plan, indent=4, allow_nan=False) + "\n"


def _fence_polygons(area: Mapping[str, Any] | None) -> list[dict[str, Any]]:
    polygons: list[dict[str, Any]] = []
    for feature in (area or {}).get("features", []):
        role = feature.get("properties", {}).get("role")
        geometry = feature.get("geometry", {})
        if role not in ("boundary", "keepout"):
            continue
        parts = (
            [geometry["coordinates"]]
            if geometry.get("type") == "Polygon"
            else geometry.get("coordinates", [])
        )
        for rings in parts:
            # QGC's polygons are one open ring, [lat, lon] (holes cannot be said: left out).
            ring = [[lat, lon] for lon, lat, *_ in rings[0][:-1]]
            polygons.append({"inclusion": role == "boundary", "polygon": ring, "version": 1})
    return polygons


def _rally(area: Mapping[str, Any] | None) -> list[list[float]]:
    return [
        [f["geometry"]["coordinates"][1], f["geometry"]["coordinates"][0], 0]
        for f in (area or {}).get("features", [])
        if f.get("geometry", {}).get("type") == "Point"
        and str(f.get("properties", {}).get("name", "")).startswith("rally-")
    ]


def _section(data: Mapping[str, Any], key: str) -> Mapping[str, Any]:
    value = data.get(key, {})
    if not isinstance(value, Mapping):
        raise FileRefused(f"the plan's {key!r} is not an object")
    return value


def _plan_item(item: Any, index: int) -> MissionItem:
    where = f"mission item {index}"
    if not isinstance(item, Mapping):
        raise FileRefused(f"{where}: not an object")
    kind = item.get("type")
    if kind == "ComplexItem":
        raise FileRefused(
            f"commands we cannot fly: {where}: a {item.get('complexItemType', 'complex')!r} "
            "pattern (convert it to waypoints in QGroundControl first)"
        )
    if kind not in ("SimpleItem", "missionItem"):
        raise FileRefused(f"{where}: type {kind!r} (SimpleItem or ComplexItem)")
    params = item.get("params")
    if params is None and "coordinate" in item:
        params = _older_params(item, where)
    command, frame = item.get("command"), item.get("frame")
    if not isinstance(command, int) or not isinstance(frame, int):
        raise FileRefused(f"{where}: 'command' and 'frame' are integers")
    if not isinstance(params, list) or len(params) != 7:
        raise FileRefused(f"{where}: 'params' is a list of 7 numbers (null for none)")
    values = []
    for value in params:
        if value is None:
            values.append(math.nan)
        elif _number(value):
            values.append(float(value))
        else:
            raise FileRefused(f"{where}: param {value!r} is not a number")
    jump_id = item.get("doJumpId", item.get("id", 0) if kind == "missionItem" else 0)
    return MissionItem(
        f"{where} (doJumpId {jump_id})" if jump_id else where,
        command,
        frame,
        (values[0], values[1], values[2], values[3]),
        values[4],
        values[5],
        0.0 if math.isnan(values[6]) else values[6],
        jump_id if isinstance(jump_id, int) else 0,
    )


def _older_params(item: Mapping[str, Any], where: str) -> list[Any]:
    """QGroundControl's older item layout (``.mission`` files, early ``.plan`` ones):
    ``param1``..``param4`` and ``coordinate`` [lat, lon, alt] instead of ``params``."""
    coordinate = item.get("coordinate")
    if not isinstance(coordinate, list) or len(coordinate) != 3:
        raise FileRefused(f"{where}: 'coordinate' is [latitude, longitude, altitude]")
    return [item.get(f"param{n}", 0) for n in range(1, 5)] + list(coordinate)


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _latlon(value: Any, where: str) -> tuple[float, float]:
    if not isinstance(value, list) or len(value) < 2 or not all(_number(v) for v in value[:2]):
        raise FileRefused(f"{where}: a position is [latitude, longitude]")
    lat, lon = float(value[0]), float(value[1])
    check_position(lon, lat, where)
    return lat, lon


# ---------------------------------------------------------------------------- older ArduPilot


def is_rally_or_old_fence(text: str) -> bool:
    """Lines of ``lat lon`` pairs and/or ``RALLY`` rows (comments ``#``)."""
    seen = False
    for line in text.splitlines():
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        if fields[0].upper() == "RALLY":
            seen = True
            continue
        if len(fields) != 2 or not all(_is_float(f) for f in fields):
            return False
        seen = True
    return seen


def old_fence_shapes(text: str) -> list[Shape]:
    """ArduPilot's older fence file (the first ``lat lon`` is the return point, the others the
    fence's corners) and ``RALLY lat lon alt ...`` rows."""
    pairs: list[tuple[float, float, str]] = []
    shapes: list[Shape] = []
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        where = f"line {number}"
        try:
            if fields[0].upper() == "RALLY":
                if len(fields) < 3:
                    raise FileRefused(f"{where}: RALLY LAT LON [ALT ...]")
                lat, lon = float(fields[1]), float(fields[2])
                rally = sum(1 for s in shapes if s.role == "point") + 1
                shapes.append(Shape.point(f"{where} (rally point)", 0, f"rally-{rally}", lat, lon))
                continue
            lat, lon = float(fields[0]), float(fields[1])
        except ValueError:
            raise FileRefused(f"{where}: not numbers") from None
        check_position(lon, lat, where)
        pairs.append((lat, lon, where))
    if pairs:
        if len(pairs) < 5:
            raise FileRefused(
                "a fence file is a return point and 3 corners or more, the first repeated "
                f"last ({len(pairs)} lines)"
            )
        corners = pairs[1:]
        if corners[0][:2] != corners[-1][:2]:
            raise FileRefused(
                f"{corners[-1][2]}: an ArduPilot fence file ends on its first corner "
                f"({corners[0][2]}); this one does not (a route? load it with 'route')"
            )
        lat, lon, where = pairs[0]
        shapes.insert(0, Shape.point(f"{where} (fence return point)", 0, "fence-return", lat, lon))
        shapes.insert(
            0,
            polygon_shape(
                f"the fence ({corners[0][2]} to {corners[-1][2]})",
                0,
                [[(lon, lat) for lat, lon, _ in corners]],
                role="inclusion",
                ident="fence",
            ),
        )
    return [
        Shape(s.label, index, s.ident, s.name, s.geometry, s.role, s.properties)
        for index, s in enumerate(shapes)
    ]


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
