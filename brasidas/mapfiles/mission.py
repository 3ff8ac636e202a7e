"""MAVLink mission items and what a Brasidas route or map makes of them: the one place that maps
MAV_CMD and MAV_FRAME numbers to waypoints, keep-outs and named points (sans-IO).

Numbers from the MAVLink ``common.xml`` definitions (mavlink.io "Mission protocol" and
"File formats"): a ground robot's route is NAV_WAYPOINT items in a global frame, possibly
closed by a DO_JUMP back to the first; a fence is polygon vertices (param1 = vertex count) and
circles (param1 = radius); rally points are named places.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

from brasidas.mapfiles.errors import FileRefused
from brasidas.mapfiles.shapes import CIRCLE_VERTICES, Shape, circle, polygon_shape


class MavCmd(IntEnum):
    """The MAV_CMD values a route or map file may hold (others are named in refusals)."""

    NAV_WAYPOINT = 16
    DO_JUMP = 177
    NAV_FENCE_RETURN_POINT = 5000
    NAV_FENCE_POLYGON_VERTEX_INCLUSION = 5001
    NAV_FENCE_POLYGON_VERTEX_EXCLUSION = 5002
    NAV_FENCE_CIRCLE_INCLUSION = 5003
    NAV_FENCE_CIRCLE_EXCLUSION = 5004
    NAV_RALLY_POINT = 5100


class MavFrame(IntEnum):
    GLOBAL = 0
    LOCAL_NED = 1
    MISSION = 2
    GLOBAL_RELATIVE_ALT = 3
    LOCAL_ENU = 4
    GLOBAL_INT = 5
    GLOBAL_RELATIVE_ALT_INT = 6
    LOCAL_OFFSET_NED = 7
    GLOBAL_TERRAIN_ALT = 10
    GLOBAL_TERRAIN_ALT_INT = 11


GLOBAL_FRAMES = frozenset(
    {
        MavFrame.GLOBAL,
        MavFrame.GLOBAL_RELATIVE_ALT,
        MavFrame.GLOBAL_INT,
        MavFrame.GLOBAL_RELATIVE_ALT_INT,
        MavFrame.GLOBAL_TERRAIN_ALT,
        MavFrame.GLOBAL_TERRAIN_ALT_INT,
    }
)
"""Latitude and longitude in x and y; the altitude (whatever its datum) is not used."""
FENCE_COMMANDS = frozenset(range(5000, 5005))
OTHER_NAMES = {
    17: "NAV_LOITER_UNLIM",
    18: "NAV_LOITER_TURNS",
    19: "NAV_LOITER_TIME",
    20: "NAV_RETURN_TO_LAUNCH",
    21: "NAV_LAND",
    22: "NAV_TAKEOFF",
    82: "NAV_SPLINE_WAYPOINT",
    93: "NAV_DELAY",
    112: "CONDITION_DELAY",
    114: "CONDITION_DISTANCE",
    176: "DO_SET_MODE",
    178: "DO_CHANGE_SPEED",
    179: "DO_SET_HOME",
    181: "DO_SET_RELAY",
    183: "DO_SET_SERVO",
    201: "DO_SET_ROI",
    203: "DO_DIGICAM_CONTROL",
    206: "DO_SET_CAM_TRIGG_DIST",
    2000: "IMAGE_START_CAPTURE",
    2500: "VIDEO_START_CAPTURE",
}


def command_name(command: int) -> str:
    """``MAV_CMD_NAME (number)`` for messages."""
    try:
        name = MavCmd(command).name
    except ValueError:
        name = OTHER_NAMES.get(command, "")
    return f"MAV_CMD_{name} ({command})" if name else f"MAV_CMD {command}"


def frame_name(frame: int) -> str:
    try:
        return f"MAV_FRAME_{MavFrame(frame).name} ({frame})"
    except ValueError:
        return f"MAV_FRAME {frame}"


@dataclass(frozen=True)
class MissionItem:
    """One mission item as files and MISSION_ITEM_INT carry it (x, y in degrees)."""

    where: str
    """How a message names it: "row 3", "mission item 2"."""
    command: int
    frame: int
    params: tuple[float, float, float, float]
    latitude: float
    longitude: float
    altitude: float = 0.0
    jump_id: int = 0
    """QGC .plan's doJumpId (a DO_JUMP's param1 names it); 0 in WPL files (sequence numbers)."""


@dataclass
class MissionRoute:
    """What a mission makes: waypoints (lat, lon), home, and what was read or left aside."""

    waypoints: list[tuple[float, float]]
    home: tuple[float, float] | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def closed(self) -> bool:
        return len(self.waypoints) >= 3 and self.waypoints[0] == self.waypoints[-1]


def route_from_items(
    items: Sequence[MissionItem],
    *,
    home_first: bool,
    jump_target: Callable[[MissionItem], int | None],
) -> MissionRoute:
    """The route of a mission, or FileRefused naming every item we cannot drive.

    ``home_first``: item 0 is home (ArduPilot and Mission Planner), not a waypoint.
    ``jump_target`` gives the index in ``items`` a DO_JUMP goes to (None: no such item)."""
    route = MissionRoute([])
    body = list(items)
    if home_first and body:
        home = body.pop(0)
        _check_position(home, "home")
        route.home = (home.latitude, home.longitude)
        route.notes.append(
            f"{home.where} is home ({home.latitude:.7f}, {home.longitude:.7f}), not a waypoint"
        )
    refused: list[str] = []
    first_waypoint: int | None = None
    loop = False
    altitudes = False
    for index, item in enumerate(body):
        if item.command == MavCmd.NAV_WAYPOINT:
            if item.frame not in GLOBAL_FRAMES:
                refused.append(f"{item.where}: a waypoint in {frame_name(item.frame)}")
                continue
            _check_position(item, "waypoint")
            if first_waypoint is None:
                first_waypoint = index + (1 if home_first else 0)
            hold = item.params[0]
            if math.isfinite(hold) and hold > 0:
                route.notes.append(
                    f"{item.where}: hold time {hold:g} s not used (the patrol does not stop)"
                )
            altitudes = altitudes or item.altitude != 0
            route.waypoints.append((item.latitude, item.longitude))
        elif item.command == MavCmd.DO_JUMP:
            target = jump_target(item)
            last = index == len(body) - 1
            if target is None or target != first_waypoint or not last:
                refused.append(
                    f"{item.where}: {command_name(item.command)} to {item.params[0]:g}: only a "
                    "last jump back to the first waypoint (a loop) can be driven"
                )
                continue
            repeat = item.params[1]
            if math.isfinite(repeat) and repeat >= 0:
                route.notes.append(
                    f"{item.where}: the jump's repeat count {repeat:g} is not used: the "
                    "patrol loops until stopped"
                )
            loop = True
        elif item.command in FENCE_COMMANDS or item.command == MavCmd.NAV_RALLY_POINT:
            refused.append(
                f"{item.where}: {command_name(item.command)} is a fence or rally item, "
                "not a waypoint (load it as a map)"
            )
        else:
            refused.append(f"{item.where}: {command_name(item.command)}")
    if refused:
        raise FileRefused("commands we cannot fly: " + "; ".join(refused))
    if not route.waypoints:
        raise FileRefused("no waypoints in the mission")
    if altitudes:
        route.notes.append("altitudes ignored (a ground robot)")
    if loop and route.waypoints[-1] != route.waypoints[0]:
        route.waypoints.append(route.waypoints[0])
    if loop:
        route.notes.append("a jump back to the first waypoint: the route is closed (loops)")
    return route


def fence_shapes(items: Sequence[MissionItem], first_index: int = 0) -> list[Shape]:
    """Fence and rally items as shapes: inclusion polygons and circles (the boundary: their
    intersection), exclusion ones (keep-outs), the return point and rally points (named)."""
    shapes: list[Shape] = []
    refused: list[str] = []
    rally = 0
    pending: list[MissionItem] = []
    for item in items:
        if pending and (item.command != pending[0].command or len(pending) >= _count(pending[0])):
            refused.extend(_close_polygon(pending, shapes, first_index))
            pending = []
        if item.command in (
            MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION,
            MavCmd.NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
        ):
            pending.append(item)
            continue
        if item.frame not in GLOBAL_FRAMES:
            refused.append(f"{item.where}: {frame_name(item.frame)} is not latitude, longitude")
            continue
        if item.command in (MavCmd.NAV_FENCE_CIRCLE_INCLUSION, MavCmd.NAV_FENCE_CIRCLE_EXCLUSION):
            _check_position(item, "circle centre")
            inclusion = item.command == MavCmd.NAV_FENCE_CIRCLE_INCLUSION
            kind = "inclusion" if inclusion else "exclusion"
            label = f"{item.where} (fence circle, {kind})"
            shapes.append(
                circle(
                    label,
                    first_index + len(shapes),
                    item.latitude,
                    item.longitude,
                    item.params[0],
                    role="inclusion" if inclusion else "keepout",
                    ident=f"fence-circle-{len(shapes) + 1}",
                    vertices=CIRCLE_VERTICES,
                )
            )
        elif item.command == MavCmd.NAV_FENCE_RETURN_POINT:
            _check_position(item, "return point")
            shapes.append(
                Shape.point(
                    f"{item.where} (fence return point)",
                    first_index + len(shapes),
                    "fence-return",
                    item.latitude,
                    item.longitude,
                )
            )
        elif item.command == MavCmd.NAV_RALLY_POINT:
            _check_position(item, "rally point")
            rally += 1
            shapes.append(
                Shape.point(
                    f"{item.where} (rally point)",
                    first_index + len(shapes),
                    f"rally-{rally}",
                    item.latitude,
                    item.longitude,
                )
            )
        else:
            refused.append(f"{item.where}: {command_name(item.command)} is not a fence item")
    if pending:
        refused.extend(_close_polygon(pending, shapes, first_index))
    if refused:
        raise FileRefused("; ".join(refused))
    return shapes


def mission_items(
    route: Sequence[tuple[float, float]], home: tuple[float, float] | None
) -> list[MissionItem]:
    """A route as mission items: home first when given (ArduPilot's sequence 0, in the global
    frame), then NAV_WAYPOINTs at relative altitude 0 (a closed route ends on its first)."""
    items = []
    if home is not None:
        items.append(
            MissionItem("home", int(MavCmd.NAV_WAYPOINT), int(MavFrame.GLOBAL), _NO_PARAMS, *home)
        )
    for latitude, longitude in route:
        items.append(
            MissionItem(
                f"item {len(items)}",
                int(MavCmd.NAV_WAYPOINT),
                int(MavFrame.GLOBAL_RELATIVE_ALT),
                _NO_PARAMS,
                latitude,
                longitude,
                jump_id=len(items) + (0 if home is not None else 1),
            )
        )
    return items


_NO_PARAMS = (0.0, 0.0, 0.0, 0.0)


def fence_items(area: Mapping[str, Any]) -> list[MissionItem]:
    """A canonical map as fence and rally items (what a ground station downloads): the
    boundary as an inclusion polygon, each keep-out's polygons as exclusion polygons (holes
    cannot be said), the named points as rally points."""
    items: list[MissionItem] = []

    def polygon(ring: Sequence[Sequence[float]], command: MavCmd, where: str) -> None:
        corners = ring[:-1]  # GeoJSON repeats the first corner; a fence does not
        for lon, lat, *_ in corners:
            items.append(
                MissionItem(
                    f"{where} vertex {len(items)}",
                    int(command),
                    int(MavFrame.GLOBAL),
                    (float(len(corners)), 0.0, 0.0, 0.0),
                    float(lat),
                    float(lon),
                )
            )

    for feature in area.get("features", []):
        role = feature.get("properties", {}).get("role", "")
        geometry = feature.get("geometry", {})
        kind, coordinates = geometry.get("type"), geometry.get("coordinates")
        if role == "boundary":
            polygon(coordinates[0], MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION, "boundary")
        elif role == "keepout":
            parts = [coordinates] if kind == "Polygon" else coordinates
            for rings in parts:
                polygon(rings[0], MavCmd.NAV_FENCE_POLYGON_VERTEX_EXCLUSION, str(feature.get("id")))
        elif kind == "Point":
            lon, lat = coordinates[:2]
            items.append(
                MissionItem(
                    str(feature.get("properties", {}).get("name", "")),
                    int(MavCmd.NAV_RALLY_POINT),
                    int(MavFrame.GLOBAL),
                    _NO_PARAMS,
                    float(lat),
                    float(lon),
                )
            )
    return items


def _count(item: MissionItem) -> int:
    count = item.params[0]
    return int(count) if math.isfinite(count) and count >= 3 and count == int(count) else 0


def _close_polygon(pending: list[MissionItem], shapes: list[Shape], first_index: int) -> list[str]:
    head = pending[0]
    count = _count(head)
    inclusion = head.command == MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION
    kind = "inclusion" if inclusion else "exclusion"
    where = f"{head.where} to {pending[-1].where}"
    if count == 0:
        return [f"{head.where}: polygon vertex count (param1) {head.params[0]:g} is not 3 or more"]
    if len(pending) != count:
        return [f"{where}: a {kind} polygon of {count} vertices has {len(pending)}"]
    bad = [item.where for item in pending if item.frame not in GLOBAL_FRAMES]
    if bad:
        return [f"{', '.join(bad)}: not in a latitude, longitude frame"]
    for item in pending:
        _check_position(item, "vertex")
    ring = [(item.longitude, item.latitude) for item in pending]
    shapes.append(
        polygon_shape(
            f"{where} (fence polygon, {kind})",
            first_index + len(shapes),
            [ring],
            role="inclusion" if inclusion else "keepout",
            ident=f"fence-{len(shapes) + 1}",
        )
    )
    return []


def _check_position(item: MissionItem, what: str) -> None:
    lat, lon = item.latitude, item.longitude
    if not (math.isfinite(lat) and math.isfinite(lon)) or abs(lat) > 90 or abs(lon) > 180:
        raise FileRefused(f"{item.where}: {what} {lat}, {lon} is not a latitude, longitude")
    if lat == 0 and lon == 0:
        raise FileRefused(f"{item.where}: {what} at 0, 0 (no position given)")
