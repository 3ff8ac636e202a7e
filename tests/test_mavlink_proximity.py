"""OBSTACLE_DISTANCE from a lidar scan, decoded by pymavlink as a ground station would."""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.perception.messages import RobotScan
from platformd.mavlink.proximity import obstacle_distance


def test_sectors_hold_the_nearest_return_clockwise_from_forward() -> None:
    bearings = tuple(float(b) for b in range(360))
    ranges = [0.0] * 360
    ranges[1] = 0.62  # ahead
    ranges[359] = 0.8  # ahead too, a little left: same sector, the nearer one wins
    ranges[90] = 3.0  # right (clockwise)
    scan = RobotScan(1.0, bearings, tuple(ranges), 3, ())
    message = obstacle_distance(scan, 5_000_000, 12.0)
    wire = message.pack(mavlink.MAVLink(None, srcSystem=1, srcComponent=1))
    (decoded,) = [mavlink.MAVLink(None).parse_char(wire)]
    assert decoded.get_type() == "OBSTACLE_DISTANCE"
    assert decoded.frame == mavlink.MAV_FRAME_BODY_FRD
    assert decoded.increment == 5
    assert decoded.max_distance == 1200
    assert decoded.distances[0] == 62
    assert decoded.distances[18] == 300  # 90 degrees clockwise
    assert decoded.distances[36] == 1201  # nothing behind: max_distance + 1
    assert decoded.time_usec == 5_000_000
