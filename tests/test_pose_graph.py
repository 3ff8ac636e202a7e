"""The iSAM2 pose graph: a loop driven with a drifting odometry is closed when a scan matches
the place it started from, and the error at the return falls (GTSAM, small_gicp)."""

from __future__ import annotations

import math

from brasidas.perception.odometry import LidarOdometry, Pose2D, scan_points
from brasidas.perception.pose_graph import PoseGraph
from platformd.sim.drive import SimulatedDrive, loop_waypoints, street_grid

YAW_BIAS_PER_M = math.radians(0.05)
"""A drift the odometry's own tests do not have: a gyro-like bias, so the loop is visibly open."""


def test_a_loop_closure_pulls_the_drifted_return_back() -> None:
    drive = SimulatedDrive(street_grid(), loop_waypoints(), seed=3)
    odometry = LidarOdometry()
    start = Pose2D(0.0, 0.0, 0.0)
    graph = PoseGraph(start, (0.01, 0.01, 0.001))
    dead = start
    while drive.laps < 1 or drive.target < 1:
        step = drive.step()
        points = scan_points(step.scan, step.speed_command_mps, step.gyro_rad_s)
        result = odometry.update(points, step.time, step.speed_command_mps, step.gyro_rad_s)
        d = result.delta
        distance = math.hypot(d.x_m, d.y_m)
        delta = Pose2D(d.x_m, d.y_m, d.yaw_rad + YAW_BIAS_PER_M * distance)
        dead = dead.compose(delta)
        sigmas = (
            0.02 * distance + 0.002,
            0.02 * distance + 0.002,
            YAW_BIAS_PER_M * distance + 0.001,
        )
        graph.odometry(delta, sigmas, points)
        assert drive.now < 400
    truth = step.truth
    open_error = math.hypot(dead.x_m - truth.x_m, dead.y_m - truth.y_m)
    closed = graph.pose
    closed_error = math.hypot(closed.x_m - truth.x_m, closed.y_m - truth.y_m)
    assert graph.closures > 0
    assert open_error > 1.0, open_error
    assert closed_error < open_error / 3, (closed_error, open_error)
