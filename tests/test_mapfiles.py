"""The map and route file readers (sans-IO): each format from our own samples or built here,
and every refusal naming what it refuses."""

from __future__ import annotations

import json
import math
import random
from pathlib import Path
from typing import Any

import pytest
from shapely import Polygon

from brasidas.autonomy.areamap import parse_map
from brasidas.autonomy.route import parse_waypoints
from brasidas.mapfiles import MAX_FILE_BYTES, FileRefused
from brasidas.mapfiles.files import (
    MapOptions,
    RouteImport,
    check_map_order,
    check_route_order,
    read_map,
    read_route,
    write_route,
)
from brasidas.mapfiles.mission import command_name
from brasidas.mapfiles.shapes import CIRCLE_VERTICES

DATA = Path(__file__).parent / "data" / "mapfiles"
FIELD = [
    [23.6524, 37.941],
    [23.6536, 37.941],
    [23.6536, 37.942],
    [23.6524, 37.942],
    [23.6524, 37.941],
]
ROBOT = (37.9415, 23.653)


def square(lon: float, lat: float, size: float) -> list[list[float]]:
    return [[lon, lat], [lon + size, lat], [lon + size, lat + size], [lon, lat + size], [lon, lat]]


def feature(geometry: dict[str, Any], **properties: Any) -> dict[str, Any]:
    return {"type": "Feature", "properties": properties, "geometry": geometry}


def polygon(*rings: list[list[float]]) -> dict[str, Any]:
    return {"type": "Polygon", "coordinates": list(rings)}


def wpl(*rows: str) -> str:
    return "QGC WPL 110\n" + "\n".join(rows) + "\n"


def row(seq: int, frame: int, command: int, *params: float, lat: float = 0, lon: float = 0) -> str:
    p = [*params, 0, 0, 0, 0][:4]
    return "\t".join(str(v) for v in [seq, 0, frame, command, *p, lat, lon, 0, 1])


HOME = row(0, 0, 16, lat=37.9415, lon=23.653)


def test_every_sample_map_loads_as_a_valid_canonical_map() -> None:
    cases = {
        "field.plan": MapOptions(),
        "fence.waypoints": MapOptions(),
        "old.fen": MapOptions(),
        "field.kml": MapOptions(boundary="field", keepouts="barn"),
        "buildings.osm": MapOptions(boundary_bbox=True),
        "plain.geojson": MapOptions(boundary="0", keepouts="rest"),
    }
    for name, options in cases.items():
        found = read_map((DATA / name).read_text(), name, options)
        area = parse_map(found.geojson)  # what the platform will check
        assert area.inside(*area.local(*ROBOT)), name
        assert area.name == Path(name).stem or name == "plain.geojson"


def test_a_bare_geometry_a_single_feature_and_a_multipolygon_area() -> None:
    bare = read_map(json.dumps(polygon(FIELD)))
    assert bare.format == "GeoJSON"
    assert "the file's only polygon" in bare.notes[0]
    single = read_map(json.dumps(feature(polygon(FIELD), name="yard")))
    assert parse_map(single.geojson).boundary.area == pytest.approx(11708, rel=0.01)
    one_part = {"type": "MultiPolygon", "coordinates": [[FIELD]]}
    assert read_map(json.dumps(one_part)).geojson["features"][0]["geometry"]["type"] == "Polygon"
    two = {"type": "MultiPolygon", "coordinates": [[FIELD], [square(23.66, 37.95, 0.001)]]}
    with pytest.raises(FileRefused, match="the MultiPolygon has 2 separate parts|2 separate parts"):
        read_map(json.dumps(two))
    # ...but a MultiPolygon keep-out is one keep-out.
    collection = {
        "type": "FeatureCollection",
        "features": [
            feature(polygon(FIELD), role="boundary"),
            feature(
                {
                    "type": "MultiPolygon",
                    "coordinates": [
                        [square(23.6525, 37.9411, 0.0001)],
                        [square(23.6533, 37.9418, 0.0001)],
                    ],
                },
                name="sheds",
            ),
        ],
    }
    found = read_map(json.dumps(collection), options=MapOptions(keepouts="sheds"))
    assert parse_map(found.geojson).summary()["keepouts"] == ["sheds"]


def test_selectors_by_number_id_name_and_property_and_refusals_naming_the_features() -> None:
    text = (DATA / "plain.geojson").read_text()
    with pytest.raises(FileRefused) as refused:
        read_map(text)
    assert "0: polygon yard" in str(refused.value)
    assert "1: polygon barn" in str(refused.value)
    with pytest.raises(FileRefused, match="feature 1 \\('barn'\\): polygons without a role"):
        read_map(text, options=MapOptions(boundary="yard"))
    for boundary, keepouts in [
        ("0", "1"),
        ("yard", "barn"),
        ("id=yard", "building=barn"),
        ("landuse=*", "rest"),
    ]:
        found = read_map(text, options=MapOptions(boundary, keepouts))
        assert parse_map(found.geojson).summary()["keepouts"] == ["barn"], (boundary, keepouts)
    found = read_map(text, options=MapOptions("yard", "none"))
    assert parse_map(found.geojson).summary()["keepouts"] == []
    with pytest.raises(FileRefused, match="--boundary 'stable' matches nothing; the file has: 0"):
        read_map(text, options=MapOptions(boundary="stable"))
    with pytest.raises(FileRefused, match="not both"):
        read_map(text, options=MapOptions(boundary="yard", boundary_bbox=True))


def test_several_inclusion_fences_make_their_intersection_the_boundary() -> None:
    west = square(23.6524, 37.941, 0.001)
    east = square(23.6529, 37.941, 0.001)
    plan = {
        "fileType": "Plan",
        "geoFence": {
            "polygons": [
                {"inclusion": True, "polygon": [[lat, lon] for lon, lat in west[:-1]]},
                {"inclusion": True, "polygon": [[lat, lon] for lon, lat in east[:-1]]},
            ],
            "circles": [{"inclusion": False, "circle": {"center": [37.9412, 23.653], "radius": 5}}],
        },
    }
    found = read_map(json.dumps(plan))
    boundary = Polygon(found.geojson["features"][0]["geometry"]["coordinates"][0])
    assert boundary.bounds == pytest.approx((23.6529, 37.941, 23.6534, 37.942))
    assert "the intersection of" in found.notes[-1]
    circle = found.geojson["features"][1]
    assert len(circle["geometry"]["coordinates"][0]) == CIRCLE_VERTICES + 1
    apart = json.loads(json.dumps(plan))
    apart["geoFence"]["polygons"][1]["polygon"] = [
        [lat + 0.01, lon] for lat, lon in apart["geoFence"]["polygons"][1]["polygon"]
    ]
    with pytest.raises(FileRefused, match="do not overlap in one area"):
        read_map(json.dumps(apart))


def test_fence_files_refuse_what_they_cannot_be() -> None:
    with pytest.raises(
        FileRefused, match="a inclusion polygon of 4 vertices has 3|of 4 vertices has 3"
    ):
        read_map(
            wpl(
                *(
                    row(i, 0, 5001, 4, lat=37.941 + i * 1e-4, lon=23.652 + (i % 2) * 1e-3)
                    for i in range(3)
                )
            )
        )
    with pytest.raises(
        FileRefused, match=r"row 1 .*: MAV_CMD_WAYPOINT_USER_1 \(31000\) is not a fence item"
    ):
        read_map(wpl(row(0, 0, 5000, lat=37.94, lon=23.65), row(1, 0, 31000, lat=37.94, lon=23.65)))
    with pytest.raises(FileRefused, match="radius 0.1 m is not between"):
        read_map(wpl(row(0, 0, 5003, 0.1, lat=37.94, lon=23.65)))
    rally = wpl(*(row(i, 0, 5100, lat=37.9411 + i * 1e-4, lon=23.6525) for i in range(2)))
    with pytest.raises(FileRefused, match="which polygon is the boundary"):
        read_map(rally)  # rally points alone are not a map
    combined = (DATA / "old.fen").read_text() + (DATA / "rally.txt").read_text()
    found = read_map(combined)
    assert parse_map(found.geojson).summary()["points"] == ["fence-return", "rally-1", "rally-2"]


def test_kml_osm_and_overpass() -> None:
    kml = (DATA / "field.kml").read_text()
    found = read_map(kml, options=MapOptions(boundary="field", keepouts="rest"))
    assert parse_map(found.geojson).summary() | {"origin": None} == {
        "name": "",
        "origin": None,
        "area_m2": pytest.approx(11708, rel=0.01),
        "keepouts": ["barn"],
        "points": ["gate"],
        "vertices": 10,
        "notes": [],
    }
    multi = kml.replace("<Polygon>", "<MultiGeometry><Polygon>", 1).replace(
        "</Polygon>", "</Polygon></MultiGeometry>", 1
    )
    assert read_map(multi, options=MapOptions(boundary="field", keepouts="barn")).geojson
    overpass = {
        "elements": [
            *(
                {"type": "node", "id": n, "lat": lat, "lon": lon}
                for n, (lon, lat) in enumerate(square(23.6532, 37.9417, 1e-4)[:-1])
            ),
            {"type": "way", "id": 7, "nodes": [0, 1, 2, 3, 0], "tags": {"building": "yes"}},
            {
                "type": "way",
                "id": 8,
                "geometry": [{"lat": lat, "lon": lon} for lon, lat in FIELD],
                "nodes": [10, 11, 12, 13, 10],
                "tags": {"landuse": "meadow"},
            },
        ]
    }
    found = read_map(json.dumps(overpass), options=MapOptions(boundary="landuse=meadow"))
    assert found.format == "Overpass JSON"
    assert parse_map(found.geojson).summary()["keepouts"] == ["way/7"]
    # A box export cuts ways at its edge (their outer nodes are not in the file): each is
    # left out and named, not the whole file refused.
    cut = read_map(
        (DATA / "buildings.osm").read_text().replace('<node id="4"', '<node id="44"'),
        options=MapOptions(boundary_bbox=True),
    )
    assert any(
        "ways cut at the export's edge left out: way 100" in note
        and "node 4 not in the file" in note
        for note in cut.notes
    ), cut.notes
    assert "way/100" not in parse_map(cut.geojson).summary()["keepouts"]


@pytest.mark.parametrize(
    "text",
    [
        '<?xml version="1.0"?><!DOCTYPE lolz [<!ENTITY lol "lol"><!ENTITY lol2 "&lol;&lol;">]><kml>&lol2;</kml>',
        '<!DOCTYPE kml SYSTEM "file:///etc/passwd"><kml/>',
        "<kml><Placemark>",
    ],
)
def test_hostile_or_broken_xml_is_refused(text: str) -> None:
    with pytest.raises(FileRefused, match="entities are refused|not well-formed"):
        read_map(text, "evil.kml")


def test_a_huge_file_is_refused_before_it_is_read() -> None:
    huge = '{"type": "FeatureCollection", "features": []}' + " " * MAX_FILE_BYTES
    with pytest.raises(FileRefused, match="larger than 4 MiB"):
        read_map(huge)
    with pytest.raises(FileRefused, match="larger than 4 MiB"):
        read_route(huge)


def test_many_buildings_generated_load_within_the_map_limits() -> None:
    elements: list[dict[str, Any]] = []
    for k in range(400):  # a village: 400 small buildings on a grid inside the field
        lon, lat = 23.6525 + (k % 20) * 5e-5, 37.9411 + (k // 20) * 4e-5
        base = 10 * k
        ring = square(lon, lat, 2e-5)[:-1]
        elements += [
            {"type": "node", "id": base + i, "lat": y, "lon": x} for i, (x, y) in enumerate(ring)
        ]
        elements.append(
            {
                "type": "way",
                "id": k,
                "nodes": [base, base + 1, base + 2, base + 3, base],
                "tags": {"building": "house"},
            }
        )
    found = read_map(
        json.dumps(
            {
                "elements": elements,
                "bounds": {
                    "minlat": 37.941,
                    "minlon": 23.6524,
                    "maxlat": 37.942,
                    "maxlon": 23.6536,
                },
            }
        ),
        options=MapOptions(boundary_bbox=True),
    )
    assert len(parse_map(found.geojson).keepouts) == 400


def test_mission_routes_home_jumps_and_refused_commands() -> None:
    plan = read_route((DATA / "field.plan").read_text())
    assert plan.home == (37.9415, 23.653)
    assert len(plan.waypoints) == 5
    assert parse_waypoints(plan.waypoints).closed
    waypoints = read_route((DATA / "mission.waypoints").read_text())
    assert waypoints.home == (37.9415, 23.653)
    assert not parse_waypoints(waypoints.waypoints).closed
    # A last waypoint equal to the first closes it too.
    closed = wpl(
        HOME,
        *(
            row(i + 1, 3, 16, lat=lat, lon=23.6526)
            for i, lat in enumerate([37.9414, 37.9419, 37.9419, 37.9414])
        ),
    )
    closed = closed.replace("37.9419\t23.6526", "37.9419\t23.6534", 1)
    assert parse_waypoints(read_route(closed).waypoints).closed
    with pytest.raises(
        FileRefused, match=r"row 2 .*MAV_CMD_DO_JUMP \(177\) to 2: only a last jump back"
    ):
        read_route(
            wpl(
                HOME,
                row(1, 3, 16, lat=37.9414, lon=23.6526),
                row(2, 2, 177, 2, -1),
                row(3, 3, 16, lat=37.9419, lon=23.6526),
            )
        )
    with pytest.raises(FileRefused, match=r"row 1 .*: a waypoint in MAV_FRAME_LOCAL_NED \(1\)"):
        read_route(wpl(HOME, row(1, 1, 16, lat=1, lon=2)))
    with pytest.raises(FileRefused, match="commands we cannot fly: row 1 .*MAV_CMD_NAV_LAND"):
        read_route(wpl(HOME, row(1, 3, 21)))
    with pytest.raises(FileRefused, match="a fence or rally file, not a mission"):
        read_route((DATA / "fence.waypoints").read_text())
    with pytest.raises(FileRefused, match="line 3: 11 fields, a QGC WPL 110 row has 12"):
        read_route(wpl(HOME, "1\t0\t3\t16\t0\t0\t0\t0\t37.9\t23.6\t0"))
    survey = json.loads((DATA / "field.plan").read_text())
    survey["mission"]["items"].insert(1, {"type": "ComplexItem", "complexItemType": "survey"})
    with pytest.raises(FileRefused, match="mission item 1: a 'survey' pattern"):
        read_route(json.dumps(survey))
    assert command_name(22) == "MAV_CMD_NAV_TAKEOFF (22)"
    assert command_name(31999) == "MAV_CMD 31999"
    # Refusals name commands as pymavlink does, not by number alone.
    assert command_name(211) == "MAV_CMD_DO_GRIPPER (211)"
    assert command_name(92) == "MAV_CMD_NAV_GUIDED_ENABLE (92)"


def test_route_text_and_json_forms() -> None:
    text = read_route((DATA / "route.txt").read_text())
    assert [(w["lat"], w["lon"]) for w in text.waypoints][2] == (37.9419, 23.6534)
    assert text.notes == ["altitudes ignored (a ground robot)"]
    named = read_route("# a loop\nsw\n37.9414, 23.6526\nnorth gate\n")
    assert named.waypoints == ["sw", {"lat": 37.9414, "lon": 23.6526}, "north gate"]
    lists = read_route(
        '[[37.9414, 23.6526, 4], {"lat": 37.9419, "lon": 23.6534, "name": "x"}, "ne"]'
    )
    assert lists.waypoints[1] == {"lat": 37.9419, "lon": 23.6534, "name": "x"}
    assert lists.notes
    line = read_route(
        json.dumps(
            {"type": "LineString", "coordinates": [[23.6526, 37.9414, 5], [23.6534, 37.9414]]}
        )
    )
    assert line.format == "GeoJSON"
    assert line.waypoints[0] == {"lat": 37.9414, "lon": 23.6526}
    for bad, why in [
        ("37.9,23.6,1,2", "line 1: 4 numbers"),
        ("[[37.9, 23.6], [Infinity, 1]]", "Infinity is not a number JSON allows"),
        ("[[37.9, 23.6, 1, 2]]", "waypoint 0: a list is"),
        ("[[95, 23.6]]", "waypoint 0: 95.0, 23.6 is not a latitude"),
        ('{"fileType": "Plan", "mission": {"items": []}}', "no waypoints in the mission"),
    ]:
        with pytest.raises(FileRefused, match=why):
            read_route(bad)


def test_latitude_longitude_order_is_checked_and_refused_when_ambiguous() -> None:
    ring = [(lat, lon) for lon, lat in FIELD]
    good = read_route("37.9414,23.6526\n37.9419,23.6534\n")
    check_route_order(good, ring, ROBOT)
    swapped = read_route("23.6526,37.9414\n23.6534,37.9419\n")
    with pytest.raises(FileRefused, match="look swapped: the waypoints fit the map's boundary"):
        check_route_order(swapped, ring, ROBOT)
    with pytest.raises(FileRefused, match="look swapped: .*the robot's position"):
        check_route_order(swapped, None, ROBOT)
    near_diagonal = read_route("45.0001,45.0002\n45.0003,45.0001\n")
    with pytest.raises(FileRefused, match="ambiguous"):
        check_route_order(near_diagonal, None, (45.0, 45.0))
    unknown = RouteImport([{"lat": 1.0, "lon": 2.0}], "text")
    check_route_order(unknown, None, None)
    assert "not checked" in unknown.notes[0]
    found = read_map(json.dumps(polygon([[lat, lon] for lon, lat in FIELD])))
    with pytest.raises(FileRefused, match="look swapped: the robot"):
        check_map_order(found, ROBOT)


def test_routes_written_back_read_the_same() -> None:
    route = read_route((DATA / "field.plan").read_text()).waypoints
    area = read_map((DATA / "field.plan").read_text()).geojson
    for fmt in ("plan", "waypoints"):
        text = write_route(fmt, route, ROBOT, area)
        again = read_route(text, fence=fmt == "plan")
        assert again.waypoints == route
        assert again.home == ROBOT
        assert parse_waypoints(again.waypoints).closed
    plan = json.loads(write_route("plan", route, None, area))
    assert plan["mission"]["plannedHomePosition"][:2] == [route[0]["lat"], route[0]["lon"]]
    assert plan["rallyPoints"]["points"] == [[37.9411, 23.6525, 0]]
    assert all(
        not math.isnan(p)
        for item in plan["mission"]["items"]
        for p in item["params"]
        if p is not None
    )
    with pytest.raises(FileRefused, match="no route to export"):
        write_route("plan", [], ROBOT)
    with pytest.raises(FileRefused, match="export format 'gpx'"):
        write_route("gpx", route, ROBOT)


def test_more_waypoints_than_a_route_holds_are_refused_early() -> None:
    with pytest.raises(FileRefused, match="line 1001: more than 1000 waypoints"):
        read_route("37.9414,23.6526\n" * 5000)
    with pytest.raises(FileRefused, match="1001 waypoints, more than 1000"):
        read_route(json.dumps([[37.9414, 23.6526]] * 1001))
    rows = [HOME, *(row(i, 3, 16, lat=37.9414, lon=23.6526) for i in range(1, 1100))]
    with pytest.raises(FileRefused, match="more than 1000 items"):
        read_route(wpl(*rows))


def test_mission_items_are_the_one_mapping_both_ways() -> None:
    """What a MAVLink mission upload or download would use: route -> items -> route."""
    from brasidas.mapfiles.mission import MavCmd, MavFrame, mission_items, route_from_items

    route = [(37.9414, 23.6526), (37.9414, 23.6534), (37.9419, 23.6534), (37.9414, 23.6526)]
    items = mission_items(route, ROBOT)
    assert items[0].frame == MavFrame.GLOBAL
    assert items[1].frame == MavFrame.GLOBAL_RELATIVE_ALT
    # A closed route: its waypoints, then a jump back to the first (item 1).
    assert [item.command for item in items] == [MavCmd.NAV_WAYPOINT] * 4 + [MavCmd.DO_JUMP]
    again = route_from_items(items, home_first=True, jump_target=lambda item: 1)
    assert again.home == ROBOT
    assert again.waypoints == route
    assert again.closed
    kml = read_route((DATA / "field.kml").read_text(), "field.kml")
    assert kml.format == "KML"
    assert len(kml.waypoints) == 3


def test_a_route_is_not_taken_for_an_old_fence_file_and_home_alone_is_no_mission() -> None:
    with pytest.raises(FileRefused, match="line 5: an ArduPilot fence file ends on its first"):
        read_map(
            "37.9415 23.653\n37.9414 23.6526\n37.9414 23.6534\n37.9419 23.6534\n37.9419 23.6526\n"
        )
    with pytest.raises(FileRefused, match="no waypoints in the mission"):
        read_route(wpl(HOME))


def _mutations(rng: random.Random, value: Any) -> Any:
    """The value with one node replaced by something of another type or out of range."""
    replacements: list[Any] = [None, "x", [], {}, 1e308, -1, 0, True, [1, 2, 3, 4], 91.0, 5001]
    if isinstance(value, dict) and value:
        key = rng.choice(list(value))
        return value | {
            key: _mutations(rng, value[key]) if rng.random() < 0.7 else rng.choice(replacements)
        }
    if isinstance(value, list) and value:
        index = rng.randrange(len(value))
        copy = list(value)
        copy[index] = (
            _mutations(rng, value[index]) if rng.random() < 0.7 else rng.choice(replacements)
        )
        return copy
    return rng.choice(replacements)


def test_mangled_files_are_refused_never_crash() -> None:
    """Sample files with characters changed and JSON nodes swapped for wrong types: every
    outcome is a canonical map or route, or FileRefused; nothing else escapes."""
    rng = random.Random(21)
    texts = [path.read_text() for path in sorted(DATA.iterdir())]
    documents = [json.loads((DATA / name).read_text()) for name in ("field.plan", "plain.geojson")]
    documents.append([[37.9414, 23.6526, 3], {"lat": 37.9419, "lon": 23.6534}, {"name": "ne"}])
    alphabet = '0123456789.,-+eE \t\n[]{}":NaN<>/=ab'
    for _ in range(1500):
        if rng.random() < 0.5:
            chars = list(rng.choice(texts))
            for _ in range(rng.randint(1, 5)):
                at = rng.randrange(len(chars))
                chars[at : at + rng.randint(0, 8)] = rng.choice(alphabet)
            text = "".join(chars)
        else:
            text = json.dumps(_mutations(rng, rng.choice(documents)))
        try:
            json.dumps(
                read_map(text, "x", MapOptions(boundary_bbox=rng.random() < 0.3)).geojson,
                allow_nan=False,
            )
        except FileRefused:
            pass
        try:
            found = read_route(text, "x", fence=rng.random() < 0.5)
            json.dumps([found.waypoints, found.keepouts], allow_nan=False)
            check_route_order(found, None, ROBOT)
        except FileRefused:
            pass


def test_a_map_as_fence_items_reads_back_as_the_same_map() -> None:
    """The fence a MAVLink ground station would download, through the same mapping back."""
    from brasidas.mapfiles.mission import MavCmd, fence_items, fence_shapes
    from brasidas.mapfiles.shapes import assemble_map

    area = read_map((DATA / "field.kml").read_text(), "field.kml", MapOptions("field", "barn"))
    items = fence_items(area.geojson)
    assert [item.command for item in items].count(MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION) == 4
    assert items[0].params[0] == 4
    assert items[-1].command == MavCmd.NAV_RALLY_POINT
    again = assemble_map(fence_shapes(items), MapOptions(), "fence items")
    before, after = parse_map(area.geojson), parse_map(again.geojson)
    assert after.boundary.equals_exact(before.boundary, 1e-6)
    assert [zone.area for zone in after.keepouts.values()] == pytest.approx(
        [zone.area for zone in before.keepouts.values()]
    )


def test_a_projected_geojson_and_an_ambiguous_map_are_refused() -> None:
    projected = {
        "type": "FeatureCollection",
        "crs": {"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::3857"}},
        "features": [feature(polygon(FIELD))],
    }
    with pytest.raises(
        FileRefused, match="coordinates in 'urn:ogc:def:crs:EPSG::3857': only WGS-84"
    ):
        read_map(json.dumps(projected))
    projected["crs"] = {"type": "name", "properties": {"name": "urn:ogc:def:crs:OGC:1.3:CRS84"}}
    assert read_map(json.dumps(projected)).format == "GeoJSON"
    diagonal = read_map(json.dumps(polygon(square(44.99, 44.99, 0.02))))
    with pytest.raises(FileRefused, match="order ambiguous: the robot .* either way"):
        check_map_order(diagonal, (45.0, 45.001))


def test_osm_multipolygon_buildings_are_joined_from_their_ways() -> None:
    """A building with a courtyard (outer and inner ways) and one whose outline is two open
    ways; a relation with a way outside the export is named in a note, not guessed."""
    corners = {
        1: (37.9411, 23.6526),
        2: (37.9411, 23.6530),
        3: (37.9414, 23.6530),
        4: (37.9414, 23.6526),
        5: (37.94122, 23.65272),
        6: (37.94122, 23.65288),
        7: (37.94128, 23.65288),
        8: (37.94128, 23.65272),
        11: (37.9417, 23.6532),
        12: (37.9417, 23.6534),
        13: (37.9419, 23.6534),
        14: (37.9419, 23.6532),
    }
    nodes = "".join(
        f'<node id="{n}" lat="{lat}" lon="{lon}"/>' for n, (lat, lon) in corners.items()
    )

    def way(ident: int, refs: list[int]) -> str:
        return f'<way id="{ident}">' + "".join(f'<nd ref="{r}"/>' for r in refs) + "</way>"

    def relation(ident: int, members: list[tuple[int, str]], **tags: str) -> str:
        return (
            f'<relation id="{ident}">'
            + "".join(f'<member type="way" ref="{r}" role="{role}"/>' for r, role in members)
            + "".join(f'<tag k="{k}" v="{v}"/>' for k, v in tags.items())
            + '<tag k="type" v="multipolygon"/></relation>'
        )

    osm = (
        '<osm version="0.6"><bounds minlat="37.941" minlon="23.6524" maxlat="37.942" '
        f'maxlon="23.6536"/>{nodes}'
        + way(20, [1, 2, 3, 4, 1])
        + way(21, [5, 6, 7, 8, 5])
        + way(22, [11, 12, 13])
        + way(23, [11, 14, 13])  # drawn the other way round: joined reversed
        + relation(30, [(20, "outer"), (21, "inner")], building="school", name="school")
        + relation(31, [(22, "outer"), (23, "outer")], building="yes")
        + relation(32, [(99, "outer")], building="yes")
        + "</osm>"
    )
    found = read_map(osm, "village.osm", MapOptions(boundary_bbox=True))
    area = parse_map(found.geojson)
    assert sorted(area.keepouts) == ["relation/30", "relation/31"]
    school = area.keepouts["relation/30"]
    assert len(school.interiors) == 1  # the courtyard is not a keep-out
    assert area.keepout_at(*area.local(37.94125, 23.6528)) is None
    assert area.keepout_at(*area.local(37.9412, 23.6527)) == "relation/30"
    assert any(
        "relation 32 (building) not used: way 99 is not in the file" in n for n in found.notes
    )


def test_a_kmz_is_named_as_a_zip_archive() -> None:
    import io
    import zipfile

    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as kmz:
        kmz.writestr("doc.kml", (DATA / "field.kml").read_text())
    with pytest.raises(FileRefused, match="a zip archive \\(a KMZ\\?\\)"):
        read_map(archive.getvalue().decode("latin-1"), "field.kmz")


def test_a_circle_keepout_holds_the_whole_circle_and_an_inclusion_stays_inside() -> None:
    """At 500 m radius an inscribed 32-gon leaves 2.4 m of the circle outside a keep-out (more
    than an RTK clearance): keep-outs are circumscribed, inclusions inscribed."""
    from shapely import Point

    from brasidas.autonomy.geo import LocalFrame
    from brasidas.mapfiles.shapes import circle

    lat, lon, radius = -36.88, 174.82, 500.0
    frame = LocalFrame(lat, lon)
    keepout = circle("c", 0, lat, lon, radius, role="keepout", ident="k")
    inclusion = circle("c", 0, lat, lon, radius, role="inclusion", ident="i")
    for k in range(360):
        angle = math.radians(k + 0.5)
        on_circle = frame.to_geo(radius * math.cos(angle), radius * math.sin(angle))
        assert keepout.geometry.buffer(1e-9).covers(Point(on_circle[1], on_circle[0]))
    for x, y in inclusion.geometry.exterior.coords:
        east, north = frame.to_local(y, x)
        assert math.hypot(east, north) <= radius + 1e-3


def test_a_map_across_the_antimeridian_loads_at_the_station_as_on_the_platform() -> None:
    """A field on 180° with wrapped longitudes (one ring, 20 vertices, made here): valid in
    metres, self-crossing in degrees; both readers check it in the local frame."""
    lat0, lon0 = -16.55, 179.98
    ring = []
    for k in range(20):
        angle = 2 * math.pi * k / 20
        lon = lon0 + 0.04 * math.cos(angle)
        ring.append(
            [round(lon - 360 if lon > 180 else lon, 7), round(lat0 + 0.001 * math.sin(angle), 7)]
        )
    ring.append(ring[0])
    assert any(lon < 0 for lon, _ in ring)
    assert any(lon > 0 for lon, _ in ring)
    geojson = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {"role": "boundary"},
                "geometry": {"type": "Polygon", "coordinates": [ring]},
            }
        ],
    }
    found = read_map(json.dumps(geojson))
    area = parse_map(found.geojson).summary()["area_m2"]
    assert 1.4e6 < area < 1.5e6  # an ellipse 8.5 km by 220 m, not the width of the world
    bowtie = [[179.99, -16.55], [-179.99, -16.54], [-179.99, -16.55], [179.99, -16.54]]
    with pytest.raises(FileRefused, match="invalid polygon: self-intersection at -16.54"):
        read_map(json.dumps({"type": "Polygon", "coordinates": [[*bowtie, bowtie[0]]]}))


def test_an_exported_loop_ends_with_a_jump_and_keeps_the_files_home() -> None:
    """Another autopilot loops an exported closed route (a DO_JUMP, not a last waypoint that
    happens to be the first), counted laps survive, and home is the one given (the file's)."""
    corners = [(37.9414, 23.6526), (37.9419, 23.6526), (37.9419, 23.6534)]
    route = [{"lat": lat, "lon": lon} for lat, lon in [*corners, corners[0]]]
    home = (37.9413, 23.6529)
    for fmt in ("waypoints", "plan"):
        text = write_route(fmt, route, home, None, 3)
        back = read_route(text)
        assert back.home == home, fmt
        assert [(w["lat"], w["lon"]) for w in back.waypoints] == [*corners, corners[0]], fmt
        assert back.laps == 3, fmt
    rows = write_route("waypoints", route, home).splitlines()
    assert rows[-1].split("\t")[3:6] == ["177", "1", "-1"]  # DO_JUMP to item 1, forever


def test_a_rally_file_given_as_a_route_says_what_it_is() -> None:
    rally = "RALLY -36.8801 174.8201 20 0 0 0\nRALLY -36.8805 174.8209 20 0 0 0\n"
    with pytest.raises(FileRefused, match="an ArduPilot rally file, not a route: load it with"):
        read_route(rally)
    points = parse_map(
        read_map(
            "-36.8800 174.8200\n-36.8790 174.8190\n-36.8790 174.8220\n-36.8810 174.8220\n"
            "-36.8810 174.8190\n-36.8790 174.8190\n" + rally
        ).geojson
    ).points
    assert sorted(points) == ["fence-return", "rally-1", "rally-2"]


def older_item(jump_id: int, command: int, lat: float, lon: float, param1: float = 0) -> Any:
    """An item in QGroundControl's older layout (param1..4 and coordinate), made here."""
    return {
        "autoContinue": True,
        "command": command,
        "coordinate": [lat, lon, 15],
        "frame": 3,
        "id": jump_id,
        "param1": param1,
        "param2": -1 if command == 177 else 0,
        "param3": 0,
        "param4": 0,
        "type": "missionItem",
    }


def test_qgcs_older_mission_and_item_layouts_are_read() -> None:
    corners = [(37.9414, 23.6526), (37.9419, 23.6526), (37.9419, 23.6534)]
    items = [older_item(n + 1, 16, lat, lon) for n, (lat, lon) in enumerate(corners)]
    items.append(older_item(4, 177, 0, 0, param1=1))
    old = {
        "MAV_AUTOPILOT": 3,
        "complexItems": [],
        "groundStation": "QGroundControl",
        "items": items,
        "plannedHomePosition": {"coordinate": [37.9415, 23.653, 0], "type": "missionItem"},
        "version": "1.0",
    }
    found = read_route(json.dumps(old), "old.mission")
    assert found.format == "QGC mission (old)"
    assert found.home == (37.9415, 23.653)
    assert [(w["lat"], w["lon"]) for w in found.waypoints] == [*corners, corners[0]]
    # A .plan whose SimpleItems use the older layout, with a command a rover cannot do.
    plan = json.loads((DATA / "field.plan").read_text())
    older = [
        older_item(n + 1, 16, lat, lon) | {"type": "SimpleItem"}
        for n, (lat, lon) in enumerate(corners)
    ]
    plan["mission"]["items"] = older
    assert len(read_route(json.dumps(plan)).waypoints) == 3
    plan["mission"]["items"] = [
        *older,
        older_item(4, 21, 37.9414, 23.6526) | {"type": "SimpleItem"},
    ]
    with pytest.raises(FileRefused, match=r"commands we cannot fly: .*MAV_CMD_NAV_LAND \(21\)"):
        read_route(json.dumps(plan))


def test_a_named_point_far_outside_the_boundary_is_said() -> None:
    data = json.loads((DATA / "plain.geojson").read_text())
    data["features"].append(
        {
            "type": "Feature",
            "properties": {"name": "typo"},
            "geometry": {"type": "Point", "coordinates": [32.6531, 37.9416]},
        }
    )
    found = read_map(json.dumps(data), options=MapOptions(boundary="yard", keepouts="rest"))
    (note,) = [n for n in found.notes if "far outside the boundary" in n]
    assert "'typo' 7" in note
    assert "km out" in note
    assert "gate" not in note


def test_several_inclusion_fences_as_their_union_when_asked() -> None:
    """ArduPilot's FENCE_OPTIONS: two overlapping fields as one boundary (their union); two
    apart are refused; by default the intersection, as before."""

    def field(west: float, east: float) -> dict[str, Any]:
        ring = [[west, 37.941], [east, 37.941], [east, 37.942], [west, 37.942], [west, 37.941]]
        return {
            "type": "Feature",
            "properties": {"role": "boundary"},
            "geometry": {"type": "Polygon", "coordinates": [ring]},
        }

    overlapping = {
        "type": "FeatureCollection",
        "features": [field(23.652, 23.654), field(23.653, 23.655)],
    }
    text = json.dumps(overlapping)
    both = parse_map(read_map(text, options=MapOptions(union=True)).geojson).summary()["area_m2"]
    one = parse_map(read_map(text).geojson).summary()["area_m2"]
    assert both == pytest.approx(3 * one, rel=0.01)
    apart = {
        "type": "FeatureCollection",
        "features": [field(23.652, 23.653), field(23.654, 23.655)],
    }
    with pytest.raises(FileRefused, match="is 2 separate areas"):
        read_map(json.dumps(apart), options=MapOptions(union=True))
