"""MAVLink mission items and what a Brasidas route or map makes of them: the one place that maps
MAV_CMD and MAV_FRAME numbers to waypoints, keep-outs and named points (sans-IO). The station's
``.plan`` and ``.waypoints`` readers and writers and the platform's MAVLink endpoint (mission
and fence uploads and downloads, platformd.mavlink.missions) both go through it.

Numbers from the MAVLink ``common.xml`` definitions (mavlink.io "Mission protocol" and
"File formats"): a ground robot's route is NAV_WAYPOINT items in a global frame, item 0 being
home where the convention has one (ArduPilot, Mission Planner, the mission protocol), possibly
closed by a DO_JUMP back to the first waypoint or by a last waypoint equal to the first; a fence
is polygon vertices (param1 = vertex count) and circles (param1 = radius) with a return point;
rally points are named places. A refusal names every item it refuses and carries the
``MAV_MISSION_RESULT`` a ground station's MISSION_ACK says.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

from shapely import Polygon

from brasidas.mapfiles.errors import FileRefused
from brasidas.mapfiles.shapes import (
    CIRCLE_VERTICES,
    Shape,
    circle,
    combined_boundary,
    polygon_shape,
)


class MavCmd(IntEnum):
    """The MAV_CMD values a route or map file may hold (others are named in refusals)."""

    NAV_WAYPOINT = 16
    NAV_RETURN_TO_LAUNCH = 20
    DO_JUMP = 177
    DO_CHANGE_SPEED = 178
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


class MissionResult(IntEnum):
    """MAV_MISSION_RESULT: what a MISSION_ACK says of an upload."""

    ACCEPTED = 0
    ERROR = 1
    UNSUPPORTED_FRAME = 2
    UNSUPPORTED = 3
    NO_SPACE = 4
    INVALID = 5
    INVALID_PARAM1 = 6
    INVALID_PARAM5_X = 10
    INVALID_PARAM6_Y = 11
    INVALID_SEQUENCE = 13
    DENIED = 14


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
    21: "NAV_LAND",
    22: "NAV_TAKEOFF",
    82: "NAV_SPLINE_WAYPOINT",
    93: "NAV_DELAY",
    112: "CONDITION_DELAY",
    114: "CONDITION_DISTANCE",
    176: "DO_SET_MODE",
    179: "DO_SET_HOME",
    181: "DO_SET_RELAY",
    183: "DO_SET_SERVO",
    192: "DO_REPOSITION",
    201: "DO_SET_ROI",
    203: "DO_DIGICAM_CONTROL",
    206: "DO_SET_CAM_TRIGG_DIST",
    224: "DO_SET_MISSION_CURRENT",
    246: "PREFLIGHT_REBOOT_SHUTDOWN",
    400: "COMPONENT_ARM_DISARM",
    519: "REQUEST_PROTOCOL_VERSION",
    2000: "IMAGE_START_CAPTURE",
    2500: "VIDEO_START_CAPTURE",
}
"""Commands ground stations and mission files often hold that are not ours (named, not driven)."""


def command_name(command: int) -> str:
    """``MAV_CMD_NAME (number)`` for messages."""
    try:
        name = MavCmd(command).name
    except ValueError:
        name = OTHER_NAMES.get(command, "") or _pymavlink_name(command)
    return f"MAV_CMD_{name} ({command})" if name else f"MAV_CMD {command}"


def _pymavlink_name(command: int) -> str:
    """The name in pymavlink's MAV_CMD table (ArduPilot's dialect: common.xml and its own),
    without the ``MAV_CMD_`` prefix; empty for a number it does not know."""
    from pymavlink.dialects.v20 import ardupilotmega

    entry = ardupilotmega.enums["MAV_CMD"].get(command)
    name = entry.name if entry is not None else ""
    return name.removeprefix("MAV_CMD_") if name.startswith("MAV_CMD_") else ""


def frame_name(frame: int) -> str:
    try:
        return f"MAV_FRAME_{MavFrame(frame).name} ({frame})"
    except ValueError:
        return f"MAV_FRAME {frame}"


class MissionRefused(FileRefused):
    """Mission or fence items refused: the message names every item refused and why;
    ``result`` is the MAV_MISSION_RESULT of the first (what a MISSION_ACK says)."""

    def __init__(self, result: MissionResult, message: str) -> None:
        super().__init__(message)
        self.result = result


class _Refusals:
    """Every item refused, each with its MAV_MISSION_RESULT: one message names them all."""

    def __init__(self) -> None:
        self.found: list[tuple[MissionResult, str]] = []

    def add(self, result: MissionResult, text: str) -> None:
        self.found.append((result, text))

    def check(self, prefix: str = "") -> None:
        if self.found:
            text = "; ".join(text for _, text in self.found)
            raise MissionRefused(self.found[0][0], prefix + text)


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
    speeds: list[float | None] = field(default_factory=list)
    """m/s on the leg to each waypoint (DO_CHANGE_SPEED); None: the cruise speed."""
    laps: int | None = None
    """Stop after this many laps (a DO_JUMP's count) or once at the end (RETURN_TO_LAUNCH);
    None: patrol until stopped."""
    seqs: list[int] = field(default_factory=list)
    """The index in the items of each waypoint (MISSION_CURRENT's numbering)."""

    @property
    def closed(self) -> bool:
        return len(self.waypoints) >= 3 and self.waypoints[0] == self.waypoints[-1]

    def waypoint_items(self) -> list[dict[str, float]]:
        """The waypoints as the patrol's ``set_waypoints`` items ({lat, lon[, speed]})."""
        items: list[dict[str, float]] = []
        for index, (latitude, longitude) in enumerate(self.waypoints):
            item = {"lat": latitude, "lon": longitude}
            speed = self.speeds[index] if index < len(self.speeds) else None
            if speed is not None:
                item["speed"] = speed
            items.append(item)
        return items


def seq_jump_target(items: Sequence[MissionItem]) -> Callable[[MissionItem], int | None]:
    """A DO_JUMP's target when its param1 is a sequence number (WPL files, the mission
    protocol): the index of that item, None for no such item."""

    def target(item: MissionItem) -> int | None:
        seq = item.params[0]
        return int(seq) if math.isfinite(seq) and 0 <= seq < len(items) else None

    return target


def looks_like_home(item: MissionItem) -> bool:
    """Sequence 0 is home when it is a waypoint in the absolute global frame (ArduPilot,
    Mission Planner, QGroundControl's ArduPilot plans); MAVSDK's mission plugin sends its
    first waypoint there in a relative frame: that one is a waypoint."""
    return item.command == MavCmd.NAV_WAYPOINT and item.frame in (
        MavFrame.GLOBAL,
        MavFrame.GLOBAL_INT,
    )


SKIPPABLE = frozenset({MissionResult.UNSUPPORTED, MissionResult.UNSUPPORTED_FRAME})
"""What ``skip_unsupported`` leaves out (named in the notes): commands and frames a rover
cannot do; a malformed item (position, jump target) is refused all the same."""


def route_from_items(
    items: Sequence[MissionItem],
    *,
    home_first: bool,
    jump_target: Callable[[MissionItem], int | None],
    empty_ok: bool = False,
    skip_unsupported: bool = False,
    home: tuple[float, float] | None = None,
) -> MissionRoute:
    """The route of a mission, or MissionRefused naming every item we cannot drive.

    ``home_first``: item 0 is home (ArduPilot, Mission Planner, the mission protocol), not a
    waypoint; home at 0, 0 is no home. ``jump_target`` gives the index in ``items`` a DO_JUMP
    goes to (None: no such item). ``empty_ok``: no waypoints is an empty route (a ground station
    clearing the mission), not a refusal. ``skip_unsupported``: commands a rover cannot do are
    left out, each named in the notes, instead of refusing the mission. ``home``: the home
    when no item holds it (a ``.plan``'s planned home).

    DO_CHANGE_SPEED (param2 m/s; -1 no change, -2 or 0 the cruise speed) sets the speed of the
    legs after it; a last RETURN_TO_LAUNCH drives back to home and stops there; a last DO_JUMP
    to the first waypoint closes the route, its count (param2) giving the laps."""
    route = MissionRoute([], home)
    body = list(items)
    offset = 0
    if home_first and body:
        first = body.pop(0)
        offset = 1
        if first.latitude == 0 and first.longitude == 0:
            route.notes.append(f"{first.where} is home, without a position (0, 0)")
        else:
            _check_position(first, "home")
            route.home = (first.latitude, first.longitude)
            route.notes.append(
                f"{first.where} is home ({first.latitude:.7f}, {first.longitude:.7f}), "
                "not a waypoint"
            )
    refused = _Refusals()
    first_waypoint: int | None = None
    loop = False
    returns = False
    speed: float | None = None
    altitudes = False

    def unsupported(result: MissionResult, text: str) -> None:
        if skip_unsupported and result in SKIPPABLE:
            route.notes.append(f"{text}: skipped")
        else:
            refused.add(result, text)

    for index, item in enumerate(body):
        last = index == len(body) - 1
        if returns:
            unsupported(
                MissionResult.UNSUPPORTED,
                f"{item.where}: {command_name(item.command)} after RETURN_TO_LAUNCH",
            )
            continue
        if item.command == MavCmd.NAV_WAYPOINT:
            if item.frame not in GLOBAL_FRAMES:
                unsupported(
                    MissionResult.UNSUPPORTED_FRAME,
                    f"{item.where}: a waypoint in {frame_name(item.frame)}",
                )
                continue
            _check_position(item, "waypoint")
            if first_waypoint is None:
                first_waypoint = index + offset
            hold = item.params[0]
            if math.isfinite(hold) and hold > 0:
                route.notes.append(
                    f"{item.where}: hold time {hold:g} s not used (the patrol does not stop)"
                )
            altitudes = altitudes or item.altitude != 0
            route.waypoints.append((item.latitude, item.longitude))
            route.speeds.append(speed)
            route.seqs.append(index + offset)
        elif item.command == MavCmd.DO_CHANGE_SPEED:
            wanted = item.params[1]
            if not math.isfinite(wanted) or wanted < -2:
                refused.add(
                    MissionResult.INVALID,
                    f"{item.where}: {command_name(item.command)}: speed {wanted:g} m/s",
                )
            elif wanted == -1:
                pass  # no change
            elif wanted in (0, -2):
                speed = None
            else:
                speed = float(wanted)
        elif item.command == MavCmd.NAV_RETURN_TO_LAUNCH:
            returns = True
        elif item.command == MavCmd.DO_JUMP:
            target = jump_target(item)
            if target is None or target != first_waypoint or not last:
                refused.add(
                    MissionResult.INVALID_PARAM1 if last else MissionResult.INVALID_SEQUENCE,
                    f"{item.where}: {command_name(item.command)} to {item.params[0]:g}: only a "
                    "last jump back to the first waypoint (a loop) can be driven",
                )
                continue
            repeat = item.params[1]
            if math.isfinite(repeat) and repeat >= 0:
                route.laps = int(repeat) + 1
                route.notes.append(
                    f"{item.where}: {route.laps} laps (the jump repeats {repeat:g} times), "
                    "then the patrol stops at the first waypoint"
                )
            loop = True
        elif item.command in FENCE_COMMANDS or item.command == MavCmd.NAV_RALLY_POINT:
            unsupported(
                MissionResult.UNSUPPORTED,
                f"{item.where}: {command_name(item.command)} is a fence or rally item, "
                "not a waypoint (load it as a map)",
            )
        else:
            unsupported(MissionResult.UNSUPPORTED, f"{item.where}: {command_name(item.command)}")
    if returns:
        if route.home is None:
            refused.add(
                MissionResult.INVALID,
                "RETURN_TO_LAUNCH without a home (item 0 in the global frame)",
            )
        else:
            route.waypoints.append(route.home)
            route.speeds.append(speed)
            route.seqs.append(len(items) - 1)
            route.laps = 1
            route.notes.append("RETURN_TO_LAUNCH: the route ends at home; the patrol stops there")
    refused.check("commands we cannot fly: ")
    if not route.waypoints and not empty_ok:
        raise MissionRefused(MissionResult.INVALID, "no waypoints in the mission")
    if altitudes:
        route.notes.append("altitudes ignored (a ground robot)")
    if loop and len(route.waypoints) >= 2 and route.waypoints[-1] != route.waypoints[0]:
        route.waypoints.append(route.waypoints[0])
        route.speeds.append(speed)
        route.seqs.append(route.seqs[0])
    if loop:
        route.notes.append("a jump back to the first waypoint: the route is closed (loops)")
    return route


def fence_shapes(items: Sequence[MissionItem], first_index: int = 0) -> list[Shape]:
    """Fence and rally items as shapes: inclusion polygons and circles (the boundary: their
    intersection), exclusion ones (keep-outs), the return point and rally points (named).
    MissionRefused names every item refused."""
    shapes: list[Shape] = []
    refused = _Refusals()
    rally = 0
    pending: list[MissionItem] = []
    for item in items:
        if pending and (item.command != pending[0].command or len(pending) >= _count(pending[0])):
            _close_polygon(pending, shapes, first_index, refused)
            pending = []
        if item.command in (
            MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION,
            MavCmd.NAV_FENCE_POLYGON_VERTEX_EXCLUSION,
        ):
            pending.append(item)
            continue
        if item.frame not in GLOBAL_FRAMES:
            refused.add(
                MissionResult.UNSUPPORTED_FRAME,
                f"{item.where}: {frame_name(item.frame)} is not latitude, longitude",
            )
            continue
        if item.command in (MavCmd.NAV_FENCE_CIRCLE_INCLUSION, MavCmd.NAV_FENCE_CIRCLE_EXCLUSION):
            _check_position(item, "circle centre")
            inclusion = item.command == MavCmd.NAV_FENCE_CIRCLE_INCLUSION
            kind = "inclusion" if inclusion else "exclusion"
            try:
                shapes.append(
                    circle(
                        f"{item.where} (fence circle, {kind})",
                        first_index + len(shapes),
                        item.latitude,
                        item.longitude,
                        item.params[0],
                        role="inclusion" if inclusion else "keepout",
                        ident=f"fence-circle-{len(shapes) + 1}",
                        vertices=CIRCLE_VERTICES,
                    )
                )
            except FileRefused as exc:  # the radius (param1)
                refused.add(MissionResult.INVALID_PARAM1, str(exc))
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
            refused.add(
                MissionResult.UNSUPPORTED,
                f"{item.where}: {command_name(item.command)} is not a fence item",
            )
    if pending:
        _close_polygon(pending, shapes, first_index, refused)
    refused.check()
    return shapes


LatLonRing = tuple[tuple[float, float], ...]
"""(latitude, longitude) corners, the first not repeated."""


@dataclass(frozen=True)
class FencePlan:
    """A fence as the platform's map takes it: the boundary (None: keep the map's) and
    keep-out rings."""

    boundary: LatLonRing | None = None
    keepouts: tuple[LatLonRing, ...] = ()
    inclusions: int = 0
    """The inclusion polygons that made the boundary."""


def fence_plan(items: Sequence[MissionItem], *, union: bool = False) -> FencePlan:
    """A fence uploaded to the platform: :func:`fence_shapes`' checks, then the map's own rules
    (the inclusion polygons make the boundary: where they all overlap, ArduPilot's default, or
    with ``union`` their union, its ``FENCE_OPTIONS`` bit 1; keep-outs; the return point is not
    used: a rover holds inside the boundary). MissionRefused names every item refused."""
    shapes = fence_shapes(items)
    refused = _Refusals()
    inclusions: list[Shape] = []
    keepouts: list[LatLonRing] = []
    for shape in shapes:
        if shape.role == "keepout":
            keepouts.append(_ring(shape))
        elif shape.role == "inclusion" and "circle_radius_m" in shape.properties:
            refused.add(
                MissionResult.UNSUPPORTED,
                f"{shape.label}: an inclusion circle (the boundary is a polygon)",
            )
        elif shape.role == "inclusion":
            inclusions.append(shape)
        elif shape.ident != "fence-return":
            refused.add(
                MissionResult.UNSUPPORTED,
                f"{shape.label}: a rally point is not a fence item (rally points are not taken)",
            )
    refused.check()
    if not inclusions:
        return FencePlan(None, tuple(keepouts))
    try:
        area = combined_boundary(inclusions, union)
    except FileRefused as exc:
        raise MissionRefused(MissionResult.INVALID_PARAM5_X, str(exc)) from None
    # A union round a gap leaves a hole no inclusion covers: the robot keeps out of it.
    holes = [_corners(interior.coords) for interior in area.interiors]
    return FencePlan(_corners(area.exterior.coords), (*keepouts, *holes), len(inclusions))


def mission_items(
    route: Sequence[tuple[float, float]],
    home: tuple[float, float] | None,
    laps: int | None = None,
) -> list[MissionItem]:
    """A route as mission items: home first when given (ArduPilot's sequence 0, in the global
    frame), then NAV_WAYPOINTs at relative altitude 0; a closed route (its last waypoint its
    first) ends with a DO_JUMP back to the first waypoint instead, repeated forever (or
    ``laps`` - 1 times), so another autopilot loops it too. The jump's param1 is 1 both as a
    sequence number (after home) and as a ``.plan`` doJumpId (the first waypoint's)."""
    closed = len(route) >= 3 and route[0] == route[-1]
    if closed:
        route = route[:-1]
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
    if closed:
        repeat = -1.0 if laps is None else float(laps - 1)
        items.append(
            MissionItem(
                f"item {len(items)}",
                int(MavCmd.DO_JUMP),
                int(MavFrame.MISSION),
                (1.0, repeat, 0.0, 0.0),
                0.0,
                0.0,
                jump_id=len(items) + (0 if home is not None else 1),
            )
        )
    return items


_NO_PARAMS = (0.0, 0.0, 0.0, 0.0)


def fence_items(area: Mapping[str, Any], *, rally: bool = True) -> list[MissionItem]:
    """A canonical map as fence (and rally) items, what a ground station downloads: the
    boundary as an inclusion polygon, each keep-out's polygons as exclusion polygons (holes
    cannot be said), and with ``rally`` the named points as rally points."""
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
        elif kind == "Point" and rally:
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


def _close_polygon(
    pending: list[MissionItem], shapes: list[Shape], first_index: int, refused: _Refusals
) -> None:
    head = pending[0]
    count = _count(head)
    inclusion = head.command == MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION
    kind = "inclusion" if inclusion else "exclusion"
    where = f"{head.where} to {pending[-1].where}"
    if count == 0:
        refused.add(
            MissionResult.INVALID_PARAM1,
            f"{head.where}: polygon vertex count (param1) {head.params[0]:g} is not 3 or more",
        )
        return
    if len(pending) != count:
        refused.add(
            MissionResult.INVALID_PARAM1,
            f"{where}: a {kind} polygon of {count} vertices has {len(pending)}",
        )
        return
    bad = [item.where for item in pending if item.frame not in GLOBAL_FRAMES]
    if bad:
        refused.add(
            MissionResult.UNSUPPORTED_FRAME,
            f"{', '.join(bad)}: not in a latitude, longitude frame",
        )
        return
    for item in pending:
        _check_position(item, "vertex")
    ring = [(item.longitude, item.latitude) for item in pending]
    try:
        shapes.append(
            polygon_shape(
                f"{where} (fence polygon, {kind})",
                first_index + len(shapes),
                [ring],
                role="inclusion" if inclusion else "keepout",
                ident=f"fence-{len(shapes) + 1}",
            )
        )
    except FileRefused as exc:  # crossing edges, no area
        refused.add(MissionResult.INVALID, str(exc))


def _ring(shape: Shape) -> LatLonRing:
    """A polygon shape's outer ring as (lat, lon), the closing corner left out."""
    geometry = shape.geometry
    assert isinstance(geometry, Polygon)  # fence polygons and circles are one ring each
    return _corners(geometry.exterior.coords)


def _corners(coords: Any) -> LatLonRing:
    """A ring's (lon, lat) coordinates as (lat, lon), the closing corner left out."""
    corners = [(float(lat), float(lon)) for lon, lat in coords]
    return tuple(corners[:-1] if len(corners) > 1 and corners[0] == corners[-1] else corners)


def _check_position(item: MissionItem, what: str) -> None:
    lat, lon = item.latitude, item.longitude
    if not (math.isfinite(lat) and abs(lat) <= 90):
        raise MissionRefused(
            MissionResult.INVALID_PARAM5_X,
            f"{item.where}: {what} {lat}, {lon} is not a latitude, longitude",
        )
    if not (math.isfinite(lon) and abs(lon) <= 180):
        raise MissionRefused(
            MissionResult.INVALID_PARAM6_Y,
            f"{item.where}: {what} {lat}, {lon} is not a latitude, longitude",
        )
    if lat == 0 and lon == 0:
        raise MissionRefused(
            MissionResult.INVALID_PARAM5_X, f"{item.where}: {what} at 0, 0 (no position given)"
        )
