"""Mission and fence items ↔ the patrol's route and the map's geometry (pure functions).

A mission is ArduPilot's and Mission Planner's: item 0 is home (never a waypoint), then
``MAV_CMD_NAV_WAYPOINT`` items; a ``MAV_CMD_DO_JUMP`` back to the first waypoint as the last
item, or a last waypoint equal to the first, makes a closed route (it loops). A fence is
inclusion/exclusion polygon vertices (param1 the vertex count) and circles (param1 the radius):
one inclusion polygon is the map's boundary, exclusion polygons and circles are keep-outs.
Anything else is refused with the ``MAV_MISSION_RESULT`` a ground station understands and a
reason for the operator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink

MISSION = mavlink.MAV_MISSION_TYPE_MISSION
FENCE = mavlink.MAV_MISSION_TYPE_FENCE
RALLY = mavlink.MAV_MISSION_TYPE_RALLY

MAX_ITEMS = 1000
"""The longest mission or fence accepted (the route's own limit, brasidas.autonomy.route)."""
CIRCLE_SEGMENTS = 32
"""An exclusion circle becomes a keep-out polygon of this many vertices (inside the circle's
bounding polygon: 0.5 % of the radius short at the edges' middles, well under GPS error)."""
EARTH_RADIUS_M = 6_371_008.8

GLOBAL_FRAMES = frozenset(
    {
        mavlink.MAV_FRAME_GLOBAL,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
        mavlink.MAV_FRAME_GLOBAL_INT,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    }
)
"""Frames whose x, y are latitude and longitude (a rover ignores the altitude)."""

WAYPOINT = mavlink.MAV_CMD_NAV_WAYPOINT
DO_JUMP = mavlink.MAV_CMD_DO_JUMP
FENCE_RETURN_POINT = mavlink.MAV_CMD_NAV_FENCE_RETURN_POINT
FENCE_INCLUSION_VERTEX = mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
FENCE_EXCLUSION_VERTEX = mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION
FENCE_INCLUSION_CIRCLE = mavlink.MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION
FENCE_EXCLUSION_CIRCLE = mavlink.MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION


@dataclass(frozen=True)
class MissionItem:
    """One MISSION_ITEM_INT's content (x, y in degrees times 1e7, as on the wire)."""

    seq: int
    frame: int
    command: int
    param1: float = 0.0
    param2: float = 0.0
    param3: float = 0.0
    param4: float = 0.0
    x: int = 0
    y: int = 0
    z: float = 0.0
    autocontinue: int = 1
    current: int = 0

    @property
    def latitude(self) -> float:
        return self.x / 1e7

    @property
    def longitude(self) -> float:
        return self.y / 1e7


class MissionRefused(ValueError):
    """Items refused: ``result`` is the MAV_MISSION_RESULT, the message the operator's reason."""

    def __init__(self, result: int, message: str) -> None:
        super().__init__(message)
        self.result = result


@dataclass(frozen=True)
class RoutePlan:
    """A mission as the patrol takes it: waypoints (lat, lon), closed when the last is the first."""

    waypoints: tuple[tuple[float, float], ...]
    home: tuple[float, float] | None = None


@dataclass(frozen=True)
class FencePlan:
    """A fence as the map takes it: the boundary (None: keep the map's) and keep-out rings."""

    boundary: tuple[tuple[float, float], ...] | None = None
    keepouts: tuple[tuple[tuple[float, float], ...], ...] = field(default=())


def route_from_items(items: list[MissionItem]) -> RoutePlan:
    """The route of an uploaded mission; raises :class:`MissionRefused`."""
    home: tuple[float, float] | None = None
    waypoints: list[tuple[float, float]] = []
    first_waypoint_seq: int | None = None
    for item in items:
        if item.seq == 0:
            if item.command == WAYPOINT and item.frame in GLOBAL_FRAMES:
                home = _position(item) if item.x or item.y else None
            continue  # home (ArduPilot's convention): never a waypoint
        if item.command == WAYPOINT:
            if item.frame not in GLOBAL_FRAMES:
                raise MissionRefused(
                    mavlink.MAV_MISSION_UNSUPPORTED_FRAME,
                    f"item {item.seq}: frame {_frame_name(item.frame)} (use a global frame)",
                )
            if first_waypoint_seq is None:
                first_waypoint_seq = item.seq
            waypoints.append(_position(item))
            continue
        if item.command == DO_JUMP and item.seq == len(items) - 1:
            if first_waypoint_seq is None or int(item.param1) != first_waypoint_seq:
                raise MissionRefused(
                    mavlink.MAV_MISSION_INVALID_PARAM1,
                    f"item {item.seq}: DO_JUMP only back to the first waypoint "
                    f"(item {first_waypoint_seq}), to loop the route",
                )
            if len(waypoints) >= 2 and waypoints[-1] != waypoints[0]:
                waypoints.append(waypoints[0])
            continue
        raise MissionRefused(
            mavlink.MAV_MISSION_UNSUPPORTED,
            f"item {item.seq}: {command_name(item.command)} is not supported "
            "(a patrol route takes NAV_WAYPOINT and a final DO_JUMP to the first)",
        )
    return RoutePlan(tuple(waypoints), home)


def items_from_route(
    waypoints: list[tuple[float, float]], home: tuple[float, float] | None
) -> list[MissionItem]:
    """A route as mission items: home at 0, then one NAV_WAYPOINT per waypoint."""
    lat, lon = home if home is not None else (waypoints[0] if waypoints else (0.0, 0.0))
    items = [MissionItem(0, mavlink.MAV_FRAME_GLOBAL, WAYPOINT, x=_e7(lat), y=_e7(lon))]
    for lat, lon in waypoints:
        items.append(
            MissionItem(
                len(items),
                mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                WAYPOINT,
                x=_e7(lat),
                y=_e7(lon),
            )
        )
    return items


def fence_from_items(items: list[MissionItem]) -> FencePlan:
    """The geometry of an uploaded fence; raises :class:`MissionRefused`."""
    boundary: tuple[tuple[float, float], ...] | None = None
    keepouts: list[tuple[tuple[float, float], ...]] = []
    index = 0
    while index < len(items):
        item = items[index]
        if item.frame not in GLOBAL_FRAMES:
            raise MissionRefused(
                mavlink.MAV_MISSION_UNSUPPORTED_FRAME,
                f"fence item {item.seq}: frame {_frame_name(item.frame)} (use a global frame)",
            )
        if item.command == FENCE_RETURN_POINT:
            index += 1
            continue  # a rover holds inside the boundary: there is nowhere to return to
        if item.command in (FENCE_INCLUSION_VERTEX, FENCE_EXCLUSION_VERTEX):
            count = int(item.param1)
            if count < 3 or index + count > len(items):
                raise MissionRefused(
                    mavlink.MAV_MISSION_INVALID_PARAM1,
                    f"fence item {item.seq}: a polygon of {count} vertices "
                    f"({len(items) - index} items left)",
                )
            vertices = items[index : index + count]
            if any(v.command != item.command or int(v.param1) != count for v in vertices):
                raise MissionRefused(
                    mavlink.MAV_MISSION_INVALID_SEQUENCE,
                    f"fence item {item.seq}: the polygon's {count} vertices are not consecutive",
                )
            ring = tuple(_position(v) for v in vertices)
            if item.command == FENCE_INCLUSION_VERTEX:
                if boundary is not None:
                    raise MissionRefused(
                        mavlink.MAV_MISSION_UNSUPPORTED,
                        f"fence item {item.seq}: a second inclusion polygon (the map has one "
                        "boundary)",
                    )
                boundary = ring
            else:
                keepouts.append(ring)
            index += count
            continue
        if item.command == FENCE_EXCLUSION_CIRCLE:
            if not 0.5 <= item.param1 <= 10_000:
                raise MissionRefused(
                    mavlink.MAV_MISSION_INVALID_PARAM1,
                    f"fence item {item.seq}: radius {item.param1:g} m (0.5 to 10000 m)",
                )
            keepouts.append(circle_ring(_position(item), item.param1))
            index += 1
            continue
        if item.command == FENCE_INCLUSION_CIRCLE:
            raise MissionRefused(
                mavlink.MAV_MISSION_UNSUPPORTED,
                f"fence item {item.seq}: an inclusion circle (the boundary is a polygon)",
            )
        raise MissionRefused(
            mavlink.MAV_MISSION_UNSUPPORTED,
            f"fence item {item.seq}: {command_name(item.command)} is not a fence item",
        )
    return FencePlan(boundary, tuple(keepouts))


def items_from_fence(fence: FencePlan) -> list[MissionItem]:
    """The map's geometry as fence items: the boundary's inclusion polygon, then keep-outs."""
    items: list[MissionItem] = []
    rings = [(FENCE_INCLUSION_VERTEX, fence.boundary)] if fence.boundary else []
    rings += [(FENCE_EXCLUSION_VERTEX, ring) for ring in fence.keepouts]
    for command, ring in rings:
        assert ring is not None
        for lat, lon in ring:
            items.append(
                MissionItem(
                    len(items),
                    mavlink.MAV_FRAME_GLOBAL,
                    command,
                    param1=len(ring),
                    x=_e7(lat),
                    y=_e7(lon),
                )
            )
    return items


def circle_ring(centre: tuple[float, float], radius_m: float) -> tuple[tuple[float, float], ...]:
    """A circle as a polygon ring of :data:`CIRCLE_SEGMENTS` vertices (lat, lon)."""
    lat, lon = centre
    dlat = math.degrees(radius_m / EARTH_RADIUS_M)
    dlon = dlat / max(math.cos(math.radians(lat)), 1e-6)
    return tuple(
        (
            lat + dlat * math.sin(2 * math.pi * k / CIRCLE_SEGMENTS),
            lon + dlon * math.cos(2 * math.pi * k / CIRCLE_SEGMENTS),
        )
        for k in range(CIRCLE_SEGMENTS)
    )


def command_name(command: int) -> str:
    """``NAV_LAND (21)``-like name of a MAV_CMD."""
    entry = mavlink.enums["MAV_CMD"].get(command)
    name = entry.name.removeprefix("MAV_CMD_") if entry is not None else "MAV_CMD"
    return f"{name} ({command})"


def _frame_name(frame: int) -> str:
    entry = mavlink.enums["MAV_FRAME"].get(frame)
    return f"{entry.name.removeprefix('MAV_FRAME_')} ({frame})" if entry else str(frame)


def _position(item: MissionItem) -> tuple[float, float]:
    lat, lon = item.latitude, item.longitude
    if not -90 <= lat <= 90:
        raise MissionRefused(
            mavlink.MAV_MISSION_INVALID_PARAM5_X, f"item {item.seq}: latitude {lat:g}"
        )
    if not -180 <= lon <= 180:
        raise MissionRefused(
            mavlink.MAV_MISSION_INVALID_PARAM6_Y, f"item {item.seq}: longitude {lon:g}"
        )
    return (lat, lon)


def _e7(degrees: float) -> int:
    return round(degrees * 1e7)
