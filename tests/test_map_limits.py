"""Issue 26, defects 3, 4 and 10: every limit applies to every geometry and is counted before
parsing where the format allows. A 150,001-vertex boundary, a boundary with 9,996 holes, a KML
of 172,000 coordinates and a 25,000-item plan are refused without being parsed or built; a
refused map changes nothing; a 4,000-digit coordinate is a refusal, not an internal error."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import pytest
from support.hostile_files import boundary_map, kml, plan, ring
from support.patrol import LAT, LON, Robot

from brasidas.autonomy import areamap
from brasidas.autonomy.areamap import MAX_VERTICES, MapError, parse_map
from brasidas.codecs.jsonrpc import RpcError
from brasidas.mapfiles import files
from brasidas.mapfiles.errors import FileRefused
from platformd.sim.demo_area import demo_map


def holes(count: int) -> list[list[Any]]:
    return [ring(4, 37.94 + i * 1e-6, 23.65, 1e-7) for i in range(count)]


@pytest.fixture
def nothing_built(monkeypatch: pytest.MonkeyPatch) -> None:
    """Building any geometry fails the test: the refusal must come first."""

    def built(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("a geometry was built before the count refused it")

    monkeypatch.setattr(areamap, "_boundary", built)
    monkeypatch.setattr(areamap, "_keepout", built)


@pytest.mark.usefixtures("nothing_built")
@pytest.mark.parametrize(
    "geojson",
    [
        boundary_map(ring(150_001)),
        boundary_map(ring(100), *holes(9_996)),
    ],
    ids=["150001-vertex boundary", "9996 holes"],
)
def test_the_platform_counts_every_geometry_before_building_any(geojson: Any) -> None:
    with pytest.raises(MapError, match=f"more than {MAX_VERTICES}"):
        parse_map(json.dumps(geojson))


def test_added_keepouts_are_counted_before_they_are_built(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    area = parse_map(demo_map(LAT, LON))
    huge = {
        "type": "Feature",
        "properties": {"role": "keepout"},
        "geometry": {"type": "Polygon", "coordinates": [ring(MAX_VERTICES, LAT, LON, 1e-5)]},
    }
    monkeypatch.setattr(areamap, "_keepout", lambda *a: (_ for _ in ()).throw(AssertionError()))
    with pytest.raises(MapError, match=f"more than {MAX_VERTICES}"):
        area.with_keepouts(add=[huge])


@pytest.fixture
def nothing_parsed(monkeypatch: pytest.MonkeyPatch) -> None:
    def parsed(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("the file was parsed before the count refused it")

    monkeypatch.setattr(files, "parse_xml", parsed)
    monkeypatch.setattr(files, "loads", parsed)


@pytest.mark.usefixtures("nothing_parsed")
def test_the_station_counts_a_files_vertices_and_items_before_parsing() -> None:
    with pytest.raises(FileRefused, match="vertices, more than"):
        files.read_map(json.dumps(boundary_map(ring(150_001))), "big.geojson")
    with pytest.raises(FileRefused, match="vertices, more than"):
        files.read_map(kml(172_000), "big.kml")
    with pytest.raises(FileRefused, match="25000 mission items, more than"):
        files.read_route(plan(25_000), "big.plan")


def test_a_plan_with_more_waypoints_than_a_route_takes_is_refused_at_the_station() -> None:
    with pytest.raises(FileRefused, match="1500 waypoints, more than 1000"):
        files.read_route(plan(1_500), "long.plan")


def test_a_4000_digit_coordinate_is_a_refusal() -> None:
    big = "1" + "0" * 4000
    boundary = json.dumps(boundary_map(ring(8))).replace("23.651", big, 1)
    assert big in boundary
    with pytest.raises(FileRefused, match="4001 digits"):
        files.read_map(boundary, "x.geojson")
    with pytest.raises(FileRefused, match="4001 digits"):
        files.read_route(f"[[{big}, 23.6]]", "x.json")
    boundary = json.dumps(boundary_map(ring(8))).replace("23.651", "1e400", 1)
    with pytest.raises(FileRefused):
        files.read_map(boundary, "x.geojson")


async def test_a_refused_map_changes_nothing_on_the_platform(robot_factory: Any) -> None:
    robot: Robot = await robot_factory()
    await robot.call("set_waypoints", waypoints=["sw", "se"])
    before = await robot.call("get_map")
    with pytest.raises(RpcError, match=f"more than {MAX_VERTICES}"):
        await robot.call("load_map", map=boundary_map(ring(25_000, LAT, LON)))
    assert await robot.call("get_map") == before  # the map and its waypoints stay


def test_a_big_control_request_is_recorded_cut_not_serialized_whole() -> None:
    from platformd.authority import ITEMS_KEPT, _shortened

    big = boundary_map(ring(150_001))
    cut = _shortened({"map": big})
    coordinates = cut["map"]["features"][0]["geometry"]["coordinates"][0]
    assert len(coordinates) == ITEMS_KEPT + 1
    assert coordinates[-1] == "... 149938 more"
    assert big["features"][0]["geometry"]["coordinates"][0][0] == coordinates[0]


async def test_a_large_request_is_parsed_off_the_loop_to_the_same_answer() -> None:
    from brasidas.codecs.jsonrpc import LARGE_MESSAGE_BYTES, Dispatcher

    dispatcher = Dispatcher()
    big = {
        "jsonrpc": "2.0",
        "id": 1,
        "method": "load_map",
        "params": {"map": boundary_map(ring(30_000))},
    }
    text = json.dumps(big)
    assert len(text) > LARGE_MESSAGE_BYTES
    off_loop = await dispatcher.parse_off_loop(text)
    assert off_loop.message == dispatcher.parse(text).message == big
    for bad in (text.replace("23.65", "NaN", 1), "[" * 200_000 + " " * LARGE_MESSAGE_BYTES):
        refused = await dispatcher.parse_off_loop(bad)
        assert refused.message is None
        assert refused.parse_error is not None


async def test_a_sessions_heartbeat_is_answered_while_its_large_request_is_parsed(
    platform_factory: Any, fleet_key: bytes
) -> None:
    from conftest import quiet_platform_config
    from support.velocity import open_connection

    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    conn = await open_connection(daemon, fleet_key)
    finished: list[str] = []

    async def call(method: str, **params: Any) -> None:
        try:
            await conn.call(method, **params)
        except RpcError:
            pass  # load_map without a map module, or refused: its answer is what counts
        finished.append(method)

    try:
        big = boundary_map(ring(60_000, LAT, LON))  # ~1.4 MB: parsed in a worker thread
        async with asyncio.TaskGroup() as group:
            group.create_task(call("load_map", map=big))
            await asyncio.sleep(0)  # sent first
            group.create_task(call("heartbeat"))
        assert finished == ["heartbeat", "load_map"]
    finally:
        await conn.close()


def test_file_text_keeps_the_c_parser_and_a_maps_numbers_go_off_the_loop() -> None:
    from brasidas.codecs.jsonrpc import escape_heavy

    lines = [f'  <node id="{i}" lat="37.94{i:05d}" lon="23.65{i:05d}"/>' for i in range(20_000)]
    text = "<osm>\n" + "\n".join(lines) + "\n</osm>\n"
    file_import = json.dumps({"method": "map_import", "params": {"text": text}})
    assert escape_heavy(file_import)
    assert escape_heavy(file_import.encode())
    map_load = json.dumps({"method": "load_map", "params": {"map": boundary_map(ring(20_000))}})
    assert not escape_heavy(map_load)
    assert not escape_heavy(map_load.encode())
