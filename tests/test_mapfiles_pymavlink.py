"""Our mission, fence and rally files against a real third-party reader and writer: pymavlink's
``mavwp`` (MAVProxy's loaders). It runs in a child process (its MAVLink 2 setting and dialect
are process-wide), reading what we write and writing what we read."""

from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path
from typing import Any

from brasidas.autonomy.areamap import parse_map
from brasidas.autonomy.route import parse_waypoints
from brasidas.mapfiles.files import read_map, read_route, write_route

DATA = Path(__file__).parent / "data" / "mapfiles"
ROUTE = [
    {"lat": 37.9414, "lon": 23.6526},
    {"lat": 37.9414, "lon": 23.6534},
    {"lat": 37.9419, "lon": 23.6534},
    {"lat": 37.9414, "lon": 23.6526},
]
PYMAVLINK = r"""
import json, sys
from pymavlink import mavutil, mavwp
work = sys.argv[1]
out = {}
# pymavlink reads ours.
loader = mavwp.MAVWPLoader()
loader.load(f"{work}/ours.waypoints")
out["mission"] = [[w.seq, w.frame, w.command, w.x, w.y] for w in loader.wpoints]
fence = mavwp.MissionItemProtocol_Fence()
fence.load(sys.argv[2] + "/fence.waypoints")
out["fence"] = [[w.command, w.param1] for w in fence.wpoints]
old = mavwp.MAVFenceLoader()
out["old_fence"] = old.load(sys.argv[2] + "/old.fen")
rally = mavwp.MAVRallyLoader()
out["rally"] = rally.load(sys.argv[2] + "/rally.txt") or rally.rally_count()
# pymavlink writes; we read.
m = mavutil.mavlink
mission = mavwp.MAVWPLoader()
def item(seq, frame, command, p1=0, p2=0, lat=0, lon=0):
    return m.MAVLink_mission_item_message(0, 0, seq, frame, command, 0, 1, p1, p2, 0, 0, lat, lon, 0, 0)
mission.add(item(0, 0, 16, lat=37.9415, lon=23.653), comment="home")
for lat, lon in [(37.9414, 23.6526), (37.9414, 23.6534), (37.9419, 23.6534)]:
    mission.add(item(0, 3, 16, lat=lat, lon=lon))
mission.add(item(0, 2, 177, p1=1, p2=-1), comment="loop")
mission.save(f"{work}/theirs.waypoints")
points = mavwp.MAVFenceLoader()
for lat, lon in [(37.9415, 23.653), (37.941, 23.6524), (37.941, 23.6536), (37.942, 23.6536),
                 (37.942, 23.6524), (37.941, 23.6524)]:
    points.add_latlon(lat, lon)
points.save(f"{work}/theirs.fen")
rallies = mavwp.MAVRallyLoader()
rallies.create_and_append_rally_point(37.9411 * 1e7, 23.6525 * 1e7, 15, 0, 0, 0)
rallies.save(f"{work}/theirs.rally")
print(json.dumps(out))
"""


async def pymavlink(work: Path) -> dict[str, Any]:
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-c",
        PYMAVLINK,
        str(work),
        str(DATA),
        env={"MAVLINK20": "1", "MAVLINK_DIALECT": "ardupilotmega", "PATH": "/usr/bin:/bin"},
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(process.communicate(), 120)
    assert process.returncode == 0, err.decode()
    result: dict[str, Any] = json.loads(out.decode().strip().splitlines()[-1])
    return result


async def test_pymavlink_reads_our_files_and_we_read_its_files(tmp_path: Path) -> None:
    text = write_route("waypoints", ROUTE, (37.9415, 23.653))
    await asyncio.to_thread((tmp_path / "ours.waypoints").write_text, text)
    seen = await pymavlink(tmp_path)

    # Ours, as MAVProxy sees it: home at 0, NAV_WAYPOINTs at relative altitude, and a closed
    # route's DO_JUMP back to item 1 (for ever) in place of its last waypoint.
    assert [row[:3] for row in seen["mission"]] == [[0, 0, 16]] + [
        [i, 3, 16] for i in range(1, 4)
    ] + [[4, 2, 177]]
    assert [(row[3], row[4]) for row in seen["mission"][1:4]] == [
        (w["lat"], w["lon"]) for w in ROUTE[:3]
    ]
    # Our hand-written samples parse there too: 1 return point, 4+4 polygon vertices, a circle.
    assert seen["fence"] == [[5000, 0.0]] + [[5001, 4.0]] * 4 + [[5002, 4.0]] * 4 + [[5004, 6.0]]
    assert seen["old_fence"] == 6
    assert seen["rally"] == 2

    # Theirs, as we see it: home left out, the DO_JUMP to 1 closes the route.
    theirs = read_route(await asyncio.to_thread((tmp_path / "theirs.waypoints").read_text))
    assert theirs.home == (37.9415, 23.653)
    assert parse_waypoints(theirs.waypoints).closed
    assert len(theirs.waypoints) == 4
    fence_text = await asyncio.to_thread((tmp_path / "theirs.fen").read_text)
    rally_text = await asyncio.to_thread((tmp_path / "theirs.rally").read_text)
    area = parse_map(read_map(fence_text + rally_text).geojson)
    assert area.summary()["points"] == ["fence-return", "rally-1"]
    assert (
        area.boundary.area
        == parse_map(read_map((DATA / "old.fen").read_text()).geojson).boundary.area
    )
