"""Patrol: planning time on a 1 km² map with 50 keep-outs; cross-track error while following.

The cross-track figure comes from a kinematic simulation run faster than real time: the
simulated vehicle's model (``platformd.sim.vehicle``, first-order lag, 6 km/h), the simulated
GPS's error model (``platformd.sim.gps``: a NEO-6M's 2.5 m CEP, wandering over minutes; and
an RTK-corrected receiver's 0.02 m, with the platform configured for it) through its NMEA and the real decoder at 10 Hz, the IMU's yaw at 10 Hz, the real pose filter,
planner and pure pursuit at 10 Hz. The error is measured from the vehicle's true position to
the planned path, and from where the receiver puts the vehicle (the part the platform controls).
"""

from __future__ import annotations

import math
import os
import random
import statistics
import time
from typing import Any

from shapely import Point, box, unary_union
from shapely.affinity import rotate

from brasidas.autonomy.areamap import parse_map
from brasidas.autonomy.follower import FollowerParameters
from brasidas.autonomy.patrol import Patrol, PatrolParameters
from brasidas.autonomy.planner import Planner, Unreachable, cross_track
from brasidas.autonomy.route import parse_waypoints
from brasidas.config import PlatformConfig, load_config
from brasidas.config.platform import AutonomySection
from brasidas.messages import PatrolState
from platformd.sim.demo_area import demo_map, demo_route
from platformd.sim.gps import NEO_6M, RTK, ReceiverErrors
from platformd.sim.kinematic import KinematicRun

SPEED_KMH = 6.0
FULL_TURN_RATE = 1.5
START = (37.9415, 23.6530)


async def run() -> dict[str, Any]:
    figures = planning()
    figures.update(await town())
    figures.update(largest())
    figures.update(following())
    figures.update(await platform_cpu())
    return figures


async def town(
    buildings: int = 1000, edits: int = 10, plans: int = 200, floor_s: float = 10.0
) -> dict[str, Any]:
    """A town of ``buildings`` (``platformd.sim.town``: OSM-like footprints, streets, names)
    on a --sim platform: load, the graph's build in the planner process, one keep-out added
    and removed while it patrols (answer, event-loop stall, the graph's change), the patrol's
    plans (round trip to the planner process), RSS of both processes; the event loop's stall
    against the same patrol with nothing built, in the same run (the machine's floor)."""
    import asyncio
    import json
    import tempfile
    from pathlib import Path

    from bench.support import percentiles
    from brasidas import topics
    from brasidas.autonomy.areamap import MAX_VERTICES
    from brasidas.limits import MAP_REQUEST_MAX_BYTES
    from platformd.app import PlatformDaemon
    from platformd.autonomy.patrol import PatrolActor
    from platformd.sim.town import clear_around, town_map

    data = clear_around(town_map(*START, buildings=buildings, seed=1), *START, 12.0)
    text = json.dumps(data)
    loads = []
    for _ in range(3):
        started = time.perf_counter()
        area = parse_map(text)
        loads.append(time.perf_counter() - started)
    clearance = PatrolParameters.clearance_m
    started = time.perf_counter()
    planner = Planner(area.boundary, area.keepouts, clearance)
    build = time.perf_counter() - started
    rng = random.Random(3)
    free = [
        p for p in ((rng.uniform(-400, 400), rng.uniform(-400, 400)) for _ in range(4000))
        if area.inside(*p) and _clear(area, p, clearance + 1.0)
    ]  # fmt: skip
    times = []
    for a, b in zip(free[:plans], free[plans : 2 * plans], strict=False):
        started = time.perf_counter()
        try:
            planner.plan(a, b)
        except Unreachable:
            continue
        times.append((time.perf_counter() - started) * 1000)
    plan = percentiles(times)

    folder = Path(tempfile.mkdtemp(prefix="bench-town-"))
    config = load_config(
        PlatformConfig,
        None,
        [
            "signaling.port=0", "velocity.port=0", "beacon.enabled=false",
            "navcam.enabled=false", "audio.enabled=false", "sim.enabled=true",
            "motor.enabled=true", "gps.enabled=true", "imu.enabled=true", "gps.sim_rate_hz=10",
            f"map.file={folder / 'map.geojson'}", f"autonomy.route_file={folder / 'route.json'}",
        ],
    )  # fmt: skip
    daemon = PlatformDaemon(config, None)
    await daemon.start()
    stalls: list[float] = []
    floor_stalls: list[float] = []
    phases: dict[str, tuple[int, int]] = {}
    probe_task: asyncio.Task[None] | None = None

    async def probe() -> None:
        loop = asyncio.get_running_loop()
        while True:
            due = loop.time() + 0.005
            await asyncio.sleep(0.005)
            stalls.append((loop.time() - due) * 1000)

    try:
        bus = daemon.ctx.bus
        await _until(lambda: bus.last(topics.POSE) is not None)
        patrol = next(a for a in daemon.supervisor.actors if isinstance(a, PatrolActor))
        rpc = daemon.ctx.rpc
        probe_task = asyncio.get_running_loop().create_task(probe())
        await _until(lambda: patrol.planner.pid is not None)
        await asyncio.sleep(1.0)
        rss_before = _rss_mb() + _rss_mb(patrol.planner.pid)
        started = time.perf_counter()
        mark = len(stalls)
        await rpc.call_local("load_map", map=text)
        load_answer = time.perf_counter() - started
        await _until(lambda: patrol.planner_ready)
        load_ready = time.perf_counter() - started
        phases["load"] = (mark, len(stalls))
        load_build = patrol.last_build_s or 0.0
        rss_parent, rss_planner = _rss_mb(), _rss_mb(patrol.planner.pid)
        route = [area.frame.to_geo(*p) for p in _loop_points(area, planner, free)]
        await rpc.call_local(
            "set_waypoints", waypoints=[f"{lat:.7f},{lon:.7f}" for lat, lon in route]
        )
        arming = daemon.ctx.arming
        assert arming is not None  # a start arms through the pre-arm checks (issue 27)
        await _until(lambda: not arming.reasons())
        await rpc.call_local("patrol_start")
        # The machine's floor in this run: the same patrol on the same map, nothing built
        # (half before the edits, half after: the machine's load drifts).
        mark = len(stalls)
        await asyncio.sleep(floor_s / 2)
        floor_stalls = stalls[mark:]
        answers, rebuilds, blocks, loop_cpu = [], [], [], []
        mark = len(stalls)
        for index in range(edits):
            x, y = free[-1 - index]
            shed = {
                "type": "Feature",
                "id": f"bench-shed-{index}",
                "properties": {"role": "keepout"},
                "geometry": {
                    "type": "Polygon",
                    "coordinates": [
                        [
                            list(reversed(area.frame.to_geo(x + dx, y + dy)))
                            for dx, dy in ((0, 0), (4, 0), (4, 4), (0, 4), (0, 0))
                        ]
                    ],
                },
            }
            for kind, change in (("add", {"add": [shed]}), ("remove", {"remove": [shed["id"]]})):
                first = len(stalls)
                started, cpu = time.perf_counter(), time.thread_time()
                try:
                    await rpc.call_local("update_map", **change)
                except Exception:  # the robot may be standing where the shed would go
                    continue
                answers.append((time.perf_counter() - started) * 1000)
                loop_cpu.append((time.thread_time() - cpu) * 1000)
                await _until(lambda: patrol.planner_ready)
                rebuilds.append((kind, (patrol.last_build_s or 0.0) * 1000))
                blocks.append(max(stalls[first:], default=0.0))
        await asyncio.sleep(1.0)
        phases["edits"] = (mark, len(stalls))
        mark = len(stalls)
        await asyncio.sleep(floor_s / 2)
        floor_stalls += stalls[mark:]
        rss_after = _rss_mb(), _rss_mb(patrol.planner.pid)
        state = patrol.core.state.value
        trips = [trip * 1000 for trip, _ in patrol.plan_times]
        inside = [spent * 1000 for _, spent in patrol.plan_times]
    finally:
        if probe_task is not None:
            probe_task.cancel()
            await asyncio.gather(probe_task, return_exceptions=True)
        await daemon.stop()

    def stall(phase: str) -> dict[str, float]:
        first, last = phases.get(phase, (0, 0))
        part = (floor_stalls if phase == "floor" else stalls[first:last]) or [0.0]
        return {**percentiles(part), "max": round(max(part), 1)}

    load, floor, edited = stall("load"), stall("floor"), stall("edits")
    added = [ms for kind, ms in rebuilds if kind == "add"] or [0.0]
    removed = [ms for kind, ms in rebuilds if kind == "remove"] or [0.0]
    return {
        "town_buildings": len(area.keepouts),
        "town_vertices": area.summary()["vertices"],
        "town_geojson_kb": round(len(text) / 1024, 1),
        "town_parse_ms_median": round(statistics.median(loads) * 1000, 1),
        "town_planner_build_ms": round(build * 1000, 1),
        "town_planner_nodes": len(planner.nodes),
        "town_planner_edges": planner.edge_count,
        "town_plan_p50_ms": plan["p50"],
        "town_plan_p99_ms": plan["p99"],
        "town_load_map_answer_ms": round(load_answer * 1000, 1),
        "town_load_map_to_plan_ready_ms": round(load_ready * 1000, 1),
        "town_load_planner_process_build_ms": round(load_build * 1000, 1),
        "town_rss_before_map_mb": rss_before,
        "town_rss_with_map_mb": f"{rss_parent + rss_planner:.1f} "
        f"(platform {rss_parent}, planner process {rss_planner})",
        "town_rss_after_edits_mb": f"{sum(rss_after):.1f} "
        f"(platform {rss_after[0]}, planner process {rss_after[1]})",
        "town_update_map_answer_p50_ms": percentiles(answers or [0.0])["p50"],
        "town_update_map_answer_p99_ms": percentiles(answers or [0.0])["p99"],
        "town_update_map_loop_block_p99_ms": percentiles(blocks or [0.0])["p99"],
        "town_update_map_loop_cpu_p50_ms": percentiles(loop_cpu or [0.0])["p50"],
        "town_update_map_loop_cpu_p99_ms": percentiles(loop_cpu or [0.0])["p99"],
        "town_update_map_add_rebuild_p50_ms": percentiles(added)["p50"],
        "town_update_map_add_rebuild_max_ms": round(max(added), 1),
        "town_update_map_remove_rebuild_p50_ms": percentiles(removed)["p50"],
        "town_update_map_remove_rebuild_max_ms": round(max(removed), 1),
        "town_update_map_count": len(answers),
        "town_patrol_plans": len(trips),
        "town_patrol_plan_round_trip_p50_ms": percentiles(trips or [0.0])["p50"],
        "town_patrol_plan_round_trip_p99_ms": percentiles(trips or [0.0])["p99"],
        "town_patrol_plan_in_process_p99_ms": percentiles(inside or [0.0])["p99"],
        "town_loop_stall_floor_p50_ms": floor["p50"],
        "town_loop_stall_floor_p99_ms": floor["p99"],
        "town_loop_stall_floor_max_ms": floor["max"],
        "town_loop_stall_load_p99_ms": load["p99"],
        "town_loop_stall_load_max_ms": load["max"],
        "town_loop_stall_edits_p50_ms": edited["p50"],
        "town_loop_stall_edits_p99_ms": edited["p99"],
        "town_loop_stall_edits_max_ms": edited["max"],
        "town_load_average": " ".join(f"{x:.1f}" for x in os.getloadavg()),
        "town_patrol_state_after": state,
        "town_limits": (
            f"{MAX_VERTICES} vertices (planner build time and memory), "
            f"{MAP_REQUEST_MAX_BYTES} bytes per request (brasidas.limits)"
        ),
        "town_note": (
            "stall: lateness of a 5 ms sleep on the platform's event loop; load: from "
            "load_map until the planner process has the graph; floor: the same patrol on the "
            f"same map for {floor_s:g} s (half before the edits, half after) with nothing built (the machine's own lateness at "
            "this load); edits: a keep-out added and removed while it patrols, until each "
            "graph is ready; loop_block: the longest stall during each update_map; loop_cpu: the event "
            "loop thread's CPU from the call to its answer (update_map's share, and whatever "
            "else ran on the loop meanwhile); rebuild: "
            "the graph's change in the planner process (add, remove); plan round trip: asked "
            "on the event loop, answered by the planner process"
        ),
    }


async def _until(predicate: Any, timeout: float = 300.0) -> None:
    import asyncio

    for _ in range(int(timeout / 0.01)):
        if predicate():
            return
        await asyncio.sleep(0.01)
    raise TimeoutError("the platform did not get there")


def largest(buildings: int = 3400) -> dict[str, Any]:
    """The largest map the platform takes: a town just under the vertex cap; its size on the
    wire against the request limit, its parse and its planner's build (what bounds it)."""
    import json
    import resource

    from brasidas.autonomy.areamap import MAX_VERTICES
    from brasidas.limits import MAP_REQUEST_MAX_BYTES
    from platformd.sim.town import town_map

    text = json.dumps(town_map(*START, buildings=buildings, seed=4))
    started = time.perf_counter()
    area = parse_map(text)
    parse = time.perf_counter() - started
    started = time.perf_counter()
    planner = Planner(area.boundary, area.keepouts, PatrolParameters.clearance_m)
    build = time.perf_counter() - started
    return {
        "largest_map_buildings": len(area.keepouts),
        "largest_map_vertices": f"{area.vertices} of {MAX_VERTICES}",
        "largest_map_kb": f"{len(text) / 1024:.0f} of {MAP_REQUEST_MAX_BYTES / 1024:.0f}",
        "largest_map_parse_ms": round(parse * 1000, 1),
        "largest_map_planner_build_s": round(build, 1),
        "largest_map_planner_nodes": len(planner.nodes),
        "largest_map_planner_edges": planner.edge_count,
        "largest_map_bench_max_rss_mb": round(
            resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1
        ),
    }


def _rss_mb(pid: int | None = 0) -> float:
    """A process's resident memory (this one's by default; 0.0 for none)."""
    if pid is None:
        return 0.0
    with open(f"/proc/{pid or 'self'}/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return round(int(line.split()[1]) / 1024, 1)
    return 0.0


def _clear(area: Any, point: tuple[float, float], distance: float) -> bool:
    return not area.meets_keepout(Point(point).buffer(distance, quad_segs=2))


def _loop_points(
    area: Any, planner: Planner, free: list[tuple[float, float]]
) -> list[tuple[float, float]]:
    """Four free points 40-120 m from the start that the planner reaches: a closed loop."""
    start = area.local(*START)
    chosen = [start]
    for point in free:
        if 40 < math.dist(point, start) < 120:
            try:
                planner.plan(chosen[-1], point)
            except Unreachable:
                continue
            chosen.append(point)
            if len(chosen) == 4:
                break
    return [*chosen, start]


def planning(seed: int = 7, plans: int = 300) -> dict[str, Any]:
    """Plan between random free points of a 1 km x 1 km map with 50 rotated rectangles."""
    rng = random.Random(seed)
    boundary = box(0, 0, 1000, 1000)
    zones = []
    for _ in range(50):
        cx, cy = rng.uniform(60, 940), rng.uniform(60, 940)
        w, h = rng.uniform(10, 60), rng.uniform(10, 60)
        zones.append(
            rotate(box(cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2), rng.uniform(0, 90))
        )
    started = time.perf_counter()
    clearance = PatrolParameters.clearance_m  # the default: what a NEO-6M's error needs
    planner = Planner(boundary, zones, clearance=clearance)
    build = time.perf_counter() - started
    blocked = unary_union([zone.buffer(clearance) for zone in zones])
    inner = boundary.buffer(-clearance - 0.5)
    times: list[float] = []
    lengths: list[float] = []
    while len(times) < plans:
        a = (rng.uniform(0, 1000), rng.uniform(0, 1000))
        b = (rng.uniform(0, 1000), rng.uniform(0, 1000))
        if any(blocked.covers(Point(p)) or not inner.covers(Point(p)) for p in (a, b)):
            continue
        started = time.perf_counter()
        try:
            path = planner.plan(a, b)
        except Unreachable:
            continue
        times.append(time.perf_counter() - started)
        lengths.append(path.length / math.dist(a, b))
    times.sort()
    return {
        "plan_1km2_50_keepouts_p50_ms": round(statistics.median(times) * 1000, 2),
        "plan_1km2_50_keepouts_p99_ms": round(times[int(len(times) * 0.99)] * 1000, 2),
        "plan_graph_build_ms": round(build * 1000, 1),
        "plan_graph_nodes": len(planner.nodes),
        "plan_graph_edges": planner.edge_count,
        "plan_length_over_straight_mean": round(statistics.fmean(lengths), 3),
    }


RECEIVERS: dict[str, tuple[ReceiverErrors, tuple[str, ...]]] = {
    # The rover's receiver, the platform's defaults.
    "neo6m": (NEO_6M, ()),
    # An RTK-corrected receiver (u-blox ZED-F9P class, 0.01 m + 1 ppm CEP: platformd.sim.gps.RTK)
    # and the keys that tell the platform so: the fix's absolute error and its fix-to-fix noise,
    # 0.02 m per axis, and a clearance of the follower's tracking (0.9 m max at 6 km/h) instead
    # of 2 sigma of a NEO-6M's error.
    "rtk": (
        RTK,
        ("autonomy.gps_sigma_m=0.02", "autonomy.gps_jitter_m=0.02", "autonomy.clearance_m=1.0"),
    ),
}


def following(seeds: range = range(1, 11), laps: int = 2) -> dict[str, Any]:
    """Two laps of a closed 4-waypoint route around a keep-out at 6 km/h, once per seed (each
    seed a different receiver error: a NEO-6M's wanders over minutes, so one run sees one
    offset), with each receiver of :data:`RECEIVERS` and the platform configured for it."""
    figures: dict[str, Any] = {}
    for name, (receiver, overrides) in RECEIVERS.items():
        autonomy = load_config(PlatformConfig, None, overrides).autonomy
        runs = [_follow(seed, laps, receiver, autonomy) for seed in seeds]
        series = {key: [e for run in runs for e in run[key]] for key in FIGURES}
        per_run = sorted(statistics.fmean(run["truth"]) for run in runs)
        prefix = f"follow_6kmh_{name}"
        figures.update(
            {
                f"{prefix}_truth_mean_m": round(statistics.fmean(series["truth"]), 3),
                f"{prefix}_truth_max_m": round(max(series["truth"]), 3),
                f"{prefix}_truth_run_means_m": [round(m, 3) for m in per_run],
                f"{prefix}_receiver_mean_m": round(statistics.fmean(series["receiver"]), 3),
                f"{prefix}_receiver_max_m": round(max(series["receiver"]), 3),
                f"{prefix}_tracking_mean_m": round(statistics.fmean(series["tracking"]), 3),
                f"{prefix}_pose_error_mean_m": round(statistics.fmean(series["pose_truth"]), 3),
                f"{prefix}_pose_error_from_receiver_mean_m": round(
                    statistics.fmean(series["pose_receiver"]), 3
                ),
                f"{prefix}_pose_sigma_mean_m": round(statistics.fmean(series["sigma"]), 3),
                f"{prefix}_runs": len(runs),
                f"{prefix}_sim_seconds": round(sum(run["seconds"] for run in runs), 1),
            }
        )
    figures["follow_note"] = (
        "kinematic simulation (vehicle model; receiver error models: neo6m 2.5 m CEP wandering "
        "over minutes, the platform's defaults; rtk 0.02 m per axis, autonomy.gps_sigma_m and "
        "gps_jitter_m 0.02, clearance_m 1.0), not the full platform. truth: cross-track error "
        "of the true position to the planned path; receiver: of where the receiver puts the "
        "robot (the truth plus the receiver's error: what the platform itself controls); "
        "tracking: of the estimate"
    )
    return figures


FIGURES = ("truth", "receiver", "tracking", "pose_truth", "pose_receiver", "sigma")


def _follow(
    seed: int, laps: int, receiver: ReceiverErrors, autonomy: AutonomySection
) -> dict[str, Any]:
    lat0, lon0 = START
    area = parse_map(demo_map(lat0, lon0))
    route = parse_waypoints(demo_route(), area.points)
    full_speed = SPEED_KMH / 3.6
    patrol = Patrol(
        PatrolParameters(
            follower=FollowerParameters(
                cruise_speed=full_speed,
                max_turn_rate=1.0,
                full_speed=full_speed,
                full_turn_rate=FULL_TURN_RATE,
                lookahead_m=2.0,
                tolerance_m=0.5,
            ),
            clearance_m=autonomy.clearance_m,
        )
    )
    patrol.set_map(area)
    patrol.set_route(route)
    patrol.start()
    run = KinematicRun(
        patrol,
        area,
        start=START,
        seed=seed,
        max_yaw_rate=FULL_TURN_RATE,
        receiver=receiver,
        gps_sigma_m=autonomy.gps_sigma_m,
        gps_jitter_m=autonomy.gps_jitter_m,
    )
    figures: dict[str, Any] = {key: [] for key in FIGURES}
    while patrol.cursor.lap < laps and run.now < 600:
        tick = run.tick()
        status = patrol.status()
        estimate = tick.estimate
        if (
            status.state is PatrolState.PATROLLING
            and patrol.planned_path
            and estimate
            and estimate.heading_known
            and abs(tick.command.linear) > 0.5  # under way (not turning on the spot at a corner)
        ):
            path, here = patrol.planned_path, (estimate.x, estimate.y)
            figures["truth"].append(cross_track(path, tick.truth_xy))
            figures["receiver"].append(cross_track(path, tick.receiver_xy))
            figures["tracking"].append(cross_track(path, here))
            figures["pose_truth"].append(math.dist(tick.truth_xy, here))
            figures["pose_receiver"].append(math.dist(tick.receiver_xy, here))
            figures["sigma"].append(estimate.sigma_xy)
    figures["seconds"] = run.now
    return figures


async def platform_cpu(seconds: float = 20.0) -> dict[str, Any]:
    """CPU of the platform patrolling the demo loop (GPS 10 Hz, IMU 100 Hz, telemetry streamed
    at 5 Hz, no video), against the same platform not patrolling.

    The rover's devices run in a process of their own, as real devices do
    (``brasidas-platform simulate vehicle``: the AX3500 and the NEO-6M on ptys, one vehicle
    model). The MPU-6050 is on I2C, which a pty cannot carry: it stays emulated in the
    platform's process, on a twin of the vehicle model that the platform's own motor commands
    move, and what the emulated chip costs is measured apart and taken out (the real chip's
    cost is the I2C transfer, which the driver's calls still make).
    """
    import asyncio
    import socket
    import sys
    import tempfile
    from pathlib import Path

    from bench.support import cpu_seconds
    from brasidas import topics
    from brasidas.messages import MotionState
    from platformd import app
    from platformd.context import PlatformContext
    from platformd.sim import SimulatedDevices, mpu6050
    from platformd.sim.demo_area import demo_map, demo_route
    from platformd.sim.vehicle import vehicle_for
    from platformd.telemetry.aggregator import TelemetryAggregator

    devices = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "platformd", "--set", "gps.sim_rate_hz=10", "simulate", "vehicle",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL,
    )  # fmt: skip
    assert devices.stdout is not None
    motor_pty = (await asyncio.wait_for(devices.stdout.readline(), 10)).decode().strip()
    gps_pty = (await asyncio.wait_for(devices.stdout.readline(), 10)).decode().strip()
    folder = Path(tempfile.mkdtemp(prefix="bench-patrol-"))
    config = load_config(
        PlatformConfig,
        None,
        [
            "signaling.port=0",
            "velocity.port=0",
            "beacon.enabled=false",
            "navcam.enabled=false",
            "audio.enabled=false",
            "motor.enabled=true",
            f"motor.port={motor_pty}",
            "motor.bytesize=8",  # a pty refuses 7E1; the bytes are the same
            "motor.parity=N",
            "gps.enabled=true",
            f"gps.port={gps_pty}",
            "imu.enabled=true",
            "imu.rate_hz=100",
            "telemetry.rate_hz=5",
            f"map.file={folder / 'map.geojson'}",
            f"autonomy.route_file={folder / 'route.json'}",
        ],
    )
    twin = vehicle_for(config)
    chip, open_bus = mpu6050.emulate(config.imu, twin)
    emulation = [0.0]  # thread CPU seconds spent inside the emulated chip

    def timed_bus(number: int) -> Any:
        bus = open_bus(number)
        for name in ("read_byte_data", "write_byte_data", "read_i2c_block_data"):
            method = getattr(bus, name)

            def timed(*args: Any, _method: Any = method) -> Any:
                started = time.thread_time()
                try:
                    return _method(*args)
                finally:
                    emulation[0] += time.thread_time() - started

            setattr(bus, name, timed)
        return bus

    async def imu_only(ctx: PlatformContext) -> SimulatedDevices:
        return SimulatedDevices(vehicle=twin, mpu6050=chip, i2c_bus=timed_bus)

    real_start = app.start_simulators
    app.start_simulators = imu_only
    daemon = app.PlatformDaemon(config, None)
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    sink.setblocking(False)
    try:
        await daemon.start()
        bus = daemon.ctx.bus

        def steer_twin(state: MotionState) -> None:
            twin.set_command(state.command.linear, state.command.angular)

        bus.subscribe(topics.MOTION_STATE, steer_twin)
        posed = asyncio.Event()
        unsubscribe = bus.subscribe(topics.POSE, lambda _pose: posed.set())
        await asyncio.wait_for(posed.wait(), 15)
        unsubscribe()
        await daemon.ctx.rpc.call_local("load_map", map=demo_map(*START))
        await daemon.ctx.rpc.call_local("set_waypoints", waypoints=demo_route())
        aggregator = next(a for a in daemon.supervisor.actors if isinstance(a, TelemetryAggregator))
        aggregator.sender.start_stream("bench", None, sink.getsockname(), 5.0)
        await asyncio.sleep(2.0)
        idle, idle_emulation = await _cpu_percent(seconds, emulation)
        arming = daemon.ctx.arming
        assert arming is not None  # a start arms through the pre-arm checks (issue 27)
        await _until(lambda: not arming.reasons())
        await daemon.ctx.rpc.call_local("patrol_start")
        await asyncio.sleep(2.0)
        from platformd.autonomy.patrol import PatrolActor

        patrol = next(a for a in daemon.supervisor.actors if isinstance(a, PatrolActor))
        planner_pid = patrol.planner.pid
        devices_cpu = cpu_seconds(devices.pid)
        planner_cpu = cpu_seconds(planner_pid) if planner_pid is not None else 0.0
        patrolling, patrol_emulation = await _cpu_percent(seconds, emulation)
        devices_cpu = cpu_seconds(devices.pid) - devices_cpu
        if planner_pid is not None and planner_pid == patrol.planner.pid:
            planner_cpu = cpu_seconds(planner_pid) - planner_cpu
        report = bus.last(topics.PATROL_STATUS)
        state = report.state if report is not None else "?"
        lap = report.lap if report is not None else 0
        waypoint = report.waypoint if report is not None else None
    finally:
        app.start_simulators = real_start
        await daemon.stop()
        sink.close()
        devices.terminate()
        await devices.wait()
    return {
        "platform_cpu_patrolling_pct_of_core": round(patrolling - patrol_emulation, 2),
        "platform_cpu_not_patrolling_pct_of_core": round(idle - idle_emulation, 2),
        "platform_cpu_patrolling_with_imu_emulation_pct": round(patrolling, 2),
        "platform_cpu_imu_emulation_pct": round(patrol_emulation, 2),
        "sim_devices_process_cpu_pct": round(100.0 * devices_cpu / seconds, 2),
        "planner_process_cpu_patrolling_pct": round(100.0 * planner_cpu / seconds, 2),
        "platform_cpu_patrol_state": f"{state} (waypoint {waypoint}, lap {lap})",
        "platform_cpu_note": (
            "the platform's own share: AX3500 and GPS simulated in another process, the "
            "emulated MPU-6050's own CPU taken out; on a shared machine (pessimistic)"
        ),
    }


async def _cpu_percent(seconds: float, emulation: list[float]) -> tuple[float, float]:
    """The process's CPU over ``seconds`` and the emulated chip's share of it (% of a core)."""
    import asyncio

    cpu, wall, chip = time.process_time(), time.monotonic(), emulation[0]
    await asyncio.sleep(seconds)
    elapsed = time.monotonic() - wall
    return (
        100.0 * (time.process_time() - cpu) / elapsed,
        100.0 * (emulation[0] - chip) / elapsed,
    )
