"""The lidar: LD06/LD19/STL-27L frames from the serial line to scans, obstacles and speed limits.

The reader opens ``lidar.port`` (8N1 at the model's baud rate) with pyserial-asyncio and hands
the bytes to the sans-IO :mod:`brasidas.codecs.ldlidar` decoder and scan assembler (on the
loop: a few hundred small frames a second). Each revolution is turned into the robot's frame
and its obstacles and speed limits computed in the lidar's own worker thread
(:mod:`brasidas.perception.proximity`), then published: ``LIDAR_SCAN`` and ``PROXIMITY``, which
the motion arbiter applies to every motor command in every mode. Each limit allows for how late limits
have recently reached the arbiter (:mod:`brasidas.perception.latency`): on a starved CPU the
robot approaches more slowly, so a stall does not eat its clearance. Bytes are read in large
gulps, so a backlog on the line yields its newest revolution at once, never a queue of old
ones. When scans stop for
``lidar.scan_timeout_s`` (port gone, sensor stalled) the limits become a stop: a robot that
cannot see does not drive. A port that is missing or vanishes is reported and reopened with
capped backoff, as the GPS's is.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import dataclasses
import functools
import logging
import math
from pathlib import Path
from typing import Any

import serial

from brasidas import topics
from brasidas.actor import Actor
from brasidas.autonomy.areamap import AreaMap
from brasidas.bus import Bus
from brasidas.clock import Clock, LoopClock, timeout_at
from brasidas.codecs.ldlidar import LidarDecoder, LidarScan, ScanAssembler
from brasidas.codecs.telemetry_schema import Perception
from brasidas.config.lidar import LidarSection
from brasidas.messages import Mode, PoseEstimate, Velocity
from brasidas.perception.latency import MAX_EXTRA_S, DriveSpeed, UpdateLatency
from brasidas.perception.limits import limit_for
from brasidas.perception.messages import Proximity, RobotScan
from brasidas.perception.proximity import Geometry, proximity, silent, to_robot
from brasidas.perception.view import PlanePose, pose_at, reframe
from brasidas.security import state_dir
from platformd.context import PlatformContext, SerialDevice
from platformd.lidar_localization import DRIVE_LAG_S, GPS_WAIT_S, Localizer
from platformd.lidar_models import MODELS, baudrate_of
from platformd.serial_port import PortOpener, read_line_forever

_LOGGER = logging.getLogger(__name__)

READ_SIZE = 65536
"""A whole backlog at once (a second of STL-27L is 36 kB): only its newest scan is judged."""


class LidarReader(Actor):
    """Reads the sensor; publishes scans in the robot's frame and the speed limits."""

    name = "lidar"

    def __init__(
        self,
        bus: Bus,
        config: LidarSection,
        geometry: Geometry,
        *,
        clock: Clock | None = None,
    ) -> None:
        super().__init__(bus)
        self.config = config
        self.geometry = geometry
        self.opener = PortOpener(SerialDevice(config.port, baudrate_of(config)))
        self.clock: Clock = clock or LoopClock()
        self.decoder = LidarDecoder()
        self.assembler = ScanAssembler()
        self.connected = False
        self.error = ""
        self.scans = 0
        self.scans_skipped = 0
        """Revolutions not analysed because the worker was still busy with the previous one."""
        self.last: RobotScan | None = None
        self.proximity: Proximity = silent(0.0, config.scan_timeout_s)
        self._last_scan_at: float | None = None
        self._scan_times: collections.deque[float] = collections.deque(maxlen=64)
        self._pending: LidarScan | None = None
        self._wake = asyncio.Event()
        self._worker = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="lidar")
        self.localizer: Localizer | None = None
        """The odometry and GPS gate, when ``lidar.odometry``: its figures join the section."""
        self._poses: collections.deque[tuple[float, PlanePose]] = collections.deque(maxlen=64)
        self._asks: dict[Mode, Velocity] = {}
        """The last motion asked of the motors by each mode's source (not retained topics)."""
        self.scan_pose: PlanePose | None = None
        """The robot's pose (``POSE``) in the middle of the last scan's revolution."""
        self.latency = UpdateLatency(1.0 / MODELS[config.model].rate_hz, MAX_EXTRA_S)
        """How late limits reach the arbiter: the dead time the next ones allow for."""
        self.extra_dead_s = 0.0
        """The extra dead time the last limits were computed with."""
        self.drive = DriveSpeed(DRIVE_LAG_S)
        """The speed the drive has reached, from ``MOTOR_COMMAND``: the limits judge it."""

    async def run(self) -> None:
        self.bus.publish(topics.PROXIMITY, self.proximity)  # stopped until the first scan
        unsubscribes = [
            self.bus.subscribe(topics.POSE, self._on_pose),
            self.bus.subscribe(topics.MOTOR_COMMAND, self._on_motor_command),
            self.bus.subscribe(topics.CMD_VEL, functools.partial(self._on_ask, Mode.AUTONOMOUS)),
            self.bus.subscribe(
                topics.TELEOP_VELOCITY, functools.partial(self._on_ask, Mode.TELEOP)
            ),
        ]
        try:
            async with asyncio.TaskGroup() as group:
                group.create_task(self._analyse_loop(), name="lidar:analyse")
                await read_line_forever(self)
        finally:
            for unsubscribe in unsubscribes:
                unsubscribe()
            self.opener.close()
            self._worker.shutdown(wait=False, cancel_futures=True)

    # ------------------------------------------------------------------ serial line

    def line_opened(self, device: serial.Serial) -> None:
        _LOGGER.info("lidar (%s) reading %s", self.config.model, self.config.port)
        self.connected = True
        self.error = ""
        self.decoder.reset()

    async def read_line(self, reader: asyncio.StreamReader) -> None:
        while True:
            try:
                async with timeout_at(self.clock, self._deadline()):
                    data = await reader.read(READ_SIZE)
            except TimeoutError:
                self._check_silence()
                continue
            if not data:
                return
            self.feed(data)

    def _deadline(self) -> float | None:
        if self._last_scan_at is None:
            return None
        return self._last_scan_at + self.config.scan_timeout_s

    def feed(self, data: bytes) -> None:
        """Bytes from the sensor; a completed revolution goes to the worker. On the loop."""
        now = self.clock.time()
        for frame in self.decoder.feed(data, now):
            scan = self.assembler.feed(frame)
            if scan is not None:
                self.scans += 1
                self._last_scan_at = now
                self._scan_times.append(now)
                if self._pending is not None:
                    self.scans_skipped += 1
                self._pending = scan
                self._wake.set()

    def _check_silence(self) -> None:
        last = self._last_scan_at
        if last is not None and self.clock.time() - last >= self.config.scan_timeout_s:
            self._last_scan_at = None
            self.latency.reset()
            self._blind(f"no lidar scan for {self.config.scan_timeout_s:g} s")

    def line_down(self, reason: str, *, log: bool) -> None:
        self.connected = False
        self.error = reason
        (_LOGGER.warning if log else _LOGGER.debug)("lidar: %s; retrying", reason)
        self._last_scan_at = None
        self._blind(reason)
        self.latency.reset()

    def _blind(self, reason: str) -> None:
        if self.proximity.forward_limit == 0 and self.proximity.reverse_limit == 0:
            if self.proximity.reason.endswith(reason):
                return
        self.proximity = dataclasses.replace(
            silent(self.clock.time(), self.config.scan_timeout_s), reason=f"stopped: {reason}"
        )
        _LOGGER.warning("lidar blind (%s): motors held at zero", reason)
        self.bus.publish(topics.PROXIMITY, self.proximity)

    # ------------------------------------------------------------------ analysis (worker thread)

    async def _analyse_loop(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await self._wake.wait()
            self._wake.clear()
            scan, self._pending = self._pending, None
            if scan is None:
                continue
            now = self.clock.time()
            extra, speed = self.latency.extra(now), self.drive.at(now)
            robot, limits = await loop.run_in_executor(
                self._worker, self._analyse, scan, extra, speed
            )
            if self._last_scan_at is None:
                continue  # went blind while the worker ran: the stop stands
            self.latency.published(self.clock.time(), scan.ended)
            self.extra_dead_s = extra
            self.last = robot
            self.scan_pose = pose_at(self._poses, (scan.started + scan.ended) / 2)
            self.bus.publish(topics.LIDAR_SCAN, robot)
            if _stopped(limits) != _stopped(self.proximity):  # not every slowing: the log
                log = _LOGGER.warning if _stopped(limits) else _LOGGER.info
                log("lidar: %s", limits.reason or "way clear")
            self.proximity = limits
            self.bus.publish(topics.PROXIMITY, limits)

    def _analyse(
        self, scan: LidarScan, extra_dead_s: float, speed_mps: float
    ) -> tuple[RobotScan, Proximity]:
        robot = to_robot(scan, self.geometry)
        return robot, proximity(robot, self.geometry, self.proximity, extra_dead_s, speed_mps)

    def _on_pose(self, pose: PoseEstimate) -> None:
        if pose.heading_known:
            self._poses.append((pose.time, (pose.x_m, pose.y_m, pose.yaw_rad)))
        else:
            self._poses.clear()  # a yaw that is a guess places nothing

    def as_shown(self, bearing_deg: float, range_m: float) -> tuple[float, float]:
        """A point of the last scan around the robot's latest pose, the one telemetry shows
        it with: the robot moved and turned since the scan (by the pose's own estimate)."""
        latest = self.bus.last(topics.POSE)
        then = self.scan_pose
        if then is None or latest is None or not latest.heading_known:
            return bearing_deg, range_m
        return reframe(bearing_deg, range_m, then, (latest.x_m, latest.y_m, latest.yaw_rad))

    def _on_motor_command(self, velocity: Velocity) -> None:
        self.drive.commanded(self.clock.time(), velocity.linear * self.geometry.max_speed_mps)

    def _on_ask(self, mode: Mode, velocity: Velocity) -> None:
        self._asks[mode] = velocity

    def _asked(self) -> tuple[float, float]:
        """The motion asked of the motors now (the hand or the patrol's), before the limits:
        the arc whose limit and reason are shown."""
        state = self.bus.last(topics.MOTION_STATE)
        asked = self._asks.get(state.mode if state is not None else Mode.AUTONOMOUS)
        return (asked.linear, asked.angular) if asked is not None else (0.0, 0.0)

    def scan_hz(self) -> float:
        """Revolutions in the last second."""
        now = self.clock.time()
        return float(sum(1 for t in self._scan_times if now - t <= 1.0))

    def section(self) -> Perception:
        """The ``perception`` telemetry section."""
        limits, scan = self.proximity, self.last
        obstacles: list[tuple[float, ...]] = []
        if scan is not None and self._last_scan_at is not None:
            for o in scan.obstacles:
                bearing, distance = self.as_shown(
                    math.degrees(math.atan2(-o.y_m, o.x_m)) % 360.0, math.hypot(o.x_m, o.y_m)
                )
                obstacles.append((round(bearing, 1), round(distance, 2), o.radius_m))
            obstacles = sorted(obstacles, key=lambda o: o[1])[:12]
        forward, reason = limit_for(limits, *self._asked())
        return Perception(
            connected=self.connected,
            scan_hz=self.scan_hz(),
            points_used=scan.points_used if scan is not None else 0,
            nearest_m=limits.nearest_m,
            nearest_bearing_deg=limits.nearest_bearing_deg,
            forward_limit=round(forward, 3),
            reverse_limit=round(limits.reverse_limit, 3),
            reason=reason,
            obstacles=tuple(obstacles),
            crc_errors=self.decoder.crc_errors,
            **_localization(self.localizer),
        )

    def counters(self) -> dict[str, Any]:
        return {
            "scans": self.scans,
            "scans_skipped": self.scans_skipped,
            "frames": self.decoder.frames,
            "crc_errors": self.decoder.crc_errors,
            "resync_bytes": self.decoder.resync_bytes,
            "extra_dead_ms": round(self.extra_dead_s * 1000),
            "worst_update_gap_ms": round(self.latency.worst_s * 1000),
        }


def _localization(localizer: Localizer | None) -> dict[str, Any]:
    if localizer is None:
        return {"localization": "off"}
    fused = localizer.fused
    return {
        "localization": fused.source if fused is not None else "none",
        "position_sigma_m": round(fused.sigma_m, 2) if fused is not None else None,
        "gps_accepted": localizer.fusion.accepted,
        "gps_rejected": localizer.fusion.rejected,
        "gps_refusal": localizer.gps_refusal,
        "map_place": localizer.map_place(),
    }


def _stopped(limits: Proximity) -> bool:
    return limits.forward_limit == 0.0 or limits.reverse_limit == 0.0


def grid_path(config: LidarSection) -> Path:
    """Where the occupancy grid is kept (``lidar.grid_file``)."""
    return Path(config.grid_file).expanduser() if config.grid_file else state_dir() / "grid.npz"


def capabilities(config: LidarSection) -> dict[str, Any]:
    return {"model": config.model, "port": config.port, "baudrate": baudrate_of(config)}


async def async_setup(ctx: PlatformContext) -> None:
    config = ctx.config.lidar
    if not config.enabled:
        return
    simulator = ctx.sim.lidar or ctx.sim.lidar_replay
    section = dataclasses.replace(config, port=simulator.path) if simulator else config
    geometry = Geometry(
        section,
        ctx.config.safety.braking_mps2,
        ctx.config.platform.max_speed_kmh / 3.6,
        math.radians(ctx.config.autonomy.full_turn_rate_dps),
    )
    reader = LidarReader(ctx.bus, section, geometry)
    ctx.capabilities.register("lidar", lambda: capabilities(section))
    ctx.telemetry.add_counters("lidar", reader.counters)
    ctx.telemetry.register(Perception, reader.section)
    ctx.supervisor.start(reader)
    if config.odometry:

        def area() -> AreaMap | None:  # the patrol's map, once autonomy has set up
            return ctx.patrol.area if ctx.patrol is not None else None

        reader.localizer = Localizer(
            ctx.bus,
            ctx.config.platform.max_speed_kmh / 3.6,
            grid_path=grid_path(config),
            area=area,
            max_yaw_rate_rad_s=math.radians(ctx.config.autonomy.full_turn_rate_dps),
            gps_sigma_m=ctx.config.autonomy.gps_sigma_m,
            gps_wait_s=GPS_WAIT_S if ctx.config.gps.enabled else 0.0,
        )
        ctx.telemetry.add_counters("localization", reader.localizer.counters)
        ctx.supervisor.start(reader.localizer)
    from platformd import perception_view  # the scan, grid and fused pose shown

    perception_view.start(ctx, reader)
    if config.map_obstacles:
        from platformd import obstacle_zones  # the patrol's temporary keep-outs

        obstacle_zones.start(ctx)
