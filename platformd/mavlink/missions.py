"""Mission and fence items on the wire ↔ the patrol's route and the map's geometry.

What the numbers mean (commands, frames, home at seq 0, the closing DO_JUMP, fence polygons,
circles and the return point, the refusals and their ``MAV_MISSION_RESULT``) is decided in one
place, :mod:`brasidas.mapfiles.mission`, which the station's ``.plan`` and ``.waypoints`` files
use too; here only MISSION_ITEM_INT's form (seq, x and y in degrees times 1e7) is translated.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.autonomy.geo import to_e7
from brasidas.autonomy.route import MAX_WAYPOINTS
from brasidas.mapfiles import mission
from brasidas.mapfiles.mission import (
    FencePlan,
    MavCmd,
    MissionRefused,
    MissionRoute,
    command_name,
)

__all__ = [
    "DO_JUMP",
    "FENCE",
    "FENCE_EXCLUSION_CIRCLE",
    "FENCE_EXCLUSION_VERTEX",
    "FENCE_INCLUSION_CIRCLE",
    "FENCE_INCLUSION_VERTEX",
    "FENCE_RETURN_POINT",
    "MAX_ITEMS",
    "MISSION",
    "RALLY",
    "WAYPOINT",
    "FencePlan",
    "MissionItem",
    "MissionRefused",
    "command_name",
    "fence_from_items",
    "items_from_fence",
    "items_from_route",
    "route_from_items",
]

MISSION = mavlink.MAV_MISSION_TYPE_MISSION
FENCE = mavlink.MAV_MISSION_TYPE_FENCE
RALLY = mavlink.MAV_MISSION_TYPE_RALLY

MAX_ITEMS = MAX_WAYPOINTS
"""The longest mission or fence accepted (the route's own limit)."""

WAYPOINT = MavCmd.NAV_WAYPOINT
DO_JUMP = MavCmd.DO_JUMP
FENCE_RETURN_POINT = MavCmd.NAV_FENCE_RETURN_POINT
FENCE_INCLUSION_VERTEX = MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION
FENCE_EXCLUSION_VERTEX = MavCmd.NAV_FENCE_POLYGON_VERTEX_EXCLUSION
FENCE_INCLUSION_CIRCLE = MavCmd.NAV_FENCE_CIRCLE_INCLUSION
FENCE_EXCLUSION_CIRCLE = MavCmd.NAV_FENCE_CIRCLE_EXCLUSION


@dataclass(frozen=True)
class MissionItem:
    """One MISSION_ITEM_INT's content (x, y in degrees times 1e7, as on the wire): what an
    upload received, kept to be downloaded back verbatim."""

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

    def read(self) -> mission.MissionItem:
        """The item as the one mapping reads it (named ``item SEQ`` in refusals)."""
        return mission.MissionItem(
            f"item {self.seq}",
            self.command,
            self.frame,
            (self.param1, self.param2, self.param3, self.param4),
            self.latitude,
            self.longitude,
            self.z,
        )

    @classmethod
    def written(cls, seq: int, item: mission.MissionItem) -> MissionItem:
        return cls(
            seq,
            item.frame,
            item.command,
            *item.params,
            x=to_e7(item.latitude),
            y=to_e7(item.longitude),
            z=item.altitude,
        )


def route_from_items(items: list[MissionItem], *, skip_unsupported: bool = False) -> MissionRoute:
    """The route of an uploaded mission (item 0 is home when it looks like home: see
    :func:`~brasidas.mapfiles.mission.looks_like_home`; none but home clears the route);
    raises :class:`MissionRefused`."""
    read = [item.read() for item in items]
    return mission.route_from_items(
        read,
        home_first=bool(read) and mission.looks_like_home(read[0]),
        jump_target=mission.seq_jump_target(read),
        empty_ok=True,
        skip_unsupported=skip_unsupported,
    )


def route_index(waypoint_seqs: tuple[int, ...], seq: int) -> int:
    """The route waypoint of mission item ``seq`` (item 0 is home without ``waypoint_seqs``;
    an item that is no waypoint: the next waypoint's)."""
    if not waypoint_seqs:
        return seq - 1
    for index, waypoint_seq in enumerate(waypoint_seqs):
        if waypoint_seq >= seq:
            return index
    return -1


def fence_from_items(items: list[MissionItem], *, union: bool = False) -> FencePlan:
    """The geometry of an uploaded fence (``union``: several inclusion polygons make their
    union, FENCE_OPTIONS bit 1); raises :class:`MissionRefused`."""
    return mission.fence_plan([item.read() for item in items], union=union)


def items_from_route(
    waypoints: list[tuple[float, float]],
    home: tuple[float, float] | None,
    laps: int | None = None,
) -> list[MissionItem]:
    """A route as mission items: home at 0 (the first waypoint when there is no home yet),
    then one NAV_WAYPOINT per waypoint (a closed route: a DO_JUMP back instead of its last)."""
    home = home if home is not None else (waypoints[0] if waypoints else (0.0, 0.0))
    return _written(mission.mission_items(waypoints, home, laps))


def items_from_fence(area: dict[str, Any]) -> list[MissionItem]:
    """The map's boundary and keep-outs (its canonical GeoJSON) as fence items."""
    return _written(mission.fence_items(area, rally=False))


def _written(items: list[mission.MissionItem]) -> list[MissionItem]:
    return [MissionItem.written(seq, item) for seq, item in enumerate(items)]
