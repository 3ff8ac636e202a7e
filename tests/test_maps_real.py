"""Real maps (issue 21, issue 19's map parts): anywhere on Earth, multi-part areas, holes,
repeated names, thousands of buildings, limits that agree end to end, atomic loads."""

from __future__ import annotations

import asyncio
import copy
import io
import json
import math
import os
import threading
import tomllib
from collections.abc import Callable
from contextlib import redirect_stdout
from pathlib import Path
from typing import Any

import pytest
import shapely
from conftest import quiet_platform_config, wait_until
from shapely import LineString
from support.maps import drivable_town

from brasidas import topics
from brasidas.autonomy import planner as planner_module
from brasidas.autonomy.areamap import MapError, parse_map
from brasidas.autonomy.geo import LocalFrame
from brasidas.autonomy.planner import Planner
from brasidas.autonomy.route import RouteStore
from brasidas.codecs.telemetry_schema import Autonomy, Snapshot
from brasidas.config import TelemetryReceiverSection
from platformd import cli as platform_cli
from platformd.autonomy.patrol import PatrolActor
from platformd.sim.demo_area import demo_map, demo_route, offset
from platformd.sim.town import town_map
from stationd.telemetry import Annunciator

LAT, LON = 37.9415, 23.6530


def square(frame: LocalFrame, x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
    """A closed ring of [lon, lat] for a rectangle in metres of ``frame``."""
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)]
    return [[lon, lat] for lat, lon in (frame.to_geo(x, y) for x, y in corners)]


def feature(role: str, kind: str, coordinates: Any, **extra: Any) -> dict[str, Any]:
    return {
        "type": "Feature",
        **extra,
        "properties": {"role": role},
        "geometry": {"type": kind, "coordinates": coordinates},
    }


def collection(*features: dict[str, Any]) -> dict[str, Any]:
    return {"type": "FeatureCollection", "features": list(features)}


# --------------------------------------------------------------------------- 1: anywhere


FIJI = LocalFrame(-16.49, 180.0)


def fiji_ring(shift_deg: float = 0.0) -> list[list[float]]:
    """About 4.3 km x 2.2 km across the 180° meridian, longitudes wrapped to ±180."""
    ring = square(FIJI, -2150, -1100, 2150, 1100)
    return [[((lon + shift_deg + 180) % 360) - 180, lat] for lon, lat in ring]


def test_an_area_across_the_180th_meridian_has_a_continuous_frame() -> None:
    area = parse_map(collection(feature("boundary", "Polygon", [fiji_ring()])))
    moved = parse_map(collection(feature("boundary", "Polygon", [fiji_ring(-0.2)])))
    origin_lat, origin_lon = area.summary()["origin"]
    assert abs(origin_lat + 16.49) < 0.001
    assert abs(abs(origin_lon) - 180.0) < 0.001
    assert area.boundary.area == pytest.approx(4300 * 2200, rel=1e-3)
    assert area.boundary.area == pytest.approx(moved.boundary.area, rel=1e-4)
    # A waypoint 332 m due north of the robot is 332 m away, due north: east is east.
    robot = FIJI.to_geo(0.0, 0.0)
    waypoint = FIJI.to_geo(0.0, 332.0)
    east = FIJI.to_geo(50.0, 0.0)  # longitude wraps to -179.99...
    (x0, y0), (x1, y1) = area.local(*robot), area.local(*waypoint)
    assert math.dist((x0, y0), (x1, y1)) == pytest.approx(332.0, abs=0.5)
    assert abs(math.degrees(math.atan2(x1 - x0, y1 - y0))) < 0.5  # course 0°
    assert area.local(*east)[0] - x0 == pytest.approx(50.0, abs=0.1)
    planner = Planner(area.boundary, {}, 4.5)
    assert planner.plan((x0, y0), (x1, y1)).length == pytest.approx(332.0, abs=0.5)


def test_the_rfc7946_split_form_is_the_same_area() -> None:
    west = square(FIJI, -2150, -1100, 0, 1100)
    east = square(FIJI, 0, -1100, 2150, 1100)
    # RFC 7946 §3.1.9: the halves meet at +180 and -180 exactly.
    west = [[180.0 if abs(lon - 180.0) < 1e-6 else lon, lat] for lon, lat in west]
    east = [[-180.0 if abs(abs(lon) - 180.0) < 1e-6 else lon, lat] for lon, lat in east]
    split = parse_map(collection(feature("boundary", "MultiPolygon", [[west], [east]])))
    whole = parse_map(collection(feature("boundary", "Polygon", [fiji_ring()])))
    assert split.boundary.area == pytest.approx(whole.boundary.area, rel=1e-4)
    assert split.boundary.geom_type == "Polygon"  # one area again, no seam
    assert split.inside(*split.local(*FIJI.to_geo(0.0, 0.0)))


@pytest.mark.parametrize("latitude", [74.7, 89.5, -89.9])
def test_areas_near_the_poles_keep_their_size(latitude: float) -> None:
    frame = LocalFrame(latitude, 12.0)
    area = parse_map(
        collection(feature("boundary", "Polygon", [square(frame, -500, -500, 500, 500)]))
    )
    assert area.boundary.area == pytest.approx(1e6, rel=1e-4)


def test_several_inclusion_areas_are_intersected_and_a_multipolygon_area_kept() -> None:
    frame = LocalFrame(LAT, LON)
    a = feature("boundary", "Polygon", [square(frame, 0, 0, 100, 100)])
    b = feature("boundary", "Polygon", [square(frame, 50, 0, 150, 100)])
    both = parse_map(collection(a, b))
    assert both.boundary.area == pytest.approx(50 * 100, rel=1e-3)
    parted = feature(
        "boundary",
        "MultiPolygon",
        [[square(frame, 0, 0, 100, 100)], [square(frame, 200, 0, 300, 100)]],
    )
    area = parse_map(collection(parted))
    assert area.boundary.area == pytest.approx(2e4, rel=1e-3)
    again = parse_map(area.geojson())
    assert again.summary() == area.summary()
    with pytest.raises(MapError, match="no area in common"):
        parse_map(collection(a, feature("boundary", "Polygon", [square(frame, 500, 0, 600, 9)])))


# --------------------------------------------------------------------------- 2 and 5


def two_part_keepout_map(as_multipolygon: bool) -> tuple[dict[str, Any], tuple[float, float]]:
    frame = LocalFrame(LAT, LON)
    left, right = square(frame, -400, -20, -187.8, 20), square(frame, 187.8, -20, 400, 20)
    boundary = feature("boundary", "Polygon", [square(frame, -600, -300, 600, 300)])
    if as_multipolygon:
        zones = [feature("keepout", "MultiPolygon", [[left], [right]], id="pair")]
    else:
        zones = [
            feature("keepout", "Polygon", [left], id="left"),
            feature("keepout", "Polygon", [right], id="right"),
        ]
    return collection(boundary, *zones), frame.to_geo(0.0, 0.0)


def test_a_multipolygon_keepout_is_its_parts_not_their_hull() -> None:
    for as_multipolygon in (False, True):
        data, between = two_part_keepout_map(as_multipolygon)
        area = parse_map(data)
        area.check_position(*between, "the waypoint")  # 187.8 m from either part
        planner = Planner(area.boundary, list(area.keepouts.values()), 4.5)
        start = area.local(*offset(*between, 0, -150))
        assert planner.plan(start, area.local(*between)).length == pytest.approx(150, abs=1)
        assert area.keepout_at(*area.local(*offset(*between, 300, 0))) in ("pair", "right")


def test_a_point_in_a_hole_is_measured_to_the_hole() -> None:
    frame = LocalFrame(LAT, LON)
    outer = square(frame, -3000, -3000, 3000, 3000)
    hole = square(frame, -1000, -1000, 1000, 1000)[::-1]
    area = parse_map(collection(feature("boundary", "Polygon", [outer, hole])))
    inside_hole = frame.to_geo(0.0, 24.1)  # 975.9 m from the hole's edge, 2975.9 m from outside
    with pytest.raises(MapError, match=r"outside the map's boundary \(975\.9 m from it\)"):
        area.check_position(*inside_hole)


# --------------------------------------------------------------------------- 6: names


def test_repeated_names_get_unique_ids_and_say_so() -> None:
    data = town_map(LAT, LON, buildings=300, seed=3)
    names = [f["properties"].get("name") for f in data["features"][1:]]
    assert names.count(" ") > 1
    assert names.count("Garage") > 1
    area = parse_map(data)
    assert len(area.keepouts) == 300
    assert "Garage (2)" in area.keepouts
    assert " " not in area.keepouts
    assert any("repeat a name" in note and "'Garage'" in note for note in area.notes)
    assert area.summary()["notes"] == list(area.notes)
    # An explicit id used twice is still a mistake, and an update's repeated name is renamed.
    zone = next(f for f in data["features"] if f["properties"].get("name") == "Garage")
    more = area.with_keepouts(add=[copy.deepcopy(zone)])
    assert len(more.keepouts) == 301
    assert more.notes
    with pytest.raises(MapError, match="exists already"):
        more.with_keepouts(add=[zone | {"id": "Garage (2)"}])


def files(tmp_path: Path) -> tuple[str, str]:
    return f"map.file={tmp_path / 'map.geojson'}", f"autonomy.route_file={tmp_path / 'route.json'}"


async def test_a_map_refused_at_start_is_a_warning_not_only_a_log_line(
    platform_factory: Callable[..., Any], tmp_path: Path
) -> None:
    bad = demo_map(LAT, LON)
    bad["features"].append(copy.deepcopy(bad["features"][1]))  # "shed" twice
    (tmp_path / "map.geojson").write_text(json.dumps(bad))
    daemon = await platform_factory(quiet_platform_config(*files(tmp_path)), None)
    section = daemon.ctx.telemetry.build_one(Autonomy)
    assert isinstance(section, Autonomy)
    assert section.reason == "no map"
    assert "keep-out id 'shed' used twice" in getattr(section, "map_error", "")
    from brasidas.annunciator import MAP_REFUSED

    annunciator = Annunciator(TelemetryReceiverSection())
    (change,) = annunciator.evaluate(Snapshot({Autonomy: section}), 0.0, None, now=1.0)
    assert change.active
    assert change.warning.code == MAP_REFUSED
    assert "used twice" in change.warning.message


# --------------------------------------------------------------------------- 7: small things


def test_platform_config_takes_its_options_after_the_command() -> None:
    out = io.StringIO()
    with redirect_stdout(out):
        assert platform_cli.main(["config", "--sim"]) == 0
    assert tomllib.loads(out.getvalue())["sim"]["enabled"] is True


async def test_a_clearance_that_leaves_no_room_is_said_at_load(
    platform_factory: Callable[..., Any], tmp_path: Path
) -> None:
    frame = LocalFrame(LAT, LON)
    small = collection(feature("boundary", "Polygon", [square(frame, 0, 0, 20, 10)]))  # 200 m²
    daemon = await platform_factory(quiet_platform_config(*files(tmp_path)), None)
    answer = await daemon.ctx.rpc.call_local("load_map", map=small)
    (note,) = answer["map"].get("notes", [])
    assert "clearance_m 4.5 m leaves 11 m² of this map's 200 m² to drive in" in note
    assert "a clearance of 2.5 m or less would leave room" in note


# --------------------------------------------------------------------------- 3: off the loop


def test_one_keepout_changes_the_planner_as_a_rebuild_would() -> None:
    area = parse_map(town_map(LAT, LON, buildings=120, seed=5))
    planner = Planner(area.boundary, area.keepouts, 4.5)
    frame = area.frame
    shed = feature("keepout", "Polygon", [square(frame, 3, -40, 9, -34)], id="new shed")
    changed = area.with_keepouts(add=[shed])
    added = planner.changed({"new shed": changed.keepouts["new shed"]})
    rebuilt = Planner(changed.boundary, changed.keepouts, 4.5)
    first = next(iter(area.keepouts))
    removed = added.changed({}, ["new shed", first])
    without = dict(area.keepouts)
    del without[first]
    rebuilt_without = Planner(area.boundary, without, 4.5)

    def edges(p: Planner) -> set[tuple[tuple[float, float], ...]]:
        nodes = [tuple(round(c, 4) for c in node) for node in p.nodes.tolist()]
        return {
            tuple(sorted((nodes[u], nodes[v])))
            for u, v in zip(p._edge_u.tolist(), p._edge_v.tolist(), strict=True)
        }

    for incremental, full in ((added, rebuilt), (removed, rebuilt_without)):
        assert not edges(full) - edges(incremental)  # nothing the full build finds is lost
        for a, b in edges(incremental) - edges(full):  # and anything more is drivable
            assert full._free.covers(LineString([a, b]))


def test_removing_a_keepout_checks_only_the_corner_pairs_that_can_cross_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    area = parse_map(town_map(LAT, LON, buildings=120, seed=5))
    planner = Planner(area.boundary, area.keepouts, 4.5)
    tested: list[int] = []
    meets_box = planner_module._meets_box

    def counted(a: Any, b: Any, box: Any) -> Any:
        tested.append(len(a))
        return meets_box(a, b, box)

    monkeypatch.setattr(planner_module, "_meets_box", counted)
    key = sorted(area.keepouts)[len(area.keepouts) // 2]
    planner.changed({}, [key])
    count = len(planner.nodes)
    # Not every pair of corners (a removal's cost grew with their square): those in the wedge
    # the reopened zone spans from each corner.
    assert 0 < sum(tested) < 0.2 * count * (count - 1) / 2, (sum(tested), count)


async def test_map_updates_never_run_geometry_on_the_event_loop(
    platform_factory: Callable[..., Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    daemon = await platform_factory(
        quiet_platform_config(
            "sim.enabled=true",
            "gps.enabled=true",
            "gps.sim_rate_hz=10",
            f"map.file={tmp_path / 'map.geojson'}",
            f"autonomy.route_file={tmp_path / 'route.json'}",
        ),
        None,
    )
    bus = daemon.ctx.bus
    await wait_until(lambda: bus.last(topics.POSE) is not None, 10)
    pose = bus.last(topics.POSE)
    assert pose is not None
    town = drivable_town(pose.latitude, pose.longitude, buildings=400)
    built_in: list[str] = []
    for name in ("__init__", "changed"):
        original = getattr(Planner, name, None)
        if original is None:
            continue

        def spy(*args: Any, _original: Any = original, **kwargs: Any) -> Any:
            built_in.append(threading.current_thread().name)
            return _original(*args, **kwargs)

        monkeypatch.setattr(planner_module.Planner, name, spy)
    await daemon.ctx.rpc.call_local("load_map", map=town)
    waypoints = [
        "{:.7f},{:.7f}".format(*offset(pose.latitude, pose.longitude, e, n))
        for e, n in ((0, 0), (0, 6), (0, 0))
    ]
    await daemon.ctx.rpc.call_local("set_waypoints", waypoints=waypoints)
    arming = daemon.ctx.arming
    assert arming is not None  # a start arms through the pre-arm checks (issue 27)
    await wait_until(lambda: not arming.reasons(), 20)
    await daemon.ctx.rpc.call_local("patrol_start")
    frame = LocalFrame(pose.latitude, pose.longitude)
    shed = feature("keepout", "Polygon", [square(frame, 30, 30, 36, 36)], id="new shed")
    answer = await daemon.ctx.rpc.call_local("update_map", add=[shed])
    assert "new shed" in answer["map"]["keepouts"]
    # Until the changed planner is ready the patrol holds and says why.
    assert answer["patrol"]["state"] in ("holding", "stopped", "patrolling")
    if answer["patrol"]["state"] == "holding":  # (or a late fix on a busy machine)
        reason = answer["patrol"]["reason"]
        assert "waiting for the new plan" in reason or "GPS fix" in reason, reason
    patrol = next(a for a in daemon.supervisor.actors if isinstance(a, PatrolActor))
    await wait_until(lambda: patrol.planner_ready, 60)
    # Built in the planner process: not on the event loop, nor in a thread of this process
    # (NumPy and Shapely there would hold the loop's GIL).
    assert built_in == [], built_in
    assert patrol.planner.pid not in (None, os.getpid())


def test_the_patrol_holds_until_the_new_plan_is_ready() -> None:
    from brasidas.autonomy.follower import FollowerParameters
    from brasidas.autonomy.localization import Estimate
    from brasidas.autonomy.patrol import Patrol, PatrolParameters
    from brasidas.autonomy.route import parse_waypoints
    from brasidas.messages import PatrolState

    follower = FollowerParameters(
        cruise_speed=1.6, max_turn_rate=1.0, full_speed=1.6, full_turn_rate=1.5
    )
    patrol = Patrol(PatrolParameters(follower=follower, clearance_m=1.5))
    area = parse_map(demo_map(LAT, LON))
    patrol.set_map(area)
    patrol.set_route(parse_waypoints(demo_route(), area.points))
    patrol.start()
    x, y = area.local(LAT, LON)
    here = Estimate(time=0.0, x=x, y=y, yaw=0.0, speed=0.0, sigma_xy=0.1, sigma_yaw=0.01)
    patrol.step(here, 0.1)
    assert patrol.status().state is PatrolState.PATROLLING
    frame = area.frame
    rock = feature("keepout", "Polygon", [square(frame, 30, 5, 32, 7)], id="rock")
    changed = area.with_keepouts(add=[rock])
    patrol.update_map(changed, build=False)
    patrol.step(here, 0.1)
    assert patrol.status().state is PatrolState.HOLDING
    assert patrol.reason == "the map changed: waiting for the new plan (being built)"
    assert not patrol.set_planner(area, Planner(area.boundary, area.keepouts, 1.5))  # stale
    assert patrol.set_planner(changed, Planner(changed.boundary, changed.keepouts, 1.5))
    patrol.step(here, 0.1)
    assert patrol.status().state is PatrolState.PATROLLING


# --------------------------------------------------------------------------- 19.6: atomic


async def test_a_crash_between_the_map_and_its_route_never_pairs_them(
    platform_factory: Callable[..., Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = quiet_platform_config(*files(tmp_path))
    first = await platform_factory(config, None)
    await first.ctx.rpc.call_local("load_map", map=demo_map(LAT, LON))
    await first.ctx.rpc.call_local("set_waypoints", waypoints=demo_route())
    assert RouteStore(tmp_path / "route.json").load().waypoints
    moved = demo_map(LAT + 0.00001, LON)  # the same field a metre north: the route fits it

    def crash(*args: Any, **kwargs: Any) -> None:
        raise KeyboardInterrupt("killed between the two writes")

    monkeypatch.setattr(RouteStore, "save", crash)
    with pytest.raises(KeyboardInterrupt):
        await first.ctx.rpc.call_local("load_map", map=moved)
    monkeypatch.undo()
    await first.stop()
    (tmp_path / ".map.geojson.abcd1234").write_text("half a map")  # a crash mid-write
    (tmp_path / ".route.json.zz99yy88").write_text("[")
    again = await platform_factory(config, None)
    stored = await again.ctx.rpc.call_local("get_map")
    assert stored["map"]["features"][1]["geometry"] == moved["features"][1]["geometry"]
    assert stored["route"] == []  # the new map, never with the old route
    assert sorted(os.listdir(tmp_path)) == ["map.geojson", "route.json"]


def test_a_map_under_the_vertex_cap_fits_one_request() -> None:
    from brasidas.autonomy.areamap import MAX_VERTICES
    from brasidas.codecs.jsonrpc import encode_request
    from brasidas.limits import MAP_REQUEST_MAX_BYTES
    from stationd.daemon import API_MAX_BYTES

    town = town_map(LAT, LON, buildings=3400, seed=4)  # ~18,700 vertices, as OSM exports them
    for zone in town["features"][1:]:
        zone["properties"].pop("name", None)  # names are another test's
    area = parse_map(town)
    vertices = sum(int(shapely.get_num_coordinates(z)) for z in area.keepouts.values())
    assert MAX_VERTICES - 2000 < vertices < MAX_VERTICES
    request = encode_request("map_load", {"platform_id": "rover-1", "map": json.dumps(town)}, 1)
    assert len(request) < MAP_REQUEST_MAX_BYTES < API_MAX_BYTES
    from brasidas.config import PlatformConfig, load_config

    assert (
        load_config(PlatformConfig, None, []).signaling.max_request_bytes == MAP_REQUEST_MAX_BYTES
    )


async def test_a_new_map_stops_the_build_of_the_one_it_replaces(
    platform_factory: Callable[..., Any], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    daemon = await platform_factory(quiet_platform_config(*files(tmp_path)), None)
    patrol = next(a for a in daemon.supervisor.actors if isinstance(a, PatrolActor))
    caplog.set_level("INFO", logger="platformd.autonomy.patrol")
    await daemon.ctx.rpc.call_local("load_map", map=town_map(LAT, LON, buildings=1000, seed=6))
    await daemon.ctx.rpc.call_local("load_map", map=demo_map(LAT, LON))
    await wait_until(lambda: patrol.planner_ready, 60)
    assert patrol.core.area is not None
    assert patrol.core.area.name == "demo field"
    await wait_until(lambda: "dropped: a new map came" in caplog.text, 30)


def test_remote_planning_holds_until_the_answer_and_drops_one_for_an_old_map() -> None:
    from brasidas.autonomy.follower import FollowerParameters
    from brasidas.autonomy.localization import Estimate
    from brasidas.autonomy.patrol import Patrol, PatrolParameters
    from brasidas.autonomy.route import parse_waypoints
    from brasidas.messages import PatrolState

    follower = FollowerParameters(
        cruise_speed=1.6, max_turn_rate=1.0, full_speed=1.6, full_turn_rate=1.5
    )
    patrol = Patrol(PatrolParameters(follower=follower, clearance_m=1.5))
    patrol.remote = True
    area = parse_map(demo_map(LAT, LON))
    patrol.set_map(area, build=False)
    patrol.set_route(parse_waypoints(demo_route(), area.points))
    patrol.start()
    x, y = area.local(LAT, LON)
    here = Estimate(time=0.0, x=x, y=y, yaw=0.0, speed=0.0, sigma_xy=0.1, sigma_yaw=0.01)
    patrol.step(here, 0.1)
    assert patrol.reason == "the map changed: waiting for the new plan (being built)"
    assert not patrol.plan_requests
    assert patrol.planner_ready(patrol.map_revision)
    patrol.step(here, 0.1)
    (asked,) = patrol.plan_requests
    assert patrol.status().state is PatrolState.HOLDING
    assert patrol.reason.startswith("planning the path to")
    patrol.plan_requests.clear()
    patrol.step(here, 0.1)
    assert not patrol.plan_requests  # asked once
    # A keep-out comes before the answer: the answer is for the old map, and dropped.
    rock = feature("keepout", "Polygon", [square(area.frame, 30, 5, 32, 7)], id="rock")
    patrol.update_map(area.with_keepouts(add=[rock]), build=False)
    assert not patrol.set_plan(asked.revision, asked.id, [asked.start, asked.goal])
    assert patrol.stale_plans == 1
    patrol.step(here, 0.1)
    assert patrol.status().state is PatrolState.HOLDING
    assert not patrol.planned_path
    assert not patrol.planner_ready(asked.revision)  # a graph of the old map: not ready
    assert patrol.planner_ready(patrol.map_revision)
    patrol.step(here, 0.1)
    (again,) = patrol.plan_requests
    assert again.revision == patrol.map_revision
    assert again.id != asked.id
    patrol.plan_requests.clear()
    assert patrol.set_plan(again.revision, again.id, [again.start, again.goal])
    # With a path, the next leg is asked ahead (from the target to the one after).
    (then,) = patrol.plan_requests
    patrol.plan_requests.clear()
    assert then.origin == again.waypoint
    assert then.start == again.goal
    patrol.step(here, 0.1)  # at the first waypoint (where it starts): holds for that leg
    assert patrol.events[-1].kind == "arrived"
    assert not patrol.plan_requests  # not asked again
    assert patrol.reason.startswith("planning the path to")
    assert patrol.set_plan(then.revision, then.id, [then.start, then.goal])
    (after,) = patrol.plan_requests  # and the one after that, ahead
    patrol.step(here, 0.1)
    assert patrol.status().state is PatrolState.PATROLLING
    # Answered before the robot gets there: it goes on at the waypoint without holding.
    assert patrol.set_plan(after.revision, after.id, [after.start, after.goal])
    there = Estimate(
        time=1.0, x=then.goal[0], y=then.goal[1], yaw=0.0, speed=0.0, sigma_xy=0.1, sigma_yaw=0.01
    )
    patrol.plan_requests.clear()
    patrol.step(there, 0.1)
    assert patrol.events[-1].kind == "arrived"
    assert patrol.status().state is PatrolState.PATROLLING, patrol.reason
    assert patrol.planned_path[0] == after.start
    assert len(patrol.plan_requests) == 1
    # The target changed under a request (a ground station's MISSION_SET_CURRENT sets the
    # cursor): its answer, a path to the old target, is dropped and the new one asked.
    from brasidas.autonomy.route import Cursor

    patrol.plan_requests.clear()
    patrol.stop()
    patrol.start()
    patrol.step(there, 0.1)
    asked = next(r for r in patrol.plan_requests if r.origin == -1)
    patrol.cursor = Cursor((asked.waypoint + 1) % patrol.route.stops, True, 0, True)
    assert not patrol.set_plan(asked.revision, asked.id, [asked.start, asked.goal])
    patrol.plan_requests.clear()
    patrol.step(there, 0.1)
    (new,) = patrol.plan_requests
    assert new.waypoint == patrol.cursor.index
    assert patrol.reason.startswith("planning the path")
    # The planner process dies: hold, saying why, until it has the graph again.
    patrol.planner_lost("the planner process stopped (exit code -9)")
    patrol.step(here, 0.1)
    assert patrol.status().state is PatrolState.HOLDING
    assert patrol.reason == "the planner process stopped (exit code -9)"


async def test_the_planner_process_answers_edits_plans_and_asks_for_a_map_it_lacks() -> None:
    """The planner process's protocol, on its socket: an edit of a map it never had is
    answered ``resend``; a map, then an edit of it, each ready; a plan for an old revision
    ``stale``; a frame over the limit ends it."""
    import socket
    import struct
    import sys

    import orjson

    from brasidas.autonomy.planner_worker import HEADER, frame, parse_header

    ours, theirs = socket.socketpair()
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "brasidas.autonomy.planner_worker", str(theirs.fileno()),
        pass_fds=(theirs.fileno(),),
    )  # fmt: skip
    theirs.close()
    reader, writer = await asyncio.open_unix_connection(sock=ours)

    async def answer() -> dict[str, Any]:
        head, size = parse_header(await reader.readexactly(HEADER.size))
        header: dict[str, Any] = orjson.loads(await reader.readexactly(head))
        await reader.readexactly(size)
        return header

    try:
        area = parse_map(demo_map(LAT, LON))
        rock = feature("keepout", "Polygon", [square(area.frame, 30, 5, 32, 7)], id="rock")
        edit = orjson.dumps({"add": [rock], "remove": []})
        writer.write(frame({"op": "edit", "revision": 2, "base": 1, "clearance": 1.5}, edit))
        assert (await asyncio.wait_for(answer(), 60)) == {"op": "resend", "revision": 2}
        writer.write(
            frame({"op": "map", "revision": 1, "clearance": 1.5}, orjson.dumps(area.geojson()))
        )
        # Revision 2 was asked for already: 1 is parsed (for the edit) but not built.
        assert (await asyncio.wait_for(answer(), 60)) == {"op": "dropped", "revision": 1}
        writer.write(frame({"op": "edit", "revision": 2, "base": 1, "clearance": 1.5}, edit))
        ready = await asyncio.wait_for(answer(), 60)
        assert (ready["op"], ready["revision"], ready["incremental"]) == ("ready", 2, False)
        writer.write(frame({"op": "edit", "revision": 3, "base": 2, "clearance": 1.5}, b"{"))
        assert (await asyncio.wait_for(answer(), 60))["op"] == "failed"  # said, not a crash
        again = orjson.dumps({"add": [], "remove": ["rock"]})
        writer.write(frame({"op": "edit", "revision": 3, "base": 2, "clearance": 1.5}, again))
        ready = await asyncio.wait_for(answer(), 60)
        assert (ready["op"], ready["revision"], ready["incremental"]) == ("ready", 3, True)
        writer.write(frame({"op": "edit", "revision": 4, "base": 3, "clearance": 1.5}, edit))
        ready = await asyncio.wait_for(answer(), 60)
        assert (ready["op"], ready["revision"], ready["incremental"]) == ("ready", 4, True)
        start, goal = area.local(LAT, LON), area.local(*offset(LAT, LON, 40, 6))
        for revision in (3, 4):
            plan = {
                "op": "plan",
                "revision": revision,
                "id": revision,
                "start": start,
                "goal": goal,
            }
            writer.write(frame(plan))
        stale = await asyncio.wait_for(answer(), 60)
        assert (stale["op"], stale["id"]) == ("stale", 3), stale
        path = await asyncio.wait_for(answer(), 60)
        assert path["op"] == "path", path
        assert path["id"] == 4, path
        assert not LineString(path["points"]).intersects(
            parse_map(area.with_keepouts(add=[rock]).geojson()).keepouts["rock"]
        )
        writer.write(struct.pack("!II", 1 << 30, 0))  # a broken peer: the process ends
        assert await asyncio.wait_for(process.wait(), 30) == 0
    finally:
        writer.close()
        if process.returncode is None:
            process.kill()
            await process.wait()


async def test_a_planner_process_that_cannot_start_is_said_and_tried_again(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import sys

    from platformd.autonomy.planner_client import PlannerProcess

    lost: list[str] = []
    planner = PlannerProcess(lambda answer: None, lost.append, backoff_initial=0.01)
    monkeypatch.setattr(sys, "executable", str(tmp_path / "no-python"))
    task = asyncio.get_running_loop().create_task(planner.run())
    try:
        await wait_until(lambda: len(lost) >= 2, 10)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    assert lost[0].startswith("the planner process could not start"), lost
    assert not planner.request_plan(1, 1, (0.0, 0.0), (1.0, 1.0))  # none to ask: said


async def test_a_stopped_planner_closes_its_socket_through_its_transport() -> None:
    """The planner's socket was closed under its live transport at a stop: the event loop kept
    that transport on a descriptor number the next open reused, so a serial device opened
    later with that number failed ("File descriptor N is used by transport"), whenever the
    old transport was not yet collected (a profiler holding frames showed it)."""
    from platformd.autonomy.planner_client import PlannerProcess, PlannerState

    planner = PlannerProcess(lambda answer: None, lambda reason: None)
    loop = asyncio.get_running_loop()
    task = loop.create_task(planner.run())
    try:
        await wait_until(lambda: planner.state is PlannerState.RUNNING, 20)
        writer = planner._writer  # held, as a late collection would
        assert writer is not None
        number = writer.get_extra_info("socket").fileno()
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    assert writer.transport.is_closing()
    # The next descriptors opened take the freed number: one of them can be watched.
    pipes = [os.pipe() for _ in range(4)]
    try:
        assert number in [fd for pair in pipes for fd in pair]
        loop.add_reader(number, lambda: None)
        loop.remove_reader(number)
    finally:
        for pair in pipes:
            for fd in pair:
                os.close(fd)
