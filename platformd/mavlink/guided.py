"""A ground station's "go to this point": GUIDED's targets read from the wire (sans-IO).

QGroundControl's "Go to location" and MAVSDK's ``goto_location`` send ``MAV_CMD_DO_REPOSITION``
(COMMAND_INT: x, y in degrees times 1e7; COMMAND_LONG: param5, param6 in degrees); others stream
SET_POSITION_TARGET_GLOBAL_INT; MAVProxy's ``guided LAT LON`` sends a MISSION_ITEM_INT with
``current`` 2 (ArduPilot's guided waypoint). The service drives there through the patrol's planner (around
keep-outs) and stops; RTL is the same to home.
"""

from __future__ import annotations

import math
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

POSITION_IGNORED = (
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
)
GLOBAL_FRAMES = frozenset(
    {
        mavlink.MAV_FRAME_GLOBAL,
        mavlink.MAV_FRAME_GLOBAL_INT,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT,
        mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT,
    }
)


def reposition_target(message: Any) -> tuple[float, float] | None:
    """DO_REPOSITION's point (lat, lon), None when it has none (NaN or zero: "here")."""
    if message.get_type() == "COMMAND_INT":
        if message.frame not in GLOBAL_FRAMES:
            return None
        return _point(message.x / 1e7, message.y / 1e7)
    return _point(message.param5, message.param6)


GUIDED_ITEM = 2
"""MISSION_ITEM(_INT)'s ``current`` for ArduPilot's guided waypoint (not part of a mission)."""


def item_target(message: Any) -> tuple[float, float] | None:
    """A guided mission item's point (MISSION_ITEM_INT: degrees times 1e7)."""
    if message.frame not in GLOBAL_FRAMES:
        return None
    if message.get_type() == "MISSION_ITEM_INT":
        return _point(message.x / 1e7, message.y / 1e7)
    return _point(message.x, message.y)


def position_target(message: Any) -> tuple[float, float] | None:
    """SET_POSITION_TARGET_GLOBAL_INT's point, None when its position is masked out."""
    if message.type_mask & POSITION_IGNORED or message.coordinate_frame not in GLOBAL_FRAMES:
        return None
    return _point(message.lat_int / 1e7, message.lon_int / 1e7)


def _point(latitude: float, longitude: float) -> tuple[float, float] | None:
    if not (math.isfinite(latitude) and math.isfinite(longitude)):
        return None
    if latitude == 0 and longitude == 0:
        return None
    if abs(latitude) > 90 or abs(longitude) > 180:
        return None
    return latitude, longitude
