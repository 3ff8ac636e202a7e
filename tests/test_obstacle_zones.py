"""The lidar's obstacles on the patrol's map: a person walking gets a keep-out along their way."""

from __future__ import annotations

import random
from types import SimpleNamespace
from typing import Any

import pytest
from shapely.geometry import Point, Polygon

from brasidas.autonomy.areamap import AreaMap, MapError, parse_map
from brasidas.bus import Bus
from brasidas.messages import PoseEstimate
from brasidas.perception.messages import Obstacle, RobotScan
from platformd.obstacle_zones import ObstacleZones, ZoneChanges, clear_of_robot
from platformd.sim.demo_area import demo_map, offset

LAT, LON = 37.9415, 23.6530


def standing_robot(now: float) -> PoseEstimate:
    """At the start, facing east (robot x forward = east, y left = north)."""
    return PoseEstimate(now, LAT, LON, 0.0, 0.0, (LAT, LON), 0.0, 0.0, 0.05, 1.0, True, 0.1)


def scan(now: float, *obstacles: tuple[float, float]) -> RobotScan:
    return RobotScan(now, (), (), 0, tuple(Obstacle(x, y, 0.25, 12) for x, y in obstacles))


def polygon(area: AreaMap, feature: dict[str, Any]) -> Polygon:
    ring = feature["geometry"]["coordinates"][0]
    return Polygon([area.local(lat, lon) for lon, lat in ring])


def test_a_walker_gets_a_zone_along_their_way_a_post_keeps_its_disc() -> None:
    """A person 6 m ahead walking north at 1.3 m/s, a post 4 m ahead, both seen every half
    second with their centres jittering 0.15 m: the person's zone follows them and reaches
    where they will be in a second and a half; the post's stays one disc, never redrawn."""
    area = parse_map(demo_map(LAT, LON))
    zones = ObstacleZones(SimpleNamespace(bus=Bus()))  # type: ignore[arg-type]
    rng = random.Random(3)
    live: dict[str, dict[str, Any]] = {}
    post_zones: set[str] = set()
    now = 0.0
    walker = (6.0, -4.0)
    for _ in range(12):  # 6 s
        now += 0.5
        walker = (walker[0], walker[1] + 1.3 * 0.5)
        jitter = [rng.uniform(-0.15, 0.15) for _ in range(4)]
        changes: ZoneChanges = zones.track(
            scan(
                now,
                (walker[0] + jitter[0], walker[1] + jitter[1]),
                (4.0 + jitter[2], 1.5 + jitter[3]),
            ),
            standing_robot(now),
            area,
            now,
        )
        for zone in changes.remove:
            live.pop(zone)
        for feature in changes.add:
            live[feature["id"]] = feature
            if polygon(area, feature).contains(Point(area.local(*offset(LAT, LON, 4.0, 1.5)))):
                post_zones.add(feature["id"])
    assert len(post_zones) == 1  # drawn once, never redrawn for its jitter
    here = area.local(*offset(LAT, LON, walker[0], walker[1]))
    ahead = area.local(*offset(LAT, LON, walker[0], walker[1] + 1.3 * 1.2))
    walker_zones = [polygon(area, f) for z, f in live.items() if z not in post_zones]
    assert len(walker_zones) == 1
    # Drawn at the last redraw (within REDRAW_M of them): it covers them and their way ahead.
    assert walker_zones[0].distance(Point(here)) < 0.5
    assert walker_zones[0].contains(Point(ahead))
    track = next(t for t in zones.tracks if t.moving)
    assert 0.9 < track.velocity[1] < 1.7 and abs(track.velocity[0]) < 0.4


def lidar_zone(area: AreaMap, zone_id: str, x: float, y: float, radius: float) -> dict[str, Any]:
    ring = [
        list(reversed(area.frame.to_geo(px, py)))
        for px, py in Point(x, y).buffer(radius).exterior.coords
    ]
    return {
        "type": "Feature",
        "id": zone_id,
        "properties": {"role": "keepout", "source": "lidar"},
        "geometry": {"type": "Polygon", "coordinates": [ring]},
    }


def test_a_zone_drawn_over_the_robot_still_reaches_the_planner_with_the_others() -> None:
    """Passing a post so close that its zone is drawn over the robot: that zone goes on the
    map without the spot under the robot (the path is kept off the post) and the other new
    zone with it; a zone the robot is in already does not keep a new one out either. Before,
    the whole update was refused ("the robot is in keep-out zone 'lidar:N'") and the planner
    knew neither obstacle while the robot drove past."""
    from platformd.autonomy.patrol import PatrolActor

    area = parse_map(demo_map(LAT, LON))
    x, y = area.local(LAT, LON)
    post = lidar_zone(area, "lidar:1", x + 0.2, y + 0.3, 0.45)  # beside it, over the robot
    ahead = lidar_zone(area, "lidar:2", x + 5.0, y, 0.3)

    def change(base: AreaMap, add: list[dict[str, Any]]) -> AreaMap:
        changed, _, _ = PatrolActor._changed_map(
            SimpleNamespace(),  # type: ignore[arg-type]  # (it needs no storage: not stored)
            base,
            add,
            [],
            (LAT, LON),
            False,
        )
        return changed

    changed = change(area, [post, ahead])
    assert set(changed.keepouts) >= {"lidar:1", "lidar:2"}
    assert changed.keepout_at(x, y) is None  # the robot is not in it: it plans off the post
    assert changed.keepouts["lidar:1"].distance(Point(x, y)) < 0.15
    assert changed.keepouts["lidar:1"].contains(Point(x + 0.2, y + 0.5))  # the post's side
    # It drove into a zone (applied before): a new obstacle still enters the plan.
    inside = area.with_keepouts(add=[lidar_zone(area, "lidar:3", x, y, 0.4)])
    assert inside.keepout_at(x, y) == "lidar:3"
    later = change(inside, [lidar_zone(area, "lidar:4", x - 4.0, y, 0.3)])
    assert "lidar:4" in later.keepouts
    # The map's own keep-outs are still checked: the robot in one is refused.
    with pytest.raises(MapError):
        own = lidar_zone(area, "shed", x, y, 0.4) | {"properties": {"role": "keepout"}}
        PatrolActor._changed_map(
            SimpleNamespace(),  # type: ignore[arg-type]
            area,
            [own],
            [],
            (LAT, LON),
            False,
        )


def test_a_zone_that_is_all_under_the_robot_is_its_own_body_not_a_post() -> None:
    area = parse_map(demo_map(LAT, LON))
    x, y = area.local(LAT, LON)
    body = lidar_zone(area, "lidar:1", x, y, 0.05)
    assert clear_of_robot([body], area, LAT, LON) == []
