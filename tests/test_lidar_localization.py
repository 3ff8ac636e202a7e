"""The localizer on the bus: scans, commands, attitude and fixes in; a spoofed GPS refused,
reported in the perception telemetry and raised by the annunciator (90.30)."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
from collections.abc import Callable
from pathlib import Path

import pytest

from brasidas import topics
from brasidas.annunciator import GPS_REJECTED, Annunciator
from brasidas.autonomy.geo import LocalFrame
from brasidas.bus import Bus
from brasidas.codecs.telemetry_schema import Perception, Snapshot
from brasidas.config import TelemetryReceiverSection
from brasidas.messages import Attitude, GpsFix, Velocity
from brasidas.perception.grid import OccupancyGrid
from brasidas.perception.messages import RobotScan
from platformd.lidar_localization import Localizer
from platformd.lidar_reader import _localization
from platformd.sim.drive import MAX_SPEED_MPS, SimulatedDrive, loop_waypoints, street_grid
from platformd.sim.vehicle import VehicleModel


async def _until(predicate: Callable[[], bool], timeout: float = 10.0) -> None:
    async with asyncio.timeout(timeout):
        while not predicate():
            await asyncio.sleep(0.001)


class Rig:
    """The localizer on a bus, fed by a simulated drive (waits for each scan's processing)."""

    def __init__(self, grid_path: Path | None = None) -> None:
        self.bus = Bus()
        self.localizer = Localizer(self.bus, MAX_SPEED_MPS, grid_path=grid_path)
        self.drive = SimulatedDrive(street_grid(), loop_waypoints(), seed=2)
        self.frame = LocalFrame(*self.drive.vehicle.origin[:2])

    async def steps(self, count: int, offset_m: float = 0.0) -> None:
        bus, drive, frame, localizer = self.bus, self.drive, self.frame, self.localizer
        for _ in range(count):
            step = drive.step()
            truth = step.truth
            bus.publish(topics.MOTOR_COMMAND, Velocity(step.speed_command_mps / MAX_SPEED_MPS, 0))
            bus.publish(
                topics.ATTITUDE,
                Attitude(1, 0, 0, 0, 0, 0, math.degrees(truth.yaw_rad), stamp=step.time),
            )
            if step.gps is not None:
                latitude, longitude = frame.to_geo(step.gps[0] + offset_m, step.gps[1])
                fix = GpsFix(
                    latitude,
                    longitude,
                    42.0,
                    truth.speed_mps,
                    truth.course_deg,
                    1,
                    9,
                    1.0,
                    "",
                    stamp=step.time,
                )
                bus.publish(topics.GPS_FIX, fix)
            done = localizer.odometry.scans + 1
            bus.publish(topics.LIDAR_SCAN, step.scan)
            await _until(lambda: localizer.scans_done >= done)  # noqa: B023


async def test_a_gps_jump_is_refused_reported_and_raises_the_90_30_warning() -> None:
    rig = Rig()
    localizer, drive, steps = rig.localizer, rig.drive, rig.steps
    annunciator = Annunciator(TelemetryReceiverSection())
    task = asyncio.create_task(localizer.run())
    try:
        await asyncio.sleep(0)
        assert _localization(localizer)["localization"] == "none"  # no fix yet
        await steps(300)
        honest = _localization(localizer)
        assert honest["localization"] == "gps+lidar"
        assert honest["gps_rejected"] == 0
        assert honest["gps_accepted"] > 20
        assert honest["gps_refusal"] == ""
        assert annunciator.evaluate(Snapshot({Perception: Perception(**honest)}), 0, 0, 1) == []
        fused = localizer.fused
        assert fused is not None
        truth = drive.vehicle.pose()
        assert math.hypot(fused.x_m - truth.x_m, fused.y_m - truth.y_m) < 8.0

        await steps(20, offset_m=30.0)
        spoofed = _localization(localizer)
        assert spoofed["gps_refusal"].startswith("jump: ")
        assert spoofed["gps_accepted"] == honest["gps_accepted"]  # not one bad fix fused
        (change,) = annunciator.evaluate(Snapshot({Perception: Perception(**spoofed)}), 0, 0, 2)
        assert change.active
        assert change.warning.code == GPS_REJECTED
        assert str(GPS_REJECTED) == "90.30"
        assert change.warning.message.startswith("GPS refused: jump: ")
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


async def test_the_grid_is_saved_at_stop_and_loaded_at_start_in_its_frame(tmp_path: Path) -> None:
    path = tmp_path / "grid.npz"
    first = Rig(path)
    task = asyncio.create_task(first.localizer.run())
    await asyncio.sleep(0)  # subscribed
    await first.steps(60)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    saved = first.localizer.grid
    assert saved is not None
    assert saved.scans > 30
    assert path.exists()
    assert (saved.log_odds > 2.0).sum() > 100  # walls seen: cells surely occupied

    second = Rig(path)
    task = asyncio.create_task(second.localizer.run())
    try:
        await _until(lambda: second.localizer.grid is not None)
        loaded = second.localizer.grid
        assert loaded is not None
        assert loaded.scans == saved.scans
        frame = second.localizer.frame
        assert frame is not None
        assert (frame.latitude, frame.longitude) == (saved.latitude, saved.longitude)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)


async def test_a_grid_file_that_is_not_a_grid_is_refused_and_a_new_one_begun(
    tmp_path: Path,
) -> None:
    path = tmp_path / "grid.npz"
    path.write_bytes(b"garbage")
    rig = Rig(path)
    task = asyncio.create_task(rig.localizer.run())
    await asyncio.sleep(0)
    try:
        await rig.steps(30)
        assert "not a saved grid" in rig.localizer.grid_error
        assert rig.localizer.grid is not None
        assert rig.localizer.grid.scans > 0
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    assert OccupancyGrid.load(path).scans > 0  # the new grid replaced the garbage


def test_an_open_field_dash_and_stop_on_rtk_fixes_keeps_the_pose_on_the_robot() -> None:
    """Nothing for the scans to register (the motion prior carries the pose between fixes):
    the robot goes from standing to 5 m/s and brakes to a stop, RTK fixes at 10 Hz half a
    scan apart from the scans. The pose stays within 0.15 m of the truth and no honest fix
    is refused: the prior follows the drive's lag (not the command), each fix is compared
    with where the robot was at its time (not counted on top of the step that holds it),
    and weighted by the receiver's accuracy (``gps_sigma_m``), not a NEO-6M's."""
    now = [0.0]
    vehicle = VehicleModel(heading_deg=90.0, max_speed_mps=5.0, clock=lambda: now[0])
    localizer = Localizer(Bus(), 5.0, gps_sigma_m=0.02)
    frame = LocalFrame(*vehicle.origin[:2])
    empty = RobotScan(0.0, (), (), 0, ())
    errors: list[float] = []
    refused: list[str] = []
    command = 0.0
    for tick in range(1, 121):  # 6 s at 20 Hz: a scan, then a fix, in turn
        now[0] = tick * 0.05
        if tick == 10:
            command = 1.0
        if tick == 80:
            command = 0.0  # the lidar stop
        vehicle.set_command(command, 0.0)
        truth = vehicle.pose()
        if tick % 2:
            fix = GpsFix(
                truth.latitude,
                truth.longitude,
                42.0,
                abs(truth.speed_mps),
                truth.course_deg,
                4,
                20,
                0.6,
                "",
                stamp=now[0],
            )
            if not localizer.process(None, [fix], command * 5.0, 0.0) and localizer.fusion.started:
                refused.append(localizer.gps_refusal)
            continue
        localizer.process(dataclasses.replace(empty, time=now[0]), [], command * 5.0, 0.0)
        fused = localizer.fused
        if fused is not None:
            x, y = frame.to_local(truth.latitude, truth.longitude)
            errors.append(math.hypot(fused.x_m - x, fused.y_m - y))
    assert not refused, refused
    assert len(errors) > 40, max(errors)
    assert max(errors) < 0.15, max(errors)


def test_the_imu_turn_is_read_at_each_scans_time_and_a_reset_is_not_a_turn() -> None:
    """On a loaded machine the scans are processed late and in bursts: the IMU's turn is read
    at each scan's own time (between its samples), not at the moment it is processed, so
    each scan gets its share; a yaw that leaps (the IMU's filter restarted) is not a turn."""
    localizer = Localizer(Bus(), 5.0)
    empty = RobotScan(0.0, (), (), 0, ())
    for i in range(41):  # 2 s at 20 Hz turning left at 0.5 rad/s, a restart to 0 at 1.02 s
        t = 10.0 + i * 0.05
        yaw = 0.5 * (t - 10.0) - (0.51 if t > 11.02 else 0.0)
        localizer._on_attitude(Attitude(1, 0, 0, 0, 0, 0, math.degrees(yaw), stamp=t))
    rates = []
    for k in range(1, 20):  # all processed after the IMU's samples arrived
        scan = dataclasses.replace(empty, time=10.0 + k * 0.1)
        rate = localizer._yaw_rate(scan)
        rates.append(rate)
        localizer.process(scan, [], 0.0, rate)
    assert localizer.imu_jumps == 1
    assert all(r is not None and abs(r - 0.5) < 0.01 for r in rates[1:]), rates
    # The IMU goes silent: no turn is read from its last yaw (the command's is used).
    assert localizer._yaw_rate(dataclasses.replace(empty, time=13.0)) is None


async def test_a_scan_waits_for_the_imu_sample_of_its_time() -> None:
    """On a loaded machine a scan can reach the localizer before the IMU's sample of the same
    moment: read at once, the turn between went to the next scan instead, and the scan's
    registration, degrees off that prior, fell back to it. It waits for the sample (briefly)."""
    bus = Bus()
    localizer = Localizer(bus, 5.0)
    empty = RobotScan(0.0, (), (), 0, ())

    def imu(t: float, yaw_deg: float) -> None:
        bus.publish(topics.ATTITUDE, Attitude(1, 0, 0, 0, 0, 0, yaw_deg, stamp=t))

    async def scan_at(t: float) -> None:
        done = localizer.odometry.scans + 1
        bus.publish(topics.LIDAR_SCAN, dataclasses.replace(empty, time=t))
        await _until(lambda: localizer.scans_done >= done)

    task = asyncio.create_task(localizer.run())
    try:
        for k in range(11):  # standing still, facing east, to 10.5 s
            imu(10.0 + k * 0.05, 0.0)
        await scan_at(10.5)
        bus.publish(topics.LIDAR_SCAN, dataclasses.replace(empty, time=10.6))
        await _until(lambda: localizer.imu_waits == 1)  # its IMU sample not in yet
        imu(10.55, 0.0)
        await asyncio.sleep(0.05)  # (not a condition: that it goes on waiting)
        assert localizer.scans_done == 1
        imu(10.65, 10.0)  # turned 10° meanwhile: half of it by the scan's time
        await _until(lambda: localizer.scans_done == 2)
        assert math.degrees(localizer.last.delta.yaw_rad) == pytest.approx(5.0, abs=0.1)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def test_a_turn_made_while_the_imu_was_stale_is_taken_when_it_is_back() -> None:
    """A starved IMU reader: its samples stop for a second while the robot turns on the spot
    by 90° (commanded turn unknown to the prior: none), then come again. The turn the IMU
    saw meanwhile is given to the next scan, less what the scans took without it; before,
    the next scan after a stale IMU was given no turn and the heading stayed 90° off."""
    localizer = Localizer(Bus(), 5.0)
    empty = RobotScan(0.0, (), (), 0, ())

    def imu(t: float, yaw: float) -> None:
        localizer._on_attitude(Attitude(1, 0, 0, 0, 0, 0, math.degrees(yaw), stamp=t))

    for k in range(11):  # standing, facing east, an IMU sample each 50 ms up to 10.5 s
        imu(10.0 + k * 0.05, 0.0)
    t = 10.0
    for _ in range(5):
        t += 0.1
        localizer.process(dataclasses.replace(empty, time=t), [], 0.0, 0.0)
        localizer._yaw_rate(dataclasses.replace(empty, time=t))
    for _ in range(10):  # the IMU silent for a second: the prior turns by the command (0)
        t += 0.1
        scan = dataclasses.replace(empty, time=t)
        rate = localizer._yaw_rate(scan)
        localizer.process(scan, [], 0.0, rate, commanded_turn=0.0)
    imu(t + 0.05, math.radians(90.0))  # back: it turned left by 90° meanwhile
    t += 0.1
    scan = dataclasses.replace(empty, time=t)
    rate = localizer._yaw_rate(scan)
    assert rate is not None
    localizer.process(scan, [], 0.0, rate)
    assert abs(math.degrees(localizer.odometry.pose.yaw_rad) - 90.0) < 2.0
