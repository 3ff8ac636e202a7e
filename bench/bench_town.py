"""The town with things the map does not have (issue 30): ``make bench town``.

A --sim platform with the lidar on patrols the demo loop (140 m round the shed, at the
platform's default 6 km/h: the speed the lidar's stop is designed for; at 18 km/h a post
turned towards late is hit at 2 m/s) among 25 unmapped obstacles (posts 0.2-0.5 m, seeded, some on the loop, at least
2.5 m apart so a way round exists) and 5 pedestrians walking back and forth, with the ambient
light of a bright day (``sim.lux`` 60,000). Against the simulator's truth, sampled every
50 ms:

- **collisions**: contacts, the vehicle's centre coming nearer an obstacle's edge than the
  body's half-width (:data:`BODY_RADIUS_M`), each counted once; pedestrians counted apart,
  each contact once and split by whose doing it was: the robot's when it was moving towards
  the person (its velocity closing the gap at over :data:`MOVING_MPS`), else the person's
  (one walking into a standing or receding robot);
- **laps completed**: laps finished within :data:`LAP_TIMEOUT_S` each, of those attempted;
  a lap that times out is counted stuck, with the patrol's state and reason; laps in which
  the patrol skipped a waypoint (an obstacle's keep-out over it, or no path to it) are
  counted apart: completed, but not clean;
- **false stops per km**: the lidar's forward limit for the patrol's ask (along its arc)
  dropping to zero while nothing real (a post, a pedestrian, a wall of the map) is within
  :data:`FALSE_STOP_M` of the vehicle (stops for a silent lidar, the simulator or the
  reader stalled on a loaded machine, are counted apart);
- the minimum clearance to an obstacle's edge, the distance driven.

``--laps N`` (``BENCH_LAPS``, or ``BENCH_TOWN_LAPS``; default 50) laps; ``BENCH_TOWN_SEED``;
``BENCH_TOWN_KMH`` the patrol's speed (default the platform's); ``BENCH_TOWN_STALL_S`` stalls
the localization's worker that long every few seconds (a starved CPU, without loading a shared
machine); ``BENCH_TOWN_MINUTES`` a time budget (the laps finished by then are reported);
``BENCH_TOWN_TRACE`` a file for the truth, the estimate and the patrol's state
(JSON lines, twice a second). Real time: a lap takes about 60 s at 18 km/h and 100 s at
6 km/h, so the full 50 laps take about an hour and a half at 6 km/h.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import random
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from brasidas import topics
from brasidas.config import PlatformConfig, load_config
from brasidas.messages import PatrolState, Velocity
from brasidas.perception.limits import limit_for
from platformd.sim.demo_area import LOOP, offset

LAPS = int(os.environ.get("BENCH_LAPS") or os.environ.get("BENCH_TOWN_LAPS") or "50")
KMH = os.environ.get("BENCH_TOWN_KMH", "")
SEED = int(os.environ.get("BENCH_TOWN_SEED", "1"))
TRACE = os.environ.get("BENCH_TOWN_TRACE", "")
"""A file to write the truth, the estimate and the patrol's state to twice a second."""
STALL_S = float(os.environ.get("BENCH_TOWN_STALL_S", "0"))
"""A starved CPU without loading the shared machine: the localization's worker stalls this
long every :data:`STALL_EVERY_S` (0: never)."""
STALL_EVERY_S = 7.0
MINUTES = float(os.environ.get("BENCH_TOWN_MINUTES", "0"))
"""Stop after this long (0: when the laps are done), reporting the laps finished by then."""
OBSTACLES = 25
PEDESTRIANS = 5
LUX = 60_000.0
BODY_RADIUS_M = 0.3
"""Half the rover's width (an assumption: the simulated vehicle has no footprint)."""
FALSE_STOP_M = 1.5
MOVING_MPS = 0.1
"""The robot closing on a person faster than this is moving into them."""
LAP_TIMEOUT_S = 240.0
START = (37.9415, 23.6530)
SHED = (15.0, 10.0, 25.0, 20.0)


def obstacles(seed: int = SEED) -> list[tuple[float, float, float]]:
    """25 posts (east, north, radius) in the demo field, clear of the start and the shed,
    2.5 m apart; one in three on the loop itself."""
    rng = random.Random(seed)
    corners = list(LOOP.values())
    posts: list[tuple[float, float, float]] = []
    while len(posts) < OBSTACLES:
        if len(posts) % 3 == 0:  # on a side of the loop
            (x0, y0), (x1, y1) = rng.choice(
                list(zip(corners, corners[1:] + corners[:1], strict=True))
            )
            t = rng.uniform(0.15, 0.85)
            x, y = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
        else:
            x, y = rng.uniform(-8.0, 48.0), rng.uniform(-8.0, 38.0)
        radius = rng.uniform(0.2, 0.5)
        if math.hypot(x, y) < 4.0:
            continue
        if SHED[0] - 2 < x < SHED[2] + 2 and SHED[1] - 2 < y < SHED[3] + 2:
            continue
        if any(math.hypot(x - px, y - py) < 2.5 + radius + pr for px, py, pr in posts):
            continue
        posts.append((x, y, radius))
    return posts


def _obstacles_file(folder: Path, posts: list[tuple[float, float, float]]) -> Path:
    features = []
    for east, north, radius in posts:
        lat, lon = offset(*START, east, north)
        features.append(
            {
                "type": "Feature",
                "properties": {"radius_m": radius},
                "geometry": {"type": "Point", "coordinates": [lon, lat]},
            }
        )
    path = folder / "obstacles.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": features}))
    return path


def _segment_distance(x: float, y: float, segments: np.ndarray) -> float:
    if not len(segments):
        return math.inf
    x0, y0, x1, y1 = segments[:, 0], segments[:, 1], segments[:, 2], segments[:, 3]
    dx, dy = x1 - x0, y1 - y0
    length2 = np.maximum(dx * dx + dy * dy, 1e-12)
    t = np.clip(((x - x0) * dx + (y - y0) * dy) / length2, 0.0, 1.0)
    return float(np.min(np.hypot(x0 + t * dx - x, y0 + t * dy - y)))


def _contact(pose: Any, x: float, y: float, post: np.ndarray, ctx: Any) -> str:
    """What a contact looked like: the post's bearing from the vehicle's heading, its speed,
    the lidar's limits and why, the patrol's state (for finding the cause)."""
    bearing = math.degrees(math.atan2(post[1] - y, post[0] - x) - pose.yaw_rad)
    bearing = (bearing + 180.0) % 360.0 - 180.0
    proximity = ctx.bus.last(topics.PROXIMITY)
    status = ctx.bus.last(topics.PATROL_STATUS)
    limits = (
        f"limits {proximity.forward_limit:.2f}/{proximity.reverse_limit:.2f} "
        f"'{proximity.reason}' nearest {proximity.nearest_m}"
        if proximity is not None
        else "no lidar limits"
    )
    return (
        f"post r={post[2]:.2f} at {bearing:+.0f}° (counter-clockwise from ahead), "
        f"speed {pose.speed_mps:+.2f} m/s; {limits}; "
        f"patrol {status.state.value if status else '?'}"
    )


def _append(path: Path, text: str) -> None:
    with path.open("a") as file:
        file.write(text)


def _trace_line(ctx: Any, simulator: Any, pose: Any, x: float, y: float, proximity: Any) -> str:
    """Truth and estimate in the simulator's frame, the patrol's state (for finding causes)."""
    estimate = ctx.bus.last(topics.POSE)
    status = ctx.bus.last(topics.PATROL_STATUS)
    fields: dict[str, Any] = {
        "t": round(time.monotonic(), 2),
        "true": [round(x, 2), round(y, 2), round(math.degrees(pose.yaw_rad), 1)],
        "speed": round(pose.speed_mps, 2),
    }
    if estimate is not None and simulator.origin is not None:
        ex, ey = simulator.origin.to_local(estimate.latitude, estimate.longitude)
        fields["est"] = [round(ex, 2), round(ey, 2), round(math.degrees(estimate.yaw_rad), 1)]
        fields["err"] = round(math.hypot(ex - x, ey - y), 2)
        fields["sigma"] = round(estimate.sigma_xy_m, 2)
        fields["source"] = estimate.source
        fields["heading_known"] = estimate.heading_known
    if _LOCALIZERS:
        fields["gps_refusal"] = _LOCALIZERS[0].gps_refusal
    if status is not None:
        fields["patrol"] = [status.state.value, status.reason, status.waypoint, status.lap]
    if proximity is not None:
        fields["limits"] = [proximity.forward_limit, proximity.reverse_limit, proximity.reason]
    return json.dumps(fields)


_LOCALIZERS: list[Any] = []
"""The localizer (seen by :func:`_stall_localization`), for the trace."""


def _stall_localization() -> None:
    """Make the localization's worker thread stall now and then (a loaded machine)."""
    from platformd.lidar_localization import Localizer

    process = Localizer.process
    due = [time.monotonic() + STALL_EVERY_S]

    def stalling(self: Localizer, *args: Any, **kwargs: Any) -> Any:
        _LOCALIZERS[:] = [self]
        if time.monotonic() >= due[0]:
            due[0] = time.monotonic() + STALL_EVERY_S * random.uniform(0.5, 1.5)
            time.sleep(STALL_S)
        return process(self, *args, **kwargs)

    Localizer.process = stalling  # type: ignore[method-assign]


class _Skips(logging.Handler):
    """Counts the patrol's "waypoint … skipped" warnings."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.count = 0
        self.last: list[str] = []
        """The latest few (why)."""

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        if "skipped" in message:
            self.count += 1
            self.last = [*self.last[-4:], message]


async def run() -> dict[str, Any]:
    from platformd.app import PlatformDaemon

    folder = Path(tempfile.mkdtemp(prefix="bench-town-lidar-"))
    posts = obstacles()
    config = load_config(
        PlatformConfig,
        None,
        [
            "signaling.port=0", "velocity.port=0", "beacon.enabled=false",
            "navcam.enabled=false", "audio.enabled=false", "sim.enabled=true",
            "motor.enabled=true", "gps.enabled=true", "imu.enabled=true", "gps.sim_rate_hz=10",
            "autonomy.clearance_m=2", "sim.gps_receiver=rtk", "autonomy.gps_sigma_m=0.02",
            "autonomy.gps_jitter_m=0.02", "lidar.enabled=true",
            f"lidar.grid_file={folder / 'grid.npz'}",
            f"sim.obstacles_file={_obstacles_file(folder, posts)}",
            f"sim.pedestrians={PEDESTRIANS}", f"sim.lux={LUX}", f"sim.seed={SEED}",
            f"map.file={folder / 'map.geojson'}", f"autonomy.route_file={folder / 'route.json'}",
            *([f"platform.max_speed_kmh={KMH}", f"autonomy.cruise_speed_kmh={KMH}"] if KMH else []),
        ],
    )  # fmt: skip
    if STALL_S > 0:
        _stall_localization()
    skips = _Skips()
    logging.getLogger("platformd.autonomy.patrol").addHandler(skips)
    daemon = PlatformDaemon(config, None)
    await daemon.start()
    clean_laps = 0
    skips_at_lap_start = 0
    load_start = os.getloadavg()
    collisions = false_stops = stops = blind_stops = 0
    robot_into_person = person_into_robot = 0
    was_near_person = False
    min_clearance = math.inf
    driven = 0.0
    laps_done = 0
    stuck: list[str] = []
    contacts: list[str] = []
    false_stop_notes: list[str] = []
    lap_times: list[float] = []
    try:
        ctx = daemon.ctx
        simulator, vehicle = ctx.sim.lidar, ctx.sim.vehicle
        assert simulator is not None and vehicle is not None
        arming = ctx.arming
        assert arming is not None
        for _ in range(300):  # the pre-arm checks pass (a fix, the controller) within 60 s
            if not arming.reasons():
                break
            await asyncio.sleep(0.2)
        asked = (0.0, 0.0)

        def on_cmd_vel(velocity: Velocity) -> None:
            nonlocal asked
            asked = (velocity.linear, velocity.angular)

        ctx.bus.subscribe(topics.CMD_VEL, on_cmd_vel)
        await ctx.rpc.call_local("set_waypoints", waypoints=["sw", "se", "ne", "nw", "sw"])
        await ctx.rpc.call_local("patrol_start")
        posts_xy = np.array([(x, y, r) for x, y, r in posts])
        previous: tuple[float, float] | None = None
        was_stopped = was_touching = False
        lap_started = time.monotonic()
        last_lap = 0
        trace: list[str] = []
        last_trace = 0.0
        give_up = time.monotonic() + MINUTES * 60 if MINUTES > 0 else math.inf
        while laps_done + len(stuck) < LAPS and time.monotonic() < give_up:
            await asyncio.sleep(0.05)
            pose = vehicle.pose()
            world = simulator.generator.world
            x, y = simulator._position(pose)  # the simulator's own frame
            if previous is not None:
                driven += math.hypot(x - previous[0], y - previous[1])
            previous = (x, y)
            edges = np.hypot(posts_xy[:, 0] - x, posts_xy[:, 1] - y) - posts_xy[:, 2]
            nearest_post = float(edges.min())
            min_clearance = min(min_clearance, nearest_post)
            touching = nearest_post < BODY_RADIUS_M
            if touching and not was_touching:  # each contact once, not each sample
                collisions += 1
                if len(contacts) < 5:
                    contacts.append(_contact(pose, x, y, posts_xy[int(edges.argmin())], ctx))
            was_touching = touching
            people = world.pedestrians_at(time.monotonic())
            gaps = np.hypot(people[:, 0] - x, people[:, 1] - y) - people[:, 2]
            nearest_person = float(gaps.min()) if len(people) else math.inf
            near_person = nearest_person < BODY_RADIUS_M
            if near_person and not was_near_person:  # each contact once
                person = people[int(gaps.argmin())]
                towards = math.atan2(person[1] - y, person[0] - x)
                closing = pose.speed_mps * math.cos(towards - pose.yaw_rad)
                if closing > MOVING_MPS:
                    robot_into_person += 1
                    if len(contacts) < 5:
                        contacts.append(
                            f"person at {math.degrees(towards - pose.yaw_rad):+.0f}°, robot "
                            f"closing at {closing:.2f} m/s: "
                            + _contact(pose, x, y, np.array([*person[:2], person[2]]), ctx)
                        )
                else:
                    person_into_robot += 1
            was_near_person = near_person
            proximity = ctx.bus.last(topics.PROXIMITY)
            if TRACE and time.monotonic() - last_trace > 0.5:
                last_trace = time.monotonic()
                trace.append(_trace_line(ctx, simulator, pose, x, y, proximity) + "\n")
                if len(trace) >= 20:
                    await asyncio.to_thread(_append, Path(TRACE), "".join(trace))
                    trace.clear()
            # The limit the arbiter applies to the patrol's ask (along its arc, if it turns).
            stopped = proximity is not None and limit_for(proximity, *asked)[0] == 0.0
            status = ctx.bus.last(topics.PATROL_STATUS)
            patrolling = status is not None and status.state == PatrolState.PATROLLING
            if stopped and not was_stopped and patrolling:
                stops += 1
                wall = _segment_distance(x, y, world.segments[:, :4])
                blind = proximity is not None and "no lidar scan" in proximity.reason
                if blind:  # the simulator or the reader stalled (a loaded machine): apart
                    blind_stops += 1
                elif min(nearest_post, nearest_person, wall) > FALSE_STOP_M:
                    false_stops += 1
                    if len(false_stop_notes) < 5 and proximity is not None:
                        why = limit_for(proximity, *asked)[1]
                        false_stop_notes.append(
                            f"'{why}' asked {asked[0]:+.2f}/{asked[1]:+.2f}; nearest post "
                            f"{nearest_post:.1f} m, person {nearest_person:.1f} m, "
                            f"wall {wall:.1f} m; speed {pose.speed_mps:+.2f} m/s"
                        )
            was_stopped = stopped
            lap = status.lap if status is not None else 0
            now = time.monotonic()
            if lap > last_lap:
                laps_done += lap - last_lap
                clean_laps += skips.count == skips_at_lap_start
                skips_at_lap_start = skips.count
                last_lap = lap
                lap_times.append(now - lap_started)
                lap_started = now
            elif now - lap_started > LAP_TIMEOUT_S:
                reason = f"{status.state.value}: {status.reason}" if status else "no status"
                stuck.append(reason)
                lap_started = now
                skips_at_lap_start = skips.count
    finally:
        await daemon.stop()
        logging.getLogger("platformd.autonomy.patrol").removeHandler(skips)
    attempted = laps_done + len(stuck)
    km = driven / 1000
    load_end = os.getloadavg()
    return {
        "town_lidar_laps_attempted": attempted,
        "town_lidar_laps_completed_pct": round(100 * laps_done / max(1, attempted), 1),
        "town_lidar_laps_clean": clean_laps,
        "town_lidar_waypoints_skipped": skips.count,
        "town_lidar_last_skips": skips.last,
        "town_lidar_collisions": int(collisions),
        "town_lidar_pedestrian_contacts_robot_moving_into": robot_into_person,
        "town_lidar_pedestrian_contacts_walked_into_robot": person_into_robot,
        "town_lidar_min_clearance_to_post_edge_m": round(min_clearance, 2),
        "town_lidar_stops": stops,
        "town_lidar_false_stops": false_stops,
        "town_lidar_blind_stops": blind_stops,
        "town_lidar_false_stops_per_km": round(false_stops / km, 2) if km > 0 else None,
        "town_lidar_driven_km": round(km, 3),
        "town_lidar_lap_s_median": round(float(np.median(lap_times)), 1) if lap_times else None,
        "town_lidar_stuck": stuck[:5],
        "town_lidar_contacts": contacts,
        "town_lidar_false_stop_notes": false_stop_notes,
        "town_lidar_obstacles": OBSTACLES,
        "town_lidar_pedestrians": PEDESTRIANS,
        "town_lidar_lux": LUX,
        "town_lidar_loadavg": f"{load_start[0]:.1f} -> {load_end[0]:.1f}",
    }
