"""OBSTACLE_DISTANCE from the lidar's scans (issue 30): QGroundControl's proximity display.

Sans-IO: :func:`obstacle_distance` makes the message from a scan in the robot's frame (72
sectors of 5 degrees, clockwise from forward as MAV_FRAME_BODY_FRD has them, the nearest
obstacle return of each in centimetres; ``max_distance + 1`` where nothing is seen, as the
message defines). :class:`ObstacleDistanceSender` broadcasts the newest scan at ``rate_hz``
through the vehicle's links (the endpoint's tick calls it).
"""

from __future__ import annotations

from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas import topics
from brasidas.bus import Bus
from brasidas.perception.messages import RobotScan
from platformd.mavlink.vehicle import MavlinkVehicle

SECTORS = 72
SECTOR_DEG = 360 // SECTORS
MIN_DISTANCE_CM = 10


def obstacle_distance(scan: RobotScan, time_usec: int, max_range_m: float) -> Any:
    max_cm = min(65534, round(max_range_m * 100))
    distances = [max_cm + 1] * SECTORS
    for bearing, distance in zip(scan.bearings_deg, scan.ranges_m, strict=True):
        if distance <= 0:
            continue
        sector = int(((bearing + SECTOR_DEG / 2) % 360.0) // SECTOR_DEG) % SECTORS
        distances[sector] = min(distances[sector], max(MIN_DISTANCE_CM, round(distance * 100)))
    return mavlink.MAVLink_obstacle_distance_message(
        time_usec & 0xFFFFFFFFFFFFFFFF,
        mavlink.MAV_DISTANCE_SENSOR_LASER,
        distances,
        SECTOR_DEG,
        MIN_DISTANCE_CM,
        max_cm,
        float(SECTOR_DEG),
        0.0,
        mavlink.MAV_FRAME_BODY_FRD,
    )


class ObstacleDistanceSender:
    """The newest scan as OBSTACLE_DISTANCE, at most ``rate_hz``, to every link."""

    def __init__(
        self, bus: Bus, vehicle: MavlinkVehicle, max_range_m: float, rate_hz: float = 5.0
    ) -> None:
        self.bus = bus
        self.vehicle = vehicle
        self.max_range_m = max_range_m
        self.period = 1.0 / rate_hz
        self.sent = 0
        self._next = 0.0
        self._last: RobotScan | None = None

    def tick(self, now: float) -> None:
        scan = self.bus.last(topics.LIDAR_SCAN)
        if scan is None or scan is self._last or now < self._next:
            return
        self._last = scan
        self._next = now + self.period
        self.vehicle.broadcast(obstacle_distance(scan, int(now * 1e6), self.max_range_m))
        self.sent += 1
