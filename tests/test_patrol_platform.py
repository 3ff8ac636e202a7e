"""The patrol on a --sim platform: the real drivers against the simulated AX3500, GPS and IMU.

The simulated robot here is an 18 km/h one (``platform.max_speed_kmh``, patrolling at full
speed, braking at 6 m/s²) and its GPS sends 10 epochs a second, so laps take seconds; the
drivers, the pose filter and the patrol run unchanged. They run in wall time: the platform's
actors, the IMU's thread and the ptys share the event loop's real clock, so no simulated clock
can run them faster; the same patrol on a simulated clock is ``test_autonomy_core``. The
closed-route test's robot has an RTK-corrected receiver (``sim.gps_receiver = "rtk"``, 0.02 m per
axis, with the matching autonomy keys), so its true position is checked against the waypoints and
the keep-out; the other robots keep the default NEO-6M (2.5 m CEP, wandering over minutes: an
offset no estimator on the robot can see, so no true position could pass within 2 m).
"""

from __future__ import annotations

import asyncio
import itertools
import math
import os
import signal
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from support.patrol import LAT, LON, RTK, Robot, at

from brasidas import topics
from brasidas.codecs.jsonrpc import RpcError
from brasidas.messages import PoseEstimate, Velocity
from platformd.autonomy.patrol import PatrolActor
from platformd.beacon import BeaconAdvertiser
from platformd.mode import ModeArbiter
from platformd.session_table import Session
from platformd.sim.demo_area import demo_map, offset


async def wait_for_state(robot: Robot, state: str, timeout: float = 10.0) -> None:
    await wait_until(lambda: robot.status.state == state, timeout)


async def test_closed_route_twice_around_a_keepout_never_entered(robot_factory: Any) -> None:
    robot: Robot = await robot_factory(*RTK)
    # The route and the rock are drawn around where the robot says it is, as an operator
    # would draw them: the receiver's error (metres) must not put the start beside the rock,
    # where it would have no room to find its heading.
    here = robot.ctx.bus.last(topics.POSE)
    assert here is not None
    x0, y0 = robot.local(here.latitude, here.longitude)
    west, east, south, north = x0 + 3.5, x0 + 4.5, y0 - 0.5, y0 + 0.5
    box = [offset(LAT, LON, e, n) for e, n in ((west, south), (east, south), (east, north),
                                              (west, north), (west, south))]  # fmt: skip
    rock = {
        "type": "Feature",
        "id": "rock",
        "properties": {"role": "keepout"},
        "geometry": {"type": "Polygon", "coordinates": [[[lon, lat] for lat, lon in box]]},
    }
    await robot.call("update_map", add=[rock])
    corners = [(x0 + e, y0 + n) for e, n in ((0, 0), (8, 0), (8, 4), (0, 4))]
    answer = await robot.call("set_waypoints", waypoints=[at(*c) for c in [*corners, corners[0]]])
    assert answer["closed"]
    entered: list[tuple[str, float, float]] = []

    def in_rock(pose: PoseEstimate, truth: tuple[float, float]) -> None:
        for what, (e, n) in (
            ("truth", truth),
            ("pose", robot.local(pose.latitude, pose.longitude)),
        ):
            if west <= e <= east and south <= n <= north:
                entered.append((what, e, n))

    robot.watchers.append(in_rock)
    await robot.call("patrol_start")
    await robot.drive_laps(2)
    assert not entered, entered
    # Each corner passed on each lap: by the robot's own pose within 1.5 m (arrival tolerance
    # 0.5 m), and by the true position within 2 m.
    for index, corner in enumerate(corners):
        believed = [math.dist(corner, robot.local(p.latitude, p.longitude)) for p, _ in robot.poses]
        passes = sum(1 for a, b in itertools.pairwise(believed) if a < 1.5 <= b)
        assert passes >= 2, (index, passes)
        assert min(math.dist(corner, truth) for _, truth in robot.poses) < 2.0
    targets = [r.waypoint for r in robot.reports if r.state == "patrolling"]
    order = [t for i, t in enumerate(targets) if i == 0 or t != targets[i - 1]]
    assert order[:8] == [0, 1, 2, 3, 0, 1, 2, 3]
    # The next leg is planned while the robot drives this one: it does not stop at each
    # waypoint to wait for the planner process (a station would hear "holding" each time).
    waits = [h for h in robot.history() if h[3].startswith("planning the path")]
    assert len(waits) <= 2, robot.history()


async def test_open_route_is_driven_back_in_reverse(robot_factory: Any) -> None:
    robot: Robot = await robot_factory()
    answer = await robot.call("set_waypoints", waypoints=[at(0, 0), at(5, 0), at(10, 0)])
    assert not answer["closed"]
    await robot.call("patrol_start")

    def order() -> list[int | None]:
        targets = [r.waypoint for r in robot.reports if r.state == "patrolling"]
        return [t for i, t in enumerate(targets) if i == 0 or t != targets[i - 1]]

    await wait_until(lambda: order()[:4] == [0, 1, 2, 1], 60)
    assert robot.status.lap == 0


async def test_override_gps_loss_and_map_reload(robot_factory: Any) -> None:
    robot: Robot = await robot_factory()
    await robot.call("set_waypoints", waypoints=[at(0, 0), at(25, 0), at(25, 20), at(0, 0)])
    await robot.call("patrol_start")
    bus = robot.ctx.bus
    await wait_until(lambda: robot.status.waypoint == 1 and robot.vehicle.pose().speed_mps > 2, 30)

    assert BeaconAdvertiser(robot.ctx).current().status.autonomy  # the status word's bit 10

    # The operator takes over mid-leg: path following stops at once, their velocities drive.
    mode = next(a for a in robot.daemon.supervisor.actors if isinstance(a, ModeArbiter))
    operator = Session("operator", "station-1", "127.0.0.1", None, 0.0, 0.0)
    assert mode.request(True, operator).accepted
    assert robot.status.state == "suspended"  # inside the override's delivery, not 100 ms later
    published = len(robot.cmd_vel)
    bus.publish(topics.TELEOP_VELOCITY, Velocity(0.0, 0.6))
    motion = bus.last(topics.MOTION_STATE)
    assert motion is not None
    assert motion.command == Velocity(0.0, 0.6)
    for _ in range(5):  # the operator turns the robot for half a second
        await asyncio.sleep(0.1)
        bus.publish(topics.TELEOP_VELOCITY, Velocity(0.0, 0.6))
    assert len(robot.cmd_vel) == published
    assert mode.request(False, operator).accepted
    # Replanned in the planner process: the patrol holds (saying so) until the path comes.
    assert robot.status.state == "holding"
    assert robot.status.waypoint == 1
    assert robot.status.reason.startswith("planning the path to waypoint")
    await wait_for_state(robot, "patrolling", 10)
    await wait_until(lambda: len(robot.cmd_vel) > published + 5, 5)
    path = robot.status.path  # replanned from where the operator left it
    here = robot.ctx.bus.last(topics.POSE)
    assert here is not None
    assert path
    assert math.dist(robot.local(*path[0]), robot.local(here.latitude, here.longitude)) < 3.0

    # The GPS goes silent: hold (motors to zero) and say why; it comes back: go on.
    gps = robot.ctx.sim.gps
    assert gps is not None
    epoch = gps.generator.epoch
    gps.generator.epoch = lambda pose, utc: b""
    await wait_for_state(robot, "holding", 5)
    assert "GPS fix" in robot.status.reason
    assert robot.cmd_vel[-1] == Velocity(0.0, 0.0)
    await wait_until(lambda: abs(robot.vehicle.pose().speed_mps) < 0.05, 5)
    gps.generator.epoch = epoch
    await wait_for_state(robot, "patrolling", 5)

    # A map reload wipes the waypoints and stops the robot.
    await robot.call("load_map", map=demo_map(LAT, LON))
    assert robot.status.state == "stopped"
    assert robot.status.waypoints == 0
    assert robot.status.reason == "map loaded: waypoints cleared"
    assert robot.cmd_vel[-1] == Velocity(0.0, 0.0)
    await wait_until(lambda: abs(robot.vehicle.pose().speed_mps) < 0.05, 5)
    assert not BeaconAdvertiser(robot.ctx).current().status.autonomy
    with pytest.raises(RpcError, match="cannot start: no waypoints"):
        await robot.call("patrol_start")


async def test_invalid_maps_and_waypoints_are_refused_and_a_restart_keeps_the_route(
    robot_factory: Any,
) -> None:
    robot: Robot = await robot_factory()
    before = await robot.call("get_map")
    elsewhere = demo_map(LAT + 0.01, LON)  # a valid map whose boundary is 1 km away
    refusals = {
        "not JSON": "{broken",
        "self-intersection": _bowtie(),
        "the robot .* is outside the map's boundary": elsewhere,
    }
    for reason, bad in refusals.items():
        with pytest.raises(RpcError, match=f"map refused: .*{reason}"):
            await robot.call("load_map", map=bad)
    assert await robot.call("get_map") == before  # the old map stays
    with pytest.raises(RpcError, match="waypoints refused: waypoint 2 .* outside the map"):
        await robot.call("set_waypoints", waypoints=["sw", at(0, 200)])
    with pytest.raises(RpcError, match="waypoints refused: waypoint 1 .* keep-out zone 'shed'"):
        await robot.call("set_waypoints", waypoints=[at(20, 15)])
    with pytest.raises(RpcError, match="'lake' is neither LAT,LON nor a named point"):
        await robot.call("set_waypoints", waypoints=["sw", "lake"])
    with pytest.raises(RpcError, match="update refused: no keep-out zone 'barn'"):
        await robot.call("update_map", remove=["barn"])

    # Stored on the platform: a new daemon on the same files has the route and patrols it.
    await robot.call("load_map", map=demo_map(LAT, LON))
    route = await robot.call("set_waypoints", waypoints=["sw", "se", "ne", "sw"])
    arming = robot.ctx.arming
    assert arming is not None
    await wait_until(lambda: not arming.reasons(), 20)
    await robot.call("patrol_start")  # the operator's last word: start (issue 27)
    await wait_until(lambda: arming.last_word is not None and arming.last_word.word == "start")
    await robot.daemon.stop()
    again: Robot = await robot_factory("arming.countdown_s=0")
    stored = await again.call("get_map")
    assert stored["route"] == route["waypoints"]
    assert stored["closed"]
    # Autostart resumes it once the pre-arm checks pass (issue 27: no operator said stop).
    await wait_for_state(again, "patrolling", 20)
    assert again.status.waypoints == 4


def _bowtie() -> dict[str, Any]:
    data = demo_map(LAT, LON)
    ring = data["features"][1]["geometry"]["coordinates"][0]
    ring[1], ring[2] = ring[2], ring[1]
    return data


# --------------------------------------------------------------------------- planner process


def patrol_of(robot: Robot) -> PatrolActor:
    return next(a for a in robot.daemon.supervisor.actors if isinstance(a, PatrolActor))


def alive(pid: int) -> bool:
    """The process exists and is not a zombie (a killed child not yet reaped counts as gone
    only once it is reaped: /proc keeps a zombie)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


async def test_the_planner_process_dying_holds_the_patrol_which_says_why_and_recovers(
    robot_factory: Any,
) -> None:
    robot: Robot = await robot_factory()
    patrol = patrol_of(robot)
    await robot.call("set_waypoints", waypoints=[at(0, 0), at(25, 0), at(25, 20), at(0, 0)])
    await robot.call("patrol_start")
    await wait_for_state(robot, "patrolling", 30)
    first = patrol.planner.pid
    assert first is not None
    assert first != os.getpid()
    os.kill(first, signal.SIGKILL)
    # The patrol holds, motors at zero, and says why; no plan is asked of a dead process.
    await wait_until(lambda: "planner process stopped" in robot.status.reason, 10)
    assert robot.status.state == "holding"
    assert "waiting for it to start again" in robot.status.reason
    assert robot.cmd_vel[-1] == Velocity(0.0, 0.0)
    # Another process is started, gets the map again, and the patrol goes on.
    await wait_until(lambda: patrol.planner.pid not in (None, first) and patrol.planner_ready, 30)
    assert not alive(first)
    await wait_for_state(robot, "patrolling", 30)
    assert patrol.planner.restarts == 1


async def test_a_plan_for_an_old_map_revision_is_dropped(robot_factory: Any) -> None:
    robot: Robot = await robot_factory()
    patrol = patrol_of(robot)
    await robot.call("set_waypoints", waypoints=[at(0, 0), at(25, 0), at(25, 20), at(0, 0)])
    await robot.call("patrol_start")
    await wait_for_state(robot, "patrolling", 30)
    # An answer made for the map before a keep-out was added: never followed.
    old = patrol.core.map_revision
    rock = [[list(reversed(offset(LAT, LON, e, n))) for e, n in
             ((40, 40), (42, 40), (42, 42), (40, 42), (40, 40))]]  # fmt: skip
    shed = {"type": "Feature", "id": "rock", "properties": {"role": "keepout"},
            "geometry": {"type": "Polygon", "coordinates": rock}}  # fmt: skip
    await robot.call("update_map", add=[shed])
    assert patrol.core.map_revision == old + 1
    dropped = patrol.core.stale_plans
    far = [robot.local(*offset(LAT, LON, 90, 90))] * 2
    for request in range(0, 1000):
        patrol._on_planner_answer(
            {"op": "path", "revision": old, "id": request, "points": [list(p) for p in far]}
        )
    assert patrol.core.stale_plans == dropped + 1000
    assert all(math.dist(robot.local(*p), far[0]) > 5 for p in robot.status.path)
    await wait_for_state(robot, "patrolling", 30)  # on the new map's own plan


async def test_daemon_stop_during_a_build_leaves_no_planner_process(
    robot_factory: Any, tmp_path: Path
) -> None:
    from platformd.sim.town import clear_around, town_map

    robot: Robot = await robot_factory()
    patrol = patrol_of(robot)
    here = robot.ctx.bus.last(topics.POSE)
    assert here is not None
    town = clear_around(town_map(here.latitude, here.longitude, buildings=1000, seed=3),
                        here.latitude, here.longitude)  # fmt: skip
    await robot.call("load_map", map=town)
    pid = patrol.planner.pid
    assert pid is not None
    assert alive(pid)
    assert not patrol.planner_ready  # building (a thousand buildings: seconds)
    loop = asyncio.get_running_loop()
    started = loop.time()
    robot.close()
    await robot.daemon.stop()
    stopped = loop.time() - started
    assert not alive(pid), f"planner process {pid} left behind"
    assert stopped < 5.0  # the daemon's whole stop (its SIGTERM budget is 1 s on a quiet box)
