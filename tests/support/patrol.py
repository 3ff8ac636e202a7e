"""A --sim platform patrolling at 18 km/h with its GPS at 10 Hz, what it published and the
simulated vehicle's truth (tests/test_patrol_platform.py; the lidar and map-limit tests drive
the same robot)."""

from __future__ import annotations

import math
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest
from conftest import quiet_platform_config, until_armable, wait_until

from brasidas import topics
from brasidas.config import PlatformConfig
from brasidas.messages import PatrolStatus, PoseEstimate, Velocity
from platformd.app import PlatformDaemon
from platformd.sim.demo_area import offset
from platformd.sim.vehicle import VehicleModel

LAT, LON = 37.9415, 23.6530


def config(tmp_path: Path, *overrides: str) -> PlatformConfig:
    return quiet_platform_config(
        "sim.enabled=true",
        "motor.enabled=true",
        "gps.enabled=true",
        "imu.enabled=true",
        "gps.sim_rate_hz=10",
        "platform.max_speed_kmh=18",
        "autonomy.cruise_speed_kmh=18",
        "autonomy.lookahead_m=3",
        "autonomy.decel_mps2=6",
        "autonomy.max_turn_rate_dps=86",
        "autonomy.clearance_m=2",
        f"map.file={tmp_path / 'map.geojson'}",
        f"autonomy.route_file={tmp_path / 'route.json'}",
        *overrides,
    )


RTK = ("sim.gps_receiver=rtk", "autonomy.gps_sigma_m=0.02", "autonomy.gps_jitter_m=0.02")
"""An RTK-corrected simulated receiver and the keys that tell the platform so (docs/operator-guide.md)."""


def at(east: float, north: float) -> str:
    return "{:.8f},{:.8f}".format(*offset(LAT, LON, east, north))


class Robot:
    """A running --sim platform, what it published, and the simulated vehicle's truth."""

    def __init__(self, daemon: PlatformDaemon) -> None:
        self.daemon = daemon
        self.ctx = daemon.ctx
        vehicle = daemon.ctx.sim.vehicle
        assert vehicle is not None
        self.vehicle: VehicleModel = vehicle
        self.reports: list[PatrolStatus] = []
        self.poses: list[tuple[PoseEstimate, tuple[float, float]]] = []
        """Each pose and the true vehicle's position (metres east, north) at the time."""
        self.cmd_vel: list[Velocity] = []
        self.watchers: list[Callable[[PoseEstimate, tuple[float, float]], None]] = []
        bus = self.ctx.bus
        self._unsubscribe = [
            bus.subscribe(topics.PATROL_STATUS, self.reports.append),
            bus.subscribe(topics.POSE, self._on_pose),
            bus.subscribe(topics.CMD_VEL, self.cmd_vel.append),
        ]

    def _on_pose(self, pose: PoseEstimate) -> None:
        truth = self.vehicle.pose()
        east, north = self.local(truth.latitude, truth.longitude)
        here = (east, north)
        self.poses.append((pose, here))
        for watcher in self.watchers:
            watcher(pose, here)

    def local(self, latitude: float, longitude: float) -> tuple[float, float]:
        """Metres east and north of the sim's start."""
        north = (latitude - LAT) * 110_574.0
        east = (longitude - LON) * 111_320.0 * math.cos(math.radians(LAT))
        return east, north

    @property
    def status(self) -> PatrolStatus:
        report = self.ctx.bus.last(topics.PATROL_STATUS)
        assert report is not None
        return report

    async def call(self, method: str, **params: Any) -> Any:
        if method == "patrol_start":  # a pilot starts once the pre-arm checks pass (it arms)
            await until_armable(self.ctx)
        return await self.ctx.rpc.call_local(method, **params)

    def close(self) -> None:
        for unsubscribe in self._unsubscribe:
            unsubscribe()

    def history(self) -> list[tuple[str, int | None, int, str]]:
        """The patrol's changes of state, target, lap and reason: a failure's explanation."""
        changes: list[tuple[str, int | None, int, str]] = []
        for report in self.reports:
            change = (report.state, report.waypoint, report.lap, report.reason)
            if not changes or changes[-1] != change:
                changes.append(change)
        return changes

    async def drive_laps(
        self, laps: int, timeout: float = 150.0, also_transient: tuple[str, ...] = ()
    ) -> None:
        """Until the patrol has completed ``laps``; fails at once, with the patrol's history,
        if it holds for anything but a late fix (a busy machine can delay one), the new
        plan of a changed map (built off the event loop) or ``also_transient``'s reasons."""

        def done() -> bool:
            status = self.status
            # a late fix, a map change, a plan asked of the planner process
            transient = (
                "GPS fix",
                "waiting for the new plan",
                "planning the path",
                *also_transient,
            )
            if status.state == "holding" and not any(t in status.reason for t in transient):
                raise AssertionError(f"holding: {status.reason}; history {self.history()}")
            return status.lap >= laps

        try:
            await wait_until(done, timeout)
        except TimeoutError:
            raise AssertionError(f"not {laps} laps in {timeout:g} s: {self.history()}") from None


@pytest.fixture
async def robot_factory(tmp_path: Path) -> AsyncIterator[Callable[..., Any]]:
    started: list[tuple[PlatformDaemon, Robot]] = []

    async def start(*overrides: str) -> Robot:
        daemon = PlatformDaemon(config(tmp_path, *overrides), None)
        await daemon.start()
        robot = Robot(daemon)
        started.append((daemon, robot))
        await wait_until(lambda: daemon.ctx.bus.last(topics.POSE) is not None, 10)
        return robot

    yield start
    for daemon, robot in started:
        robot.close()
        await daemon.stop()
