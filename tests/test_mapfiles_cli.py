"""``brasidas-station map`` / ``route`` with the files users have (issues 21, 22 item 7), through
the station daemon to a --sim platform: the sample files in tests/data/mapfiles/, written by
hand from the formats' documentation."""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable
from pathlib import Path

from support.cli import run_cli
from support.connected import connected

from brasidas.mapfiles.files import read_route
from platformd.app import PlatformDaemon
from stationd.daemon import StationDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]
DATA = Path(__file__).parent / "data" / "mapfiles"


async def test_a_nan_in_a_route_file_is_refused_without_a_traceback(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    await connected(station, platform_factory, fleet_key, tmp_path)
    for name, text, why in [
        ("nan.json", "[[37.9414, 23.6526], [NaN, 23.6534]]", "NaN is not a number JSON allows"),
        ("inf.json", "[[37.9414, 23.6526], [1e999, 23.6534]]", "waypoint 1: inf, 23.6534"),
        ("nan.txt", "37.9414,23.6526\nnan,23.6534\n", "line 2: nan, 23.6534"),
    ]:
        (tmp_path / name).write_text(text)
        code, out, err = await run_cli(station, "route", "rover-7", str(tmp_path / name))
        assert code == 1, (name, out, err)
        assert why in err, (name, out, err)
        assert "Traceback" not in err


async def test_mission_files_in_and_out(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    await connected(station, platform_factory, fleet_key, tmp_path)
    code, out, err = await run_cli(
        station,
        "map",
        "rover-7",
        str(DATA / "field.kml"),
        "--boundary",
        "field",
        "--keepouts",
        "barn",
    )
    assert code == 0, err
    assert "map 'field' loaded (KML)" in out
    assert "1 keep-out zones, 1 named points" in out
    assert "note: 1 LineStrings not used" in out

    # A QGC plan: home is not a waypoint, the DO_JUMP back to the first closes the route; with
    # --fence its exclusion polygon and circle become keep-outs, its inclusion fence is checked.
    code, out, err = await run_cli(
        station, "route", "rover-7", str(DATA / "field.plan"), "--fence", "--json"
    )
    assert code == 0, err
    answer = json.loads(out)
    assert answer["closed"] is True
    assert len(answer["waypoints"]) == 5
    assert answer["keepouts_added"] == ["fence-2", "fence-circle-1"]
    assert any(
        "planned home 37.9415000, 23.6530000 is not a waypoint" in n for n in answer["notes"]
    )
    area = await station.ctx.api.call_local("map_get", platform_id="rover-7")
    keepouts = [
        f["id"] for f in area["map"]["features"] if f["properties"].get("role") == "keepout"
    ]
    assert keepouts == ["barn", "fence-2", "fence-circle-1"]

    # Row 0 of a .waypoints file is home; three rows after it are an open route.
    code, out, err = await run_cli(station, "route", "rover-7", str(DATA / "mission.waypoints"))
    assert code == 0, err
    assert "3 waypoints set from QGC WPL 110 (open" in out
    assert "is home" in out
    assert "note: altitudes ignored" in out

    # Commands we cannot fly: refused, each named, the route unchanged.
    code, _, err = await run_cli(station, "route", "rover-7", str(DATA / "takeoff.waypoints"))
    assert code == 1
    assert "MAV_CMD_NAV_TAKEOFF (22)" in err
    assert "MAV_CMD_DO_SET_SERVO (183)" in err
    area = await station.ctx.api.call_local("map_get", platform_id="rover-7")
    assert len(area["route"]) == 3

    # Text lines with tabs, spaces, an altitude, a [lat, lon, alt] list.
    code, out, err = await run_cli(station, "route", "rover-7", str(DATA / "route.txt"))
    assert code == 0, err
    assert "4 waypoints set from text" in out, err

    # Written back: .plan and .waypoints read again as the same route.
    for name in ("out.plan", "out.waypoints"):
        code, out, err = await run_cli(
            station, "route", "rover-7", "--export", str(tmp_path / name)
        )
        assert code == 0, err
        assert "4 waypoints written" in out, err
        again = read_route((tmp_path / name).read_text(), name)
        assert again.waypoints == read_route((DATA / "route.txt").read_text()).waypoints
        code, out, err = await run_cli(station, "route", "rover-7", str(tmp_path / name))
        assert code == 0, err
        assert "4 waypoints set" in out, err
    plan = json.loads((tmp_path / "out.plan").read_text())
    assert plan["fileType"] == "Plan"
    assert plan["mission"]["vehicleType"] == 10
    assert [p["inclusion"] for p in plan["geoFence"]["polygons"]] == [True, False, False, False]

    # Longitude first: refused as swapped, against the map's boundary.
    (tmp_path / "swapped.txt").write_text("23.6526,37.9414\n23.6534,37.9414\n")
    code, _, err = await run_cli(station, "route", "rover-7", str(tmp_path / "swapped.txt"))
    assert code == 1
    assert "latitude and longitude look swapped" in err


async def test_map_formats_through_the_cli(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    await connected(station, platform_factory, fleet_key, tmp_path)

    async def load(*argv: str) -> tuple[int, str, str]:
        return await run_cli(station, "map", "rover-7", *argv)

    code, out, err = await load(str(DATA / "field.plan"))
    assert code == 0, err
    assert "(QGC plan)" in out, err
    assert "2 keep-out zones, 1 named points" in out, err
    code, out, err = await load(str(DATA / "fence.waypoints"))
    assert code == 0, err
    assert "(QGC WPL 110 fence)" in out, err
    assert "2 keep-out zones" in out, err
    code, out, err = await load(str(DATA / "old.fen"))
    assert code == 0, err
    assert "(ArduPilot fence/rally)" in out, err
    assert "1 named points" in out, err
    code, out, err = await load(str(DATA / "buildings.osm"), "--boundary-bbox")
    assert code == 0, err
    assert "(OpenStreetMap XML)" in out, err
    assert "2 keep-out zones" in out, err
    assert "note: 1 open ways" in out

    # Polygons without roles: the operator says which is which, else it is refused naming them.
    code, _, err = await load(str(DATA / "plain.geojson"))
    assert code == 1
    assert "which polygon is the boundary?" in err
    assert "0: polygon yard" in err
    code, out, err = await load(
        str(DATA / "plain.geojson"), "--boundary", "landuse=farmyard", "--keepouts", "building=*"
    )
    assert code == 0, err
    assert "1 keep-out zones, 1 named points" in out, err

    # [lat, lon] where GeoJSON has [lon, lat]: the robot is inside only swapped: refused.
    swapped = json.loads((DATA / "plain.geojson").read_text())
    for feature in swapped["features"]:
        geometry = feature["geometry"]
        if geometry["type"] == "Polygon":
            geometry["coordinates"] = [[[y, x] for x, y in r] for r in geometry["coordinates"]]
    (tmp_path / "swapped.geojson").write_text(json.dumps(swapped))
    code, _, err = await load(
        str(tmp_path / "swapped.geojson"), "--boundary", "yard", "--keepouts", "none"
    )
    assert code == 1
    assert "latitude and longitude look swapped" in err

    # Hostile XML: an entity declaration is refused before anything is expanded.
    (tmp_path / "laughs.kml").write_text(
        '<?xml version="1.0"?><!DOCTYPE kml [<!ENTITY a "aaaaaaaaaa">]><kml>&a;</kml>'
    )
    code, _, err = await load(str(tmp_path / "laughs.kml"))
    assert code == 1
    assert "entities are refused" in err


async def test_big_files_up_to_the_limit_pass_the_station_and_bigger_are_refused(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    await connected(station, platform_factory, fleet_key, tmp_path)
    code, _, err = await run_cli(station, "map", "rover-7", str(DATA / "field.plan"))
    assert code == 0, err
    plan = (DATA / "field.plan").read_text()
    big = tmp_path / "big.plan"  # 3 MiB of line breaks: 6 MiB as the JSON string the API carries
    big.write_text(plan.replace('"version": 1,', '"version": 1,' + "\n" * (3 * 1024 * 1024), 1))
    code, out, err = await run_cli(station, "route", "rover-7", str(big))
    assert code == 0, err
    assert "5 waypoints set from QGC plan (closed" in out, err
    huge = tmp_path / "huge.plan"
    huge.write_text(plan + " " * (4 * 1024 * 1024))
    code, _, err = await run_cli(station, "route", "rover-7", str(huge))
    assert code == 1
    assert "huge.plan: " in err
    assert "over the limit of 4194304 bytes" in err
    (tmp_path / "latin1.txt").write_bytes("37.9414,23.6526 # caf\xe9\n".encode("latin-1"))
    code, _, err = await run_cli(station, "route", "rover-7", str(tmp_path / "latin1.txt"))
    assert code == 1
    assert "not UTF-8 text" in err
    (tmp_path / "field.kmz").write_bytes(b"PK\x03\x04" + bytes(range(256)))
    code, _, err = await run_cli(station, "map", "rover-7", str(tmp_path / "field.kmz"))
    assert code == 1
    assert "field.kmz: a zip archive (a KMZ?)" in err


async def test_a_fence_route_refused_leaves_no_keepouts_behind(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    await connected(station, platform_factory, fleet_key, tmp_path)
    code, _, err = await run_cli(
        station,
        "map",
        "rover-7",
        str(DATA / "field.kml"),
        "--boundary",
        "field",
        "--keepouts",
        "none",
    )
    assert code == 0, err
    plan = json.loads((DATA / "field.plan").read_text())
    del plan["geoFence"]["polygons"][0]  # no inclusion fence; a waypoint in its circle
    plan["mission"]["items"][0]["params"][4:6] = [37.9412, 23.6530]
    (tmp_path / "into.plan").write_text(json.dumps(plan))
    code, _, err = await run_cli(
        station, "route", "rover-7", str(tmp_path / "into.plan"), "--fence"
    )
    assert code == 1, err
    assert "keep-out zone 'fence-circle-1'" in err, err
    area = await station.ctx.api.call_local("map_get", platform_id="rover-7")
    assert [
        f.get("id") for f in area["map"]["features"] if f["properties"].get("role") == "keepout"
    ] == []


def village(buildings: int) -> str:
    """An Overpass export of small buildings on a grid in the sample field."""
    elements: list[dict[str, object]] = []
    for k in range(buildings):
        lon, lat = 23.6525 + (k % 20) * 5e-5, 37.9411 + (k // 20) * 4e-5
        ring = [(lon, lat), (lon + 2e-5, lat), (lon + 2e-5, lat + 2e-5), (lon, lat + 2e-5)]
        base = 10 * k
        elements += [
            {"type": "node", "id": base + i, "lat": y, "lon": x} for i, (x, y) in enumerate(ring)
        ]
        nodes = [base, base + 1, base + 2, base + 3, base]
        elements.append({"type": "way", "id": k, "nodes": nodes, "tags": {"building": "house"}})
    bounds = {"minlat": 37.941, "minlon": 23.6524, "maxlat": 37.942, "maxlon": 23.6536}
    return json.dumps({"elements": elements, "bounds": bounds})


async def test_a_map_bigger_than_the_platform_takes_is_refused_at_the_station(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    """Sent as it is, the platform would drop the connection on the oversized request: the
    station reads the limit the platform announces."""
    await connected(
        station, platform_factory, fleet_key, tmp_path, "signaling.max_request_bytes=65536"
    )
    (tmp_path / "village.json").write_text(village(400))
    code, _, err = await run_cli(
        station, "map", "rover-7", str(tmp_path / "village.json"), "--boundary-bbox"
    )
    assert code == 1, err
    assert "more than the platform takes in one request (64 KiB" in err, err
    (tmp_path / "hamlet.json").write_text(village(100))
    code, out, err = await run_cli(
        station, "map", "rover-7", str(tmp_path / "hamlet.json"), "--boundary-bbox"
    )
    assert code == 0, err
    assert "100 keep-out zones" in out, err
