"""The GPS gate and fusion: jumps and drags rejected and never followed, honest GPS kept."""

from __future__ import annotations

import datetime as dt
import math
import random
from collections.abc import Callable

from brasidas.perception.fusion import PoseFusion
from brasidas.perception.odometry import Pose2D
from platformd.sim.gps import NmeaGenerator
from platformd.sim.vehicle import VehicleModel

EPOCH = dt.datetime(2026, 1, 1, tzinfo=dt.UTC)
Spoof = Callable[[float], tuple[float, float]]


class Drive:
    """A rover circling at 1 m/s; odometry with 1 % noise at 10 Hz, NEO-6M fixes at 1 Hz."""

    def __init__(self, seed: int = 1) -> None:
        self.now = 0.0
        self.vehicle = VehicleModel(heading_deg=90.0, clock=lambda: self.now)
        self.vehicle.set_command(0.6, 0.03)
        self.gps = NmeaGenerator(random.Random(seed))
        self.rng = random.Random(seed + 1)
        self.fusion = PoseFusion()
        self.fusion.heading_rad = 0.0
        self.verdicts: list[tuple[float, bool, str]] = []
        self.last = self._truth()

    def _truth(self) -> Pose2D:
        pose = self.vehicle.pose()
        return Pose2D(pose.x_m, pose.y_m, pose.yaw_rad)

    def run(self, seconds: float, spoof: Spoof = lambda t: (0.0, 0.0), gps: bool = True) -> None:
        for _ in range(round(seconds * 10)):
            self.now = round(self.now + 0.1, 6)
            truth = self._truth()
            delta = self.last.between(truth)
            self.last = truth
            noisy = Pose2D(
                delta.x_m * (1 + self.rng.gauss(0, 0.01)),
                delta.y_m + self.rng.gauss(0, 0.002),
                delta.yaw_rad + self.rng.gauss(0, 0.001),
            )
            self.fusion.predict(noisy, "lidar", self.now)
            if gps and abs(self.now - round(self.now)) < 1e-6:
                self.gps.epoch(self.vehicle.pose(), EPOCH + dt.timedelta(seconds=self.now))
                east, north = self.gps.error
                sx, sy = spoof(self.now)
                verdict = self.fusion.gps(truth.x_m + east + sx, truth.y_m + north + sy, self.now)
                self.verdicts.append((self.now, verdict.accepted, verdict.reason))

    def error_m(self) -> float:
        pose, truth = self.fusion.pose(), self._truth()
        return math.hypot(pose.x_m - truth.x_m, pose.y_m - truth.y_m)

    def rejected(self) -> list[tuple[float, bool, str]]:
        return [v for v in self.verdicts if not v[1]]


def test_honest_neo6m_fixes_are_all_accepted_for_ten_minutes() -> None:
    for seed in (1, 2, 3):
        drive = Drive(seed)
        drive.run(600)
        assert drive.rejected() == []
        assert drive.fusion.pose().source == "gps+lidar"
        assert drive.error_m() < 6.0  # the NEO-6M's own wandering error, nothing worse


def test_a_30_m_jump_is_rejected_at_the_first_bad_fix_and_never_followed() -> None:
    drive = Drive()
    drive.run(120)
    before = drive.error_m()
    start = drive.now
    drive.run(30, spoof=lambda t: (30.0, 0.0))
    bad = [v for v in drive.verdicts if v[0] > start]
    assert all(not accepted for _, accepted, _ in bad)  # the first bad fix and every one after
    assert bad[0][2].startswith("jump: ")
    assert drive.error_m() < before + 1.5
    # The spoofing stops: the honest fixes are taken again after a few that agree.
    drive.run(20)
    assert drive.verdicts[-1][1] is True
    assert drive.fusion.suspect == ""


def test_a_half_metre_per_second_drag_is_caught_within_20_s_and_not_followed() -> None:
    drive = Drive()
    drive.run(120)
    start = drive.now
    drive.run(60, spoof=lambda t: (0.5 * (t - start), 0.0))
    rejected = [v for v in drive.rejected() if v[0] > start]
    assert rejected, "the drag was never noticed"
    assert rejected[0][0] - start <= 20.0
    assert rejected[0][2].startswith("drag: ")
    assert all(not accepted for t, accepted, _ in drive.verdicts if t >= rejected[0][0])
    assert drive.error_m() < 5.0  # pulled a little before it was caught, never 30 m away


def test_without_gps_the_odometry_carries_the_pose_and_says_so() -> None:
    drive = Drive()
    drive.run(120)
    sigma_before = drive.fusion.pose().sigma_m
    drive.run(60, gps=False)
    pose = drive.fusion.pose()
    assert pose.source == "lidar"
    assert pose.sigma_m > sigma_before
    drive.run(3)
    assert drive.verdicts[-1][1] is True  # the GPS returns and is trusted at once
    assert drive.fusion.pose().source == "gps+lidar"


def test_a_pose_dead_reckoned_off_the_gps_is_relocalized_not_locked_out() -> None:
    """On the motion prior (the scans not registering: an open town in bright sun) with RTK
    fixes, a stalled scan in a turn leaves the heading 30° off: the pose runs metres off
    the GPS. The GPS is not refused for good (a pose left dead-reckoning held the patrol
    "inside" a building): after a few fixes that agree the pose is back on it."""
    fusion = PoseFusion(gps_sigma_m=0.02)
    fusion.heading_rad = 0.0
    now, x = 0.0, 0.0
    for _ in range(50):  # east at 5 m/s, RTK fixes at 10 Hz
        now += 0.1
        x += 0.5
        fusion.predict(Pose2D(0.5, 0.0, 0.0), "prior", now)
        assert fusion.gps(x, 0.0, now).accepted
    # The stall: 0.6 s in one step, on a turn the prior got wrong (30° right).
    now += 0.6
    x += 3.0
    fusion.predict(Pose2D(2.6, -1.5, math.radians(-30.0)), "prior", now)
    verdicts = []
    for _ in range(30):  # the truth goes on east; the pose thinks it heads 30° right
        now += 0.1
        x += 0.5
        fusion.predict(Pose2D(0.5, 0.0, 0.0), "prior", now)
        verdicts.append(fusion.gps(x, 0.0, now))
    refused = [v for v in verdicts if not v.accepted]
    assert refused and refused[0].innovation_m > 1.0  # it did run off the GPS
    assert verdicts[-1].accepted
    assert fusion.relocalized >= 1
    pose = fusion.pose()
    assert math.hypot(pose.x_m - x, pose.y_m) < 0.3


def test_a_spoofed_jump_stays_refused_however_long_the_prior_drives() -> None:
    """The re-localization is bounded by what dead reckoning could drift: a 30 m jump
    after 10 m on the prior is still a jump."""
    fusion = PoseFusion(gps_sigma_m=0.02)
    fusion.heading_rad = 0.0
    now, x = 0.0, 0.0
    for _ in range(10):
        now += 0.1
        x += 0.5
        fusion.predict(Pose2D(0.5, 0.0, 0.0), "prior", now)
        fusion.gps(x, 0.0, now)
    verdicts = []
    for _ in range(20):  # 10 m more, the spoofer 30 m north
        now += 0.1
        x += 0.5
        fusion.predict(Pose2D(0.5, 0.0, 0.0), "prior", now)
        verdicts.append(fusion.gps(x, 30.0, now))
    assert not any(v.accepted for v in verdicts)
    assert all(v.reason.startswith("jump: ") for v in verdicts)
    assert fusion.relocalized == 0
