"""From a lidar revolution to obstacles and speed limits (pure computation, run in a thread).

The sensor's points are turned into the robot's frame (``lidar.mount_*``, ``lidar.yaw_deg``);
returns from the robot's own body (closer than ``lidar.body_radius_m`` to the sensor, or in a
``lidar.masked_sectors`` bearing) are dropped. Neighbouring returns (in scan order, under
``CLUSTER_GAP_M`` apart) make a cluster; a cluster of fewer than ``lidar.min_points`` is noise,
so a single stray return never stops the robot.

The robot may go forward at the speed that still stops ``lidar.clearance_m`` short of the
nearest obstacle in its corridor (``lidar.half_width_m`` either side of the way it goes),
after the dead time ``lidar.reaction_s`` and braking at ``safety.braking_mps2``: a robot
(autonomous or hand-driven) is slowed as it closes in and stopped at the clearance; one still
going faster than that (the drive lags its command) brakes at once (its motors commanded to
a crawl, :data:`STOP_BELOW` of top speed, until it is down to the limit), and the dead time
grows by how late limits have lately reached the motors (a starved CPU). The
corridor follows the arc the command drives, not only straight ahead: a post the robot turns
towards is in its way before it is ahead (limits for :data:`TURN_RATIOS`, the motion arbiter
takes the one of its command). Reversing likewise, straight, for what is behind. Turning on
the spot is never limited (a skid-steer robot turns inside its footprint).

Passing an obstacle beside the body (within :data:`SIDE_MARGIN_M` of its side, anywhere along
its length) caps the speed, forward and in turns, from :data:`SIDE_SPEED_MPS` at the body's side
up to full at the margin, as ArduPilot's proximity avoidance slows a vehicle closing in:
a post passed with centimetres to spare is passed slowly, never stopped for.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from brasidas.codecs.ldlidar import LidarScan
from brasidas.config.lidar import LidarSection, parse_sector
from brasidas.perception.messages import Obstacle, Proximity, RobotScan

CLUSTER_GAP_M = 0.3
"""Neighbouring returns closer than this belong to one object."""
BLIND_MARGIN_M = 0.1
"""An obstacle last seen within the body radius plus this, then not at all, holds the stop."""
STOP_BELOW = 0.02
"""A limit under this fraction of top speed is a stop (the motors would not turn anyway)."""
TURN_RATIOS = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
"""Angular over linear command (fractions of full scale) of the arcs limits are made for,
each way; a command between two takes the lower of their limits."""
SIDE_MARGIN_M = 0.3
"""An obstacle this near the body's side slows the robot (:func:`side_limit`)."""
SIDE_SPEED_MPS = 0.5
"""The speed passing an obstacle at the body's side (it rises to full at the margin)."""
MAX_ARC_RAD = math.pi
"""How far round an arc the corridor goes (further, the robot has turned back)."""


@dataclass(frozen=True)
class Geometry:
    """What the analysis needs of the configuration."""

    lidar: LidarSection
    braking_mps2: float
    max_speed_mps: float
    full_turn_rps: float = math.radians(86.0)
    """The turn rate at angular = 1 (``autonomy.full_turn_rate_dps``)."""

    @property
    def sectors(self) -> list[tuple[float, float]]:
        return [parse_sector(s) for s in self.lidar.masked_sectors]


def stopping_speed(free_m: float, dead_s: float, braking_mps2: float) -> float:
    """The speed (m/s) that stops within ``free_m`` after ``dead_s`` then braking."""
    if free_m <= 0:
        return 0.0
    return braking_mps2 * (-dead_s + math.sqrt(dead_s * dead_s + 2 * free_m / braking_mps2))


def to_robot(scan: LidarScan, geometry: Geometry) -> RobotScan:
    """The scan in the robot's frame with the body, masks and noise dropped, and its clusters."""
    lidar = geometry.lidar
    angles = np.asarray(scan.angles_deg, dtype=float)
    ranges = np.asarray(scan.ranges_m, dtype=float)
    # Sensor angles grow clockwise from its zero, which is yaw_deg counter-clockwise of forward.
    sensor_bearing = np.radians(angles - lidar.yaw_deg)
    x = lidar.mount_x_m + ranges * np.cos(sensor_bearing)
    y = lidar.mount_y_m - ranges * np.sin(sensor_bearing)
    keep = ranges > max(lidar.body_radius_m, 1e-3)
    bearings = np.degrees(np.arctan2(-y, x)) % 360.0
    for start, end in geometry.sectors:
        lo, hi = start % 360.0, end % 360.0
        inside = (
            (bearings >= lo) & (bearings <= hi) if lo <= hi else (bearings >= lo) | (bearings <= hi)
        )
        keep &= ~inside
    obstacles: list[Obstacle] = []
    clustered = np.zeros(len(ranges), dtype=bool)
    index = np.flatnonzero(keep)
    if len(index):
        px, py = x[index], y[index]
        gaps = np.hypot(np.diff(px), np.diff(py))
        breaks = np.flatnonzero(gaps > CLUSTER_GAP_M) + 1
        groups = np.split(np.arange(len(index)), breaks)
        # The scan is a circle: the last group may continue the first.
        if len(groups) > 1 and math.hypot(px[-1] - px[0], py[-1] - py[0]) <= CLUSTER_GAP_M:
            groups[0] = np.concatenate((groups[-1], groups[0]))
            groups.pop()
        for group in groups:
            if len(group) < lidar.min_points:
                continue
            clustered[index[group]] = True
            gx, gy = px[group], py[group]
            cx, cy = float(gx.mean()), float(gy.mean())
            radius = float(np.hypot(gx - cx, gy - cy).max())
            obstacles.append(Obstacle(round(cx, 3), round(cy, 3), round(radius, 3), len(group)))
    robot_ranges = np.where(clustered, np.hypot(x, y), 0.0)
    return RobotScan(
        time=scan.ended,
        bearings_deg=tuple(np.round(bearings, 2).tolist()),
        ranges_m=tuple(np.round(robot_ranges, 3).tolist()),
        points_used=int(clustered.sum()),
        obstacles=tuple(obstacles),
    )


def proximity(
    scan: RobotScan,
    geometry: Geometry,
    previous: Proximity | None = None,
    extra_dead_s: float = 0.0,
    speed_mps: float = 0.0,
) -> Proximity:
    """The speed limits for the obstacles of ``scan`` (only clustered returns count).

    An obstacle the robot stopped for that is no longer seen at all (it went into the
    sensor's blind zone, or the returns dropped out) still holds the stop: ``previous``.
    ``extra_dead_s``: measured lateness of the limits beyond ``lidar.reaction_s``
    (:mod:`brasidas.perception.latency`), added to the dead time. ``speed_mps``: the speed the
    drive has reached (forward positive; it lags the command): going faster than an obstacle
    allows brakes (a crawl commanded), not only caps the speed."""
    lidar = geometry.lidar
    dead_s = lidar.reaction_s + extra_dead_s
    ranges = np.asarray(scan.ranges_m, dtype=float)
    bearings = np.radians(np.asarray(scan.bearings_deg, dtype=float))
    used = ranges > 0
    x = ranges * np.cos(bearings)
    y = -ranges * np.sin(bearings)
    corridor = used & (np.abs(y) <= lidar.half_width_m)
    # Free distance from the sensor's edge of the robot (its front; the rear taken as far back).
    front = corridor & (x > 0)
    rear = corridor & (x < 0)
    forward_free = float(x[front].min()) - abs(lidar.mount_x_m) if front.any() else None
    reverse_free = float(-x[rear].max()) - abs(lidar.mount_x_m) if rear.any() else None
    nearest = nearest_bearing = None
    if used.any():
        i = int(np.argmin(np.where(used, ranges, np.inf)))
        nearest = round(float(ranges[i]), 3)
        nearest_bearing = round(math.degrees(float(bearings[i])) % 360.0, 1)
    sensor_nearest = (
        float(np.hypot(x[used] - lidar.mount_x_m, y[used] - lidar.mount_y_m).min())
        if used.any()
        else None
    )
    # Vanished this close to the sensor: into its blind zone, not away (it would be seen
    # going). Not something beside the robot that the corridor left (a turn on the spot).
    held = lidar.body_radius_m + BLIND_MARGIN_M
    forward_blind = reverse_blind = False
    if previous is not None:
        vanished = _closer(previous.sensor_nearest_m, held) and not _closer(sensor_nearest, held)
        forward_blind = vanished and forward_free is None and _closer(previous.forward_free_m, held)
        reverse_blind = vanished and reverse_free is None and _closer(previous.reverse_free_m, held)
        if forward_blind:
            forward_free = previous.forward_free_m
        if reverse_blind:
            reverse_free = previous.reverse_free_m
        if forward_blind or reverse_blind:  # held until something is seen there again
            sensor_nearest = previous.sensor_nearest_m
    forward, forward_why = _limit(forward_free, "ahead", geometry, dead_s, speed_mps)
    side, side_why = side_limit(x[used], y[used], geometry)
    if side < forward:
        forward, forward_why = side, side_why
    reverse, reverse_why = _limit(reverse_free, "behind", geometry, dead_s, -speed_mps)
    reason = forward_why or reverse_why
    turns: list[tuple[float, float, str]] = []
    # An arc's stop stands likewise only while that hold does (the blind zone lies in the
    # corridors ahead and behind), not for an obstacle that left the arc's corridor as the
    # robot drove on: a tight arc's corridor is a small circle beside the robot, which a post
    # passed close by leaves and nothing else enters; its stop would stand for good.
    blind = forward_blind or reverse_blind
    held_turns = {ratio: (limit, why) for ratio, limit, why in previous.turns} if previous else {}
    for ratio in (*TURN_RATIOS, *(-r for r in TURN_RATIOS)):
        free = _arc_free(x[used], y[used], ratio, geometry)
        if free is None and blind and ratio in held_turns and held_turns[ratio][0] == 0.0:
            turns.append((ratio, *held_turns[ratio]))  # into the blind zone: the stop stands
            continue
        way = "left" if ratio > 0 else "right"
        limit = _limit(free, f"in the turn {way}", geometry, dead_s, speed_mps)
        turns.append((ratio, *(limit if limit[0] <= side else (side, side_why))))
    return Proximity(
        time=scan.time,
        forward_limit=forward,
        reverse_limit=reverse,
        forward_free_m=None if forward_free is None else round(forward_free, 3),
        reverse_free_m=None if reverse_free is None else round(reverse_free, 3),
        nearest_m=nearest,
        nearest_bearing_deg=nearest_bearing,
        reason=reason,
        turns=tuple(turns),
        sensor_nearest_m=None if sensor_nearest is None else round(sensor_nearest, 3),
    )


def side_limit(x: np.ndarray, y: np.ndarray, geometry: Geometry) -> tuple[float, str]:
    """The forward cap (fraction of top speed) and its reason for returns beside the body
    (robot frame, metres): along its length, outside its half-width by under the margin."""
    lidar = geometry.lidar
    length = max(abs(lidar.mount_x_m), lidar.half_width_m)  # the body's half-length, about
    gap = np.abs(y) - lidar.half_width_m
    beside = (np.abs(x) <= length) & (gap > 0) & (gap < SIDE_MARGIN_M)
    if not beside.any():
        return 1.0, ""
    nearest = float(gap[beside].min())
    slow = min(SIDE_SPEED_MPS, geometry.max_speed_mps)
    speed = slow + (geometry.max_speed_mps - slow) * nearest / SIDE_MARGIN_M
    fraction = min(1.0, speed / geometry.max_speed_mps)
    if fraction >= 1.0:
        return 1.0, ""
    return fraction, f"slowed to {speed:.1f} m/s: obstacle {nearest:.2f} m beside"


def _closer(free_m: float | None, than_m: float) -> bool:
    return free_m is not None and free_m < than_m


def _arc_free(x: np.ndarray, y: np.ndarray, ratio: float, geometry: Geometry) -> float | None:
    """Free distance along the arc of a command turning ``ratio`` (angular over linear, full
    scale fractions) within the corridor either side of it; None when nothing is in it."""
    lidar = geometry.lidar
    radius = geometry.max_speed_mps / (abs(ratio) * geometry.full_turn_rps)
    side = y if ratio > 0 else -y  # a right turn is the left one mirrored
    # Around the turn's centre (0, radius): the angle swept from the robot to each point.
    swept = np.arctan2(x, radius - side) % (2 * math.pi)
    inside = (np.abs(np.hypot(x, side - radius) - radius) <= lidar.half_width_m) & (
        swept <= MAX_ARC_RAD
    )
    if not inside.any():
        return None
    return float((radius * swept[inside]).min()) - abs(lidar.mount_x_m)


def _limit(
    free_m: float | None, where: str, geometry: Geometry, dead_s: float, moving_mps: float
) -> tuple[float, str]:
    if free_m is None:
        return 1.0, ""
    speed = stopping_speed(free_m - geometry.lidar.clearance_m, dead_s, geometry.braking_mps2)
    fraction = min(1.0, speed / geometry.max_speed_mps)
    if fraction < STOP_BELOW:
        return 0.0, f"stopped: obstacle {free_m:.1f} m {where}"
    if moving_mps > speed:  # the drive lags: brake hard, not only cap (not a stop: it crawls)
        return STOP_BELOW, f"braking: obstacle {free_m:.1f} m {where}"
    if fraction < 1.0:
        return fraction, f"slowed to {speed:.1f} m/s: obstacle {free_m:.1f} m {where}"
    return 1.0, ""


def silent(now: float, seconds: float) -> Proximity:
    """The limits while the lidar sends nothing: stopped (it cannot see), turning allowed."""
    return Proximity(
        now, 0.0, 0.0, None, None, None, None, f"stopped: no lidar scan for {seconds:g} s"
    )
