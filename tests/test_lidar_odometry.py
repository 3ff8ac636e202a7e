"""Lidar odometry (small_gicp) on the simulator's real frames: tracking, and its guards."""

from __future__ import annotations

import math

import numpy as np
from shapely.geometry import box

from brasidas.perception.odometry import LidarOdometry, Pose2D, prior_motion, scan_points
from platformd.sim.drive import SimulatedDrive, street_grid
from platformd.sim.lidar import LidarWorld


def _run(drive: SimulatedDrive, odometry: LidarOdometry, scans: int) -> list[tuple[Pose2D, Pose2D]]:
    """(estimate, truth) after each scan, the truth relative to where the odometry began."""
    out = []
    start: Pose2D | None = None
    for _ in range(scans):
        step = drive.step()
        truth = Pose2D(step.truth.x_m, step.truth.y_m, step.truth.yaw_rad)
        start = start or truth
        result = odometry.update(
            scan_points(step.scan, step.speed_command_mps, step.gyro_rad_s),
            step.time,
            step.speed_command_mps,
            step.gyro_rad_s,
        )
        out.append((result.pose, start.between(truth)))
    return out


def test_odometry_tracks_a_drive_round_a_corner_within_a_few_decimetres() -> None:
    drive = SimulatedDrive(street_grid(), [(20.0, 0.0), (20.0, 20.0)], seed=3)
    odometry = LidarOdometry()
    poses = _run(drive, odometry, 320)  # 32 s: 20 m east, the turn, 10 m north
    estimate, truth = poses[-1]
    assert truth.y_m > 5.0  # it did turn the corner
    assert math.hypot(estimate.x_m - truth.x_m, estimate.y_m - truth.y_m) < 0.6
    assert abs(math.degrees(estimate.yaw_rad - truth.yaw_rad)) < 2.0
    assert odometry.fallbacks < 0.1 * odometry.scans  # the lidar, not the prior, did the work


def test_too_few_returns_fall_back_to_the_prior_and_say_so() -> None:
    odometry = LidarOdometry(min_points=60)
    few = np.array([[2.0, 0.0]] * 10)
    odometry.update(few, 0.0, 0.0, 0.0)
    step = odometry.update(few, 0.5, 1.0, 0.2)
    assert step.source == "prior"
    assert "10 returns" in step.reason
    expected = prior_motion(1.0, 0.2, 0.5)
    assert math.isclose(step.pose.x_m, expected.x_m)
    assert math.isclose(step.pose.y_m, expected.y_m)
    assert math.isclose(step.pose.yaw_rad, 0.1)


def test_a_corridor_is_degenerate_the_prior_stands_in_along_it() -> None:
    walls = [(box(-50.0, 2.0, 150.0, 2.5), 0.6), (box(-50.0, -2.5, 150.0, -2.0), 0.6)]
    drive = SimulatedDrive(LidarWorld(walls, []), [(100.0, 0.0)], seed=4)
    odometry = LidarOdometry()
    poses = _run(drive, odometry, 150)
    drive_step = odometry.update(scan_points(drive.step().scan), drive.now, 1.0, 0.0)
    assert drive_step.source == "lidar"
    assert "degenerate" in drive_step.reason
    assert "prior used along 0°" in drive_step.reason
    estimate, truth = poses[-1]
    # Across the corridor the walls hold it; along it, dead reckoning (the commanded speed).
    assert abs(estimate.y_m - truth.y_m) < 0.1
    assert truth.x_m > 10.0
