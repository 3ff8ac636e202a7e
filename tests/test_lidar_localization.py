"""The localizer on the bus: scans, commands, attitude and fixes in; a spoofed GPS refused,
reported in the perception telemetry and raised by the annunciator (90.30)."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable

from brasidas import topics
from brasidas.annunciator import GPS_REJECTED, Annunciator
from brasidas.autonomy.geo import LocalFrame
from brasidas.bus import Bus
from brasidas.codecs.telemetry_schema import Perception, Snapshot
from brasidas.config import TelemetryReceiverSection
from brasidas.messages import Attitude, GpsFix, Velocity
from platformd.lidar import _localization
from platformd.lidar_localization import Localizer
from platformd.sim.drive import MAX_SPEED_MPS, SimulatedDrive, loop_waypoints, street_grid


async def _until(predicate: Callable[[], bool], timeout: float = 10.0) -> None:
    async with asyncio.timeout(timeout):
        while not predicate():
            await asyncio.sleep(0.001)


async def test_a_gps_jump_is_refused_reported_and_raises_the_90_30_warning() -> None:
    bus = Bus()
    localizer = Localizer(bus, MAX_SPEED_MPS)
    drive = SimulatedDrive(street_grid(), loop_waypoints(), seed=2)
    frame = LocalFrame(*drive.vehicle.origin[:2])
    annunciator = Annunciator(TelemetryReceiverSection())

    async def steps(count: int, offset_m: float = 0.0) -> None:
        for _ in range(count):
            step = drive.step()
            truth = step.truth
            bus.publish(topics.MOTOR_COMMAND, Velocity(step.speed_command_mps / MAX_SPEED_MPS, 0))
            bus.publish(topics.ATTITUDE, Attitude(1, 0, 0, 0, 0, 0, math.degrees(truth.yaw_rad)))
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
            await _until(lambda: localizer.odometry.scans >= done)  # noqa: B023

    task = asyncio.create_task(localizer.run())
    try:
        await asyncio.sleep(0)
        assert _localization(localizer)["localization"] == "none"  # no fix yet
        await steps(300)
        honest = _localization(localizer)
        assert honest["localization"] == "gps+lidar"
        assert honest["gps_rejected"] == 0 and honest["gps_accepted"] > 20
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
        assert change.active and change.warning.code == GPS_REJECTED
        assert str(GPS_REJECTED) == "90.30"
        assert change.warning.message.startswith("GPS refused: jump: ")
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
