"""The simulated vehicle: straight runs, turns and frames, on a fake clock."""

from __future__ import annotations

import math

import pytest

from platformd.sim.vehicle import VehicleModel


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_north_run_moves_north_at_top_speed() -> None:
    clock = FakeClock()
    vehicle = VehicleModel(heading_deg=0.0, max_speed_mps=2.0, clock=clock)
    vehicle.set_command(1.0, 0.0)
    clock.now += 10.0
    pose = vehicle.pose()
    assert pose.speed_mps == pytest.approx(2.0, abs=1e-3)
    assert pose.x_m == pytest.approx(0.0, abs=1e-6)
    # 10 s at 2 m/s less the lag of the first fraction of a second.
    assert 19.0 < pose.y_m < 20.0
    assert pose.latitude > vehicle.origin[0]
    assert pose.heading_deg == pytest.approx(0.0, abs=1e-6)


def test_positive_steering_turns_left() -> None:
    clock = FakeClock()
    vehicle = VehicleModel(heading_deg=90.0, max_yaw_rate_rad_s=1.0, clock=clock)  # facing east
    vehicle.set_command(0.0, 1.0)
    clock.now += 0.5
    assert vehicle.pose().yaw_rate_rad_s > 0  # counter-clockwise, as a z-up gyro reads it
    # A quarter turn at 1 rad/s takes pi/2 s plus the lag (the 0.25 s time constant).
    clock.now += math.pi / 2 + 0.25 - 0.5
    heading = vehicle.pose().heading_deg
    assert 0.0 <= heading < 20.0 or heading > 350.0  # now facing about north


def test_stop_decays_speed_and_reverse_course() -> None:
    clock = FakeClock()
    vehicle = VehicleModel(clock=clock)
    vehicle.set_command(-0.5, 0.0)
    clock.now += 3.0
    pose = vehicle.pose()
    assert pose.speed_mps < 0
    assert pose.course_deg == pytest.approx(180.0, abs=1e-6)
    vehicle.set_command(0.0, 0.0)
    clock.now += 3.0
    assert abs(vehicle.pose().speed_mps) < 1e-3
    assert vehicle.command == (0.0, 0.0)
