"""What is shown of the lidar: the scan in sectors, the occupancy grid as an image (and back),
their Foxglove encodings through the shared projection, and through the running --sim
daemon: the ``lidar_view`` section, ``get_grid`` and the recorder's ``/grid`` and
``/pose/fused``."""

from __future__ import annotations

import asyncio
import base64
import math
import types
import warnings
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import orjson
import pytest
from conftest import running_station, until_armable, wait_until
from support.lidar import clearance, obstacles_file
from support.patrol import LAT, LON, RTK, Robot, at

from brasidas import topics
from brasidas.autonomy.geo import LocalFrame
from brasidas.bus import Bus
from brasidas.codecs.telemetry_schema import (
    LidarView,
    Snapshot,
    section_from_wire,
    section_to_wire,
)
from brasidas.perception.view import (
    UNKNOWN,
    GridRefused,
    grid_from_json,
    grid_image,
    pose_at,
    reframe,
    sector_points,
    sector_ranges,
)
from brasidas.recording import projection, schemas

GRID_PERIOD = "lidar.grid_period_s=1"
"""The grid drawn again every second, not every 5 s: what is tested is that it is drawn,
fetched and passed on, not how often (a client waited ~15 s of the 5 s periods)."""


def test_sectors_keep_the_nearest_return_clockwise_from_forward() -> None:
    ranges = sector_ranges(
        (0.0, 1.0, 358.0, 90.0, 92.4, 180.0, 270.0), (2.0, 1.5, 3.0, 4.0, 0.0, 12.0, 0.3)
    )
    assert len(ranges) == 72
    assert ranges[0] == 15  # 358°, 0° and 1° are the forward sector: the nearest, in dm
    assert ranges[18] == 40  # 90°; the 92.4° one had no return
    assert ranges[36] == 120
    assert ranges[54] == 3
    assert sum(1 for r in ranges if r) == 4
    assert sector_points(ranges)[1] == (90.0, 4.0)


def test_the_sector_scan_for_foxglove_is_counter_clockwise() -> None:
    ranges = [0] * 72
    ranges[0], ranges[18] = 20, 35  # ahead 2 m, 90° clockwise (right) 3.5 m
    message = orjson.loads(schemas.encode_sector_scan(2_000_000_000, ranges))
    assert message["frame_id"] == "base_link"
    assert len(message["ranges"]) == 72
    assert message["ranges"][0] == 2.0
    assert message["ranges"][54] == 3.5  # right is 270° counter-clockwise
    assert math.isclose(message["end_angle"], math.radians(355))


def grid_with_post(size: int = 600) -> tuple[np.ndarray, tuple[float, float]]:
    """A 0.1 m grid with free space around one occupied cell, far from its corner."""
    log_odds = np.zeros((size, size), dtype=np.float32)
    log_odds[100:500, 100:500] = -2.0  # seen free
    log_odds[321, 457] = 3.0  # a post (row = north, column = east)
    return log_odds, (-30.0, -20.0)


def test_a_scan_is_shown_around_the_pose_it_is_shown_with() -> None:
    """A turning robot's scan, taken a moment before the pose telemetry carries with it,
    moved into that pose: a post 10 m east seen facing north-east, shown from the pose
    0.1 s later (turned 6° further, 0.1 m on) is still 10 m east of where it was seen."""
    then = (0.0, 0.0, math.radians(45.0))  # yaw counter-clockwise from east
    now = (0.1, 0.0, math.radians(39.0))
    bearing, distance = reframe(45.0, 10.0, then, now)  # 45° right of forward: due east
    assert abs(bearing - 39.0) < 1e-9
    assert abs(distance - 9.9) < 1e-9
    # The pose in the middle of a scan: between the samples, the short way round the wrap.
    history = [(1.0, (0.0, 0.0, math.radians(350.0))), (1.2, (2.0, 0.0, math.radians(10.0)))]
    x, y, yaw = pose_at(history, 1.1) or (0, 0, 0)
    assert math.dist((x, y), (1.0, 0.0)) < 1e-9
    assert abs(math.remainder(yaw, math.tau)) < 1e-9
    # After the last pose: carried on at its rate, a quarter of a second at most.
    x, _, _ = pose_at(history, 1.3) or (0, 0, 0)
    assert abs(x - 3.0) < 1e-9
    x, _, _ = pose_at(history, 5.0) or (0, 0, 0)
    assert abs(x - 4.5) < 1e-9
    assert pose_at([], 1.0) is None


def test_grid_image_crops_reduces_and_keeps_an_obstacle_in_its_block() -> None:
    log_odds, origin = grid_with_post()
    image = grid_image(LAT, LON, origin, 0.1, log_odds, scans=7, max_side=100)
    assert image is not None
    # Cropped to the seen 400 x 400 cells, reduced by 4 to 100 x 100 of 0.4 m.
    assert (image.columns, image.rows, image.cell_m) == (100, 100, pytest.approx(0.4))
    assert (image.x_m, image.y_m) == (pytest.approx(-20.0), pytest.approx(-10.0))
    cells = np.frombuffer(image.cells, dtype=np.uint8).reshape(image.rows, image.columns)
    assert image.occupied_cells() == 1
    row, col = np.argwhere(cells >= 65)[0]
    # The post's world position lies in the occupied image cell.
    east, north = origin[0] + 457.05 * 0.1, origin[1] + 321.05 * 0.1
    assert image.x_m + col * image.cell_m <= east < image.x_m + (col + 1) * image.cell_m
    assert image.y_m + row * image.cell_m <= north < image.y_m + (row + 1) * image.cell_m
    assert (cells < 20).sum() == 100 * 100 - 1  # the rest free, none unknown inside the crop
    south_west, north_east = image.corners()
    frame = LocalFrame(LAT, LON)
    assert frame.to_local(*south_west) == pytest.approx((-20.0, -10.0), abs=1e-3)
    assert frame.to_local(*north_east) == pytest.approx((20.0, 30.0), abs=1e-3)
    assert grid_image(LAT, LON, origin, 0.1, np.zeros((8, 8), np.float32), 0) is None


def test_grid_json_round_trip_and_garbage_refused() -> None:
    log_odds, origin = grid_with_post()
    image = grid_image(LAT, LON, origin, 0.1, log_odds, scans=3)
    assert image is not None
    answer = orjson.loads(orjson.dumps(image.to_json(rev=4)))
    assert answer["rev"] == 4
    assert grid_from_json(answer) == image
    bomb = dict(answer, cells=base64.b64encode(zlib.compress(b"\0" * 10_000_000)).decode())
    for bad in (
        dict(answer, columns=100_000, rows=100_000),
        dict(answer, cells="not base64!"),
        dict(answer, cells=base64.b64encode(b"not zlib").decode()),
        bomb,  # more cells than it says: refused without inflating it all
        {k: v for k, v in answer.items() if k != "anchor"},
    ):
        with pytest.raises(GridRefused):
            grid_from_json(bad)


def test_the_projection_puts_the_scan_and_fused_pose_on_their_channels() -> None:
    ranges = tuple([25] + [0] * 71)
    view = LidarView(ranges_dm=ranges, fused_lat=LAT, fused_lon=LON, fused_heading_deg=90.0)
    assert section_from_wire(LidarView, section_to_wire(view)) == view
    messages, _ = projection.channel_messages(None, Snapshot({LidarView: view}), 5)
    topics_sent = [m.spec.topic for m in messages]
    assert topics_sent == ["/telemetry/lidar_view", "/lidar/scan", "/pose/fused"]
    fix = orjson.loads(messages[2].data)
    assert (fix["latitude"], fix["longitude"]) == (LAT, LON)
    # Without a scan or a fusion: neither channel.
    messages, _ = projection.channel_messages(None, Snapshot({LidarView: LidarView()}), 5)
    assert [m.spec.topic for m in messages] == ["/telemetry/lidar_view"]
    log_odds, origin = grid_with_post()
    image = grid_image(LAT, LON, origin, 0.1, log_odds, scans=3)
    assert image is not None
    grid = orjson.loads(projection.grid_message(image, 7).data)
    assert grid["frame_id"] == schemas.GRID_FRAME
    assert grid["column_count"] == image.columns
    assert grid["row_stride"] == image.columns
    assert grid["cell_stride"] == 1
    assert base64.b64decode(grid["data"]) == image.cells
    assert grid["pose"]["position"]["x"] == image.x_m
    assert UNKNOWN not in image.cells[: image.columns]  # the crop starts at what was seen


def test_a_long_seen_free_cell_is_0_percent_without_overflow() -> None:
    """Log-odds far past float32 exp()'s range (a cell seen free for minutes) read 0 % and
    100 %, without a RuntimeWarning (one rose from a driven loop's grid)."""
    log_odds, origin = grid_with_post()
    log_odds[log_odds < 0] = -500.0
    log_odds[log_odds > 0] = 500.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        image = grid_image(LAT, LON, origin, 0.1, log_odds, scans=3)
    assert image is not None
    assert set(image.cells) == {0, 100}


async def test_foxglove_live_fetches_a_grid_again_after_a_failed_fetch() -> None:
    """A grid revision whose fetch failed (a timeout on a loaded link) is fetched at the next
    snapshot: a robot that stopped draws no new revision, so waiting for one left ``/grid``
    empty (a Foxglove client waited 60 s for it in a whole-suite run)."""
    import foxglove

    from stationd.foxglove_live import FoxgloveLive, _PlatformChannels

    log_odds, origin = grid_with_post()
    image = grid_image(LAT, LON, origin, 0.1, log_odds, scans=3)
    assert image is not None
    answers: list[Any] = [TimeoutError(), image.to_json(4)]

    async def call_local(method: str, **params: Any) -> Any:
        assert (method, params) == ("perception_grid", {"platform_id": "rover-g"})
        answer = answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return answer

    ctx: Any = types.SimpleNamespace(bus=Bus(), api=types.SimpleNamespace(call_local=call_local))
    live = FoxgloveLive(ctx)
    platform = _PlatformChannels("rover-g", foxglove.Context())
    for _ in range(2):  # the same revision twice: the robot drew no new grid
        platform.pending = Snapshot({LidarView: LidarView(grid_rev=4)})
        await live._project(platform)
    assert answers == []
    assert platform.grid_data is not None
    assert base64.b64decode(orjson.loads(platform.grid_data)["data"]) == image.cells
    assert platform.grid_rev == 4


async def test_through_the_daemon_the_scan_grid_and_fused_pose_are_shown_and_recorded(
    robot_factory: Any, tmp_path: Path
) -> None:
    """A --sim rover with the lidar drives past a post the map does not have: its telemetry
    carries the post in the scan's sectors and the fused pose, ``get_grid`` hands out a grid
    in which the post's cell is occupied, and the recorder writes ``/grid`` and
    ``/pose/fused``."""
    post = (10.0, 3.0, 0.4)
    recordings = tmp_path / "recordings"
    robot: Robot = await robot_factory(
        *RTK,
        "lidar.enabled=true",
        f"lidar.grid_file={tmp_path / 'grid.npz'}",
        GRID_PERIOD,
        f"sim.obstacles_file={obstacles_file(tmp_path, post)}",
        "recorder.enabled=true",
        f"recorder.dir={recordings}",
    )
    closest: list[float] = []
    robot.watchers.append(lambda _pose, _truth: closest.append(clearance(robot, *post)))
    await robot.call("set_waypoints", waypoints=[at(0, 0), at(20, 0)])
    await until_armable(robot.ctx)
    await robot.call("patrol_start")

    def view() -> LidarView | None:
        return robot.ctx.telemetry.build().get(LidarView)

    def post_in_scan() -> bool:
        shown = view()
        return shown is not None and any(0 < dm <= 120 for dm in shown.ranges_dm)

    await wait_until(post_in_scan, 20)
    await wait_until(lambda: (v := view()) is not None and v.fused_lat is not None, 30)
    await wait_until(lambda: (v := view()) is not None and v.grid_rev > 0, 30)

    def past_it() -> bool:  # and the grid made again since: it holds the post's scans
        pose = robot.vehicle.pose()
        return robot.local(pose.latitude, pose.longitude)[0] > post[0] + 2

    await wait_until(past_it, 40)
    rev = view()
    assert rev is not None
    await wait_until(lambda: (v := view()) is not None and v.grid_rev > rev.grid_rev, 15)
    grid = grid_from_json(await robot.call("get_grid"))
    frame = LocalFrame(grid.latitude, grid.longitude)
    x, y = frame.to_local(*LocalFrame(LAT, LON).to_geo(post[0], post[1] - post[2]))
    cells = np.frombuffer(grid.cells, dtype=np.uint8).reshape(grid.rows, grid.columns)
    near = [
        int(cells[r, c])
        for r in range(grid.rows)
        for c in range(grid.columns)
        if cells[r, c] != UNKNOWN
        and math.dist(
            (grid.x_m + (c + 0.5) * grid.cell_m, grid.y_m + (r + 0.5) * grid.cell_m), (x, y)
        )
        < 1.5
    ]
    # The post is an obstacle in the grid where it is, give or take the fused pose's error
    # (the grid is drawn at the fused pose, not the simulator's truth).
    assert near, near
    assert max(near) >= 65, near
    fused = robot.ctx.bus.last(topics.FUSED_POSE)
    assert fused is not None
    await robot.daemon.stop()
    from mcap.reader import make_reader

    files = sorted(recordings.rglob("*.mcap"))
    assert files
    counts: dict[str, int] = {}
    for path in files:
        with path.open("rb") as handle:
            for _schema, channel, _message in make_reader(handle).iter_messages():
                counts[channel.topic] = counts.get(channel.topic, 0) + 1
    assert counts.get("/grid", 0) >= 1, counts
    assert counts.get("/pose/fused", 0) >= 1, counts
    assert counts.get("/pose/fused/local", 0) >= 1
    assert counts.get("/lidar/scan", 0) >= 1


async def test_a_foxglove_client_gets_the_scan_the_grid_and_the_fused_pose(
    platform_factory: Any, fleet_key: bytes, tmp_path: Path
) -> None:
    """Foxglove live (a real ``@foxglove/ws-protocol`` client): the platform's scan, occupancy
    grid and fused pose, from its telemetry and ``get_grid``, while it drives past a post."""
    from support.cli import run_cli
    from support.foxglove import subscribe
    from support.patrol import config

    from platformd.perception_view import PerceptionView
    from stationd.foxglove_live import FoxgloveLive

    post = (10.0, 3.0, 0.4)
    platform = await platform_factory(
        config(
            tmp_path,
            "platform.id=rover-lv",
            *RTK,
            "lidar.enabled=true",
            f"lidar.grid_file={tmp_path / 'grid.npz'}",
            GRID_PERIOD,
            f"sim.obstacles_file={obstacles_file(tmp_path, post)}",
        ),
        fleet_key,
    )
    await platform.ctx.rpc.call_local("set_waypoints", waypoints=[at(0, 0), at(40, 0)])
    await until_armable(platform.ctx)
    await platform.ctx.rpc.call_local("patrol_start")
    async with running_station(fleet_key, "foxglove.port=0") as station:
        (live,) = [a for a in station.supervisor.actors if isinstance(a, FoxgloveLive)]
        await asyncio.wait_for(live.serving.wait(), 30)
        code, _, err = await run_cli(
            station, "connect", "rover-lv", "--url", platform.ctx.signaling_url
        )
        assert code == 0, err
        wanted = ("/lidar/scan", "/pose/fused", "/grid")
        lines = await subscribe(live.port, 1, *wanted)
        # A client subscribing later gets the grid last published, though no new one comes
        # (the channel was advertised with the first grid, which a subscriber then missed).
        (view,) = [a for a in platform.supervisor.actors if isinstance(a, PerceptionView)]
        view.grid_period_s = 3600.0
        rev = view.grid_rev
        later = await subscribe(live.port, 1, "/grid")
        assert view.grid_rev == rev
        assert [line["topic"] for line in later if "topic" in line] == ["/grid"], later
    messages = {line["topic"]: line for line in lines if "topic" in line}
    assert set(messages) == set(wanted), lines
    scan = messages["/lidar/scan"]
    assert scan["schema"] == "foxglove.LaserScan"
    assert len(scan["json"]["ranges"]) == 72
    assert any(r > 0 for r in scan["json"]["ranges"])
    fused = messages["/pose/fused"]["json"]
    assert abs(fused["latitude"] - LAT) < 0.001
    assert abs(fused["longitude"] - LON) < 0.001
    grid = messages["/grid"]
    assert grid["schema"] == "foxglove.Grid"
    assert grid["json"]["frame_id"] == "grid"
    assert grid["json"]["fields"] == [{"name": "occupancy", "offset": 0, "type": 1}]
    assert grid["json"]["column_count"] > 10
    assert grid["json"]["cell_size"]["x"] >= 0.1
    # (The client keeps the first 48 bytes of the cells; the cells are checked in full above.)
    assert grid["bytes"] > grid["json"]["column_count"] * 10


def test_a_planner_change_geos_cannot_make_falls_back_to_a_full_build(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The town bench's stuck patrol: after many lidar keep-outs came and went, GEOS could not
    difference the free space ("Ring edge missing") and every later map revision failed, the
    patrol holding. The worker builds the graph again from the map instead."""
    import socket
    import threading

    import shapely.errors

    from brasidas.autonomy.areamap import parse_map
    from brasidas.autonomy.planner import Planner
    from brasidas.autonomy.planner_worker import _Worker
    from platformd.sim.demo_area import demo_map, offset

    area = parse_map(demo_map(LAT, LON))
    ring = [list(reversed(offset(LAT, LON, x, y))) for x, y in ((5, 5), (6, 5), (6, 6), (5, 5))]
    post = {
        "type": "Feature",
        "id": "lidar:1",
        "properties": {"role": "keepout", "source": "lidar"},
        "geometry": {"type": "Polygon", "coordinates": [ring]},
    }
    changed = area.with_keepouts([post])
    left, right = socket.socketpair()
    try:
        worker = _Worker(left)
        worker.area = area
        worker.planner = Planner(area.boundary, area.keepouts, 2.0)

        def broken(*_args: Any, **_kwargs: Any) -> Any:
            raise shapely.errors.GEOSException("TopologyException: Ring edge missing at 19.5 4.1")

        monkeypatch.setattr(Planner, "changed", broken)
        planner, incremental = worker._planner_for(changed, 2.0, threading.Event())
        assert not incremental  # built again from the map, with the post in it
        start = area.frame.to_local(*offset(LAT, LON, 0.0, 0.0))
        corner = area.frame.to_local(*offset(LAT, LON, 40.0, 30.0))
        assert len(planner.plan(start, corner).points) >= 2
    finally:
        left.close()
        right.close()


async def test_the_first_grid_image_comes_at_the_first_look_with_scans_not_a_period_later() -> None:
    """The start's look found no grid yet and still started the period: the console's first
    grid came a whole ``lidar.grid_period_s`` later (6.7 s of a browser test's wait)."""
    from brasidas.clock import ManualClock
    from brasidas.perception.grid import OccupancyGrid
    from brasidas.perception.odometry import Pose2D
    from platformd.perception_view import POSE_PERIOD_S, PerceptionView

    clock = ManualClock()
    localizer: Any = types.SimpleNamespace(grid=None, fused=None, frame=None)
    reader: Any = types.SimpleNamespace(clock=clock, last=None, localizer=localizer)
    view = PerceptionView(Bus(), reader, clock=clock, grid_period_s=5.0)
    task = asyncio.get_running_loop().create_task(view.run())
    try:
        for _ in range(3):  # the start's looks: no grid yet
            await asyncio.sleep(0)
        grid = OccupancyGrid(LAT, LON)
        wall = np.column_stack((np.full(40, 3.0), np.linspace(-2.0, 2.0, 40)))
        grid.integrate(Pose2D(0.0, 0.0, 0.0), wall)
        localizer.grid = grid
        clock.advance(POSE_PERIOD_S)
        await wait_until(lambda: view.grid_rev == 1, 5)
        # Then the period holds: a scan more is drawn only 5 s after that image.
        grid.integrate(Pose2D(0.1, 0.0, 0.0), wall)
        clock.advance(POSE_PERIOD_S)
        for _ in range(20):
            await asyncio.sleep(0.01)
        assert view.grid_rev == 1
        clock.advance(5.0)
        await wait_until(lambda: view.grid_rev == 2, 5)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
