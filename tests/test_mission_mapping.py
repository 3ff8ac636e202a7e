"""One mapping of MAV_CMD and MAV_FRAME numbers to routes and fences (brasidas.mapfiles.mission),
read the same by the station's ``.waypoints`` files and the platform's MAVLink uploads: the same
waypoints, the same refusals (every item named, with the MAV_MISSION_RESULT a ground station's
MISSION_ACK says), the same circles and the same downloads."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from shapely import Polygon

from brasidas.mapfiles.files import read_map, read_route
from brasidas.mapfiles.mission import (
    MavCmd,
    MavFrame,
    MissionRefused,
    MissionResult,
    fence_items,
    fence_shapes,
)
from brasidas.mapfiles.shapes import CIRCLE_VERTICES, MapOptions, assemble_map
from platformd.mavlink.missions import (
    MissionItem,
    fence_from_items,
    items_from_fence,
    route_from_items,
)

CORNERS = [(37.9414, 23.6526), (37.9414, 23.6534), (37.9419, 23.6534), (37.9419, 23.6526)]
HOME = (37.9415, 23.653)


def wpl(*rows: tuple[int, int, float, float, float]) -> str:
    """``QGC WPL 110`` rows of (frame, command, param1, lat, lon), numbered from 0."""
    lines = ["QGC WPL 110"]
    for seq, (frame, command, param1, lat, lon) in enumerate(rows):
        fields = [seq, 0, frame, command, param1, 0, 0, 0, lat, lon, 0, 1]
        lines.append("\t".join(str(v) for v in fields))
    return "\n".join(lines) + "\n"


def wire(*rows: tuple[int, int, float, float, float]) -> list[MissionItem]:
    """The same rows as MISSION_ITEM_INTs received by the endpoint."""
    return [
        MissionItem(seq, frame, command, param1, x=round(lat * 1e7), y=round(lon * 1e7))
        for seq, (frame, command, param1, lat, lon) in enumerate(rows)
    ]


def test_the_numbers_are_mavlinks() -> None:
    for command in MavCmd:
        assert command == getattr(mavlink, f"MAV_CMD_{command.name}"), command
    for frame in MavFrame:
        assert frame == getattr(mavlink, f"MAV_FRAME_{frame.name}"), frame
    for result in MissionResult:
        assert result == getattr(mavlink, f"MAV_MISSION_{result.name}"), result


def test_a_file_and_an_upload_make_the_same_route() -> None:
    rows = [
        (0, 16, 0, *HOME),
        *((3, 16, 0, *corner) for corner in CORNERS),
        (2, 177, 1, 0, 0),  # DO_JUMP to the first waypoint: a loop
    ]
    from_file = read_route(wpl(*rows))
    uploaded = route_from_items(wire(*rows))
    assert uploaded.waypoints == [*CORNERS, CORNERS[0]]
    assert [(w["lat"], w["lon"]) for w in from_file.waypoints] == uploaded.waypoints
    assert uploaded.home == HOME == from_file.home
    assert uploaded.closed


def test_an_upload_names_every_command_it_refuses() -> None:
    rows = [(0, 16, 0, *HOME), (3, 16, 0, *CORNERS[0]), (3, 21, 0, *CORNERS[1]), (3, 22, 0, 0, 0)]
    with pytest.raises(MissionRefused) as refused:
        route_from_items(wire(*rows))
    assert refused.value.result == mavlink.MAV_MISSION_UNSUPPORTED
    assert "item 2: MAV_CMD_NAV_LAND (21)" in str(refused.value)
    assert "item 3: MAV_CMD_NAV_TAKEOFF (22)" in str(refused.value)
    with pytest.raises(MissionRefused, match="MAV_CMD_NAV_LAND .*MAV_CMD_NAV_TAKEOFF"):
        read_route(wpl(*rows))
    # A DO_JUMP anywhere but last: the sequence is wrong, whatever its target.
    with pytest.raises(MissionRefused) as refused:
        route_from_items(wire(rows[0], rows[1], (2, 177, 1, 0, 0), (3, 16, 0, *CORNERS[2])))
    assert refused.value.result == mavlink.MAV_MISSION_INVALID_SEQUENCE


def test_home_at_zero_is_no_home_and_a_waypoint_at_zero_is_refused() -> None:
    rows = [(0, 16, 0, 0, 0), *((3, 16, 0, *corner) for corner in CORNERS)]
    assert read_route(wpl(*rows)).home is None
    assert route_from_items(wire(*rows)).home is None
    with pytest.raises(MissionRefused, match="item 2: waypoint at 0, 0") as refused:
        route_from_items(wire(rows[0], rows[1], (3, 16, 0, 0, 0)))
    assert refused.value.result == mavlink.MAV_MISSION_INVALID_PARAM5_X


def test_a_crossing_fence_polygon_is_refused_at_the_upload() -> None:
    bow_tie = [CORNERS[0], CORNERS[2], CORNERS[1], CORNERS[3]]
    rows = [(0, 5001, 4, *corner) for corner in bow_tie]
    with pytest.raises(MissionRefused, match="item 0 to item 3 .*invalid polygon") as refused:
        fence_from_items(wire(*rows))
    assert refused.value.result == mavlink.MAV_MISSION_INVALID
    with pytest.raises(MissionRefused, match="invalid polygon"):
        read_map(wpl(*rows))
    # A rally point has no place in a fence upload (a file of fence and rally items has).
    rally = [*((0, 5001, 4, *corner) for corner in CORNERS), (0, 5100, 0, *HOME)]
    with pytest.raises(MissionRefused, match="item 4 .*rally point is not a fence item"):
        fence_from_items(wire(*rally))
    assert len(read_map(wpl(*rally)).geojson["features"]) == 2  # the boundary, rally-1


def test_an_exclusion_circle_is_the_same_keepout_from_a_file_and_an_upload() -> None:
    rows = [*((0, 5001, 4, *corner) for corner in CORNERS), (0, 5004, 5.0, *HOME)]
    plan = fence_from_items(wire(*rows))
    assert plan.boundary == tuple(CORNERS)
    (keepout,) = plan.keepouts
    assert len(keepout) == CIRCLE_VERTICES
    found = read_map(wpl(*rows), "fence.waypoints", MapOptions())
    circle = found.geojson["features"][1]["geometry"]["coordinates"][0]
    corners = [value for lon, lat in circle[:-1] for value in (lat, lon)]
    assert corners == pytest.approx([value for corner in keepout for value in corner], abs=1e-8)


def test_the_endpoints_fence_download_is_the_files_fence() -> None:
    rows = [
        *((0, 5001, 4, *corner) for corner in CORNERS),
        *((0, 5002, 3, *corner) for corner in CORNERS[:3]),
    ]
    shapes = fence_shapes([item.read() for item in wire(*rows)])
    area = assemble_map(shapes, MapOptions(), "fence").geojson
    download = items_from_fence(area)
    written = fence_items(area, rally=False)
    assert [(i.command, i.param1, i.latitude, i.longitude) for i in download] == [
        (i.command, i.params[0], pytest.approx(i.latitude), pytest.approx(i.longitude))
        for i in written
    ]
    assert [i.command for i in download] == [5001] * 4 + [5002] * 3
    assert Polygon([(i.longitude, i.latitude) for i in download[:4]]).is_valid
