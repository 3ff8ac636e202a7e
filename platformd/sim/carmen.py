"""A CARMEN scan log replayed through the lidar's own wire protocol (issue 30), and small
sample logs made from the simulator for the tests and the benchmark.

:class:`CarmenReplay` (sans-IO) turns each logged scan into one revolution of the configured
model's frames (12 points a frame, angles clockwise from the sensor's zero, at the log's
angular resolution: 360 points for 1° readings), each of its points the log's reading in that
direction (none where the log's field of view does
not reach, beyond the model's range or the log's maximum), and gives the log's odometry
between two scans as the motion prior (forward speed, turn rate), as the commanded speed and
the gyro are on the robot. ``brasidas-platform simulate lidar --carmen FILE`` writes the frames
on a pty at the log's pace (:func:`serve_log`).

:func:`sample_log` drives the simulated vehicle round the street grid of
:mod:`platformd.sim.drive` and logs, every revolution, a 181-reading FLASER scan cast from its
true pose (1 cm noise), the true pose as the laser pose, and wheel odometry that drifts (2 %
scale, a yaw bias); never a third party's data.
"""

from __future__ import annotations

import asyncio
import collections
import itertools
import logging
import math
import random
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from brasidas.actor import Actor, wait_forever
from brasidas.bus import Bus
from brasidas.codecs.carmen import CarmenLog, CarmenScan, format_flaser, format_odom, parse
from brasidas.codecs.ldlidar import POINTS_PER_FRAME, encode_frame
from brasidas.config.lidar import LidarSection
from brasidas.perception.odometry import Pose2D
from platformd.lidar_models import MODELS
from platformd.sim.pty_line import PtyLine

YAW_BIAS_RAD_S = 0.01
"""The sample log's odometry turns this much more than the robot did (a wheel a bit small)."""
_LOGGER = logging.getLogger(__name__)

MIN_GAP_S, MAX_GAP_S = 0.02, 1.0
"""The pace between two scans on the pty: the log's, within these (a pause in a log is not
a lidar gone silent; a burst is not faster than the line)."""


@dataclass(frozen=True)
class Prior:
    """The log's odometry from the previous scan to this one, as the robot's prior."""

    speed_mps: float
    turn_rad_s: float
    dt_s: float


class CarmenReplay:
    """Scans of a log in, the configured model's frames out (one revolution a scan)."""

    def __init__(self, log: CarmenLog, config: LidarSection) -> None:
        self.log = log
        self.config = config
        self.model = MODELS[config.model]
        self.speed_dps = round(360.0 * self.model.rate_hz)
        self.points = 0
        """Points in the last revolution made: the log's angular resolution over 360° (the
        sensor's own density varies with its speed, so the frames may carry the log's
        directions exactly rather than resampled)."""

    def grid(self, scan: CarmenScan) -> tuple[int, float]:
        """Points a revolution for ``scan`` (a whole number of frames) and their spacing (°)."""
        angles = np.sort(np.asarray(scan.angles_rad))
        spacing = math.degrees(float(np.median(np.diff(angles)))) if len(angles) > 1 else 1.0
        points = max(POINTS_PER_FRAME, round(360.0 / max(0.05, spacing)))
        points += -points % POINTS_PER_FRAME
        return points, 360.0 / points

    def ranges(self, scan: CarmenScan) -> np.ndarray:
        """The revolution's ranges (m; 0: none), point k at k·step clockwise from the zero."""
        angles = np.asarray(scan.angles_rad)
        ranges = np.asarray(scan.ranges_m)
        order = np.argsort(angles)
        angles, ranges = angles[order], ranges[order]
        points, step_deg = self.grid(scan)
        sensor = np.arange(points) * step_deg
        # The sensor's zero is turned yaw_deg from forward; its angles grow clockwise.
        ccw = np.radians(self.config.yaw_deg - sensor)
        ccw = (ccw + math.pi) % (2 * math.pi) - math.pi
        index = np.clip(np.searchsorted(angles, ccw), 1, len(angles) - 1)
        left, right = angles[index - 1], angles[index]
        nearest = np.where(ccw - left < right - ccw, index - 1, index)
        gap = np.abs(angles[nearest] - ccw)
        spacing = float(np.median(np.diff(angles))) if len(angles) > 1 else math.radians(1)
        out = ranges[nearest]
        reach = min(scan.max_range_m, self.model.range_m)
        usable = (gap <= spacing * 0.51) & (out >= self.model.min_range_m) & (out < reach)
        return np.where(usable, out, 0.0)

    def revolution(self, scan: CarmenScan, now: float) -> bytes:
        """The frames of one revolution showing ``scan``, stamped ``now`` (s)."""
        ranges_mm = np.round(self.ranges(scan) * 1000).astype(int)
        self.points, step_deg = self.grid(scan)
        frames = []
        for first in range(0, self.points, POINTS_PER_FRAME):
            chunk = ranges_mm[first : first + POINTS_PER_FRAME]
            start = first * step_deg
            end = (first + POINTS_PER_FRAME - 1) * step_deg
            intensities = [200 if r > 0 else 0 for r in chunk]
            frames.append(
                encode_frame(
                    self.speed_dps,
                    start,
                    end,
                    [int(r) for r in chunk],
                    intensities,
                    int(now * 1000) % 30000,
                )
            )
        return b"".join(frames)

    def priors(self) -> Iterator[tuple[CarmenScan, Prior]]:
        """Each scan with the odometry's motion since the one before (the first: still)."""
        previous: CarmenScan | None = None
        for scan in self.log.scans:
            if previous is None:
                yield scan, Prior(0.0, 0.0, 0.0)
            else:
                yield scan, odometry_prior(previous, scan)
            previous = scan


def odometry_prior(before: CarmenScan, after: CarmenScan) -> Prior:
    """Forward speed and turn rate from the logged odometry of two scans."""
    dt = after.time - before.time
    if dt <= 0:
        return Prior(0.0, 0.0, 0.0)
    x0, y0, t0 = before.odometry
    x1, y1, t1 = after.odometry
    c, s = math.cos(t0), math.sin(t0)
    forward = c * (x1 - x0) + s * (y1 - y0)
    turn = math.atan2(math.sin(t1 - t0), math.cos(t1 - t0))
    return Prior(forward / dt, turn / dt, dt)


def load(path: str | Path) -> CarmenLog:
    with open(path, encoding="utf-8", errors="replace") as handle:
        return parse(handle)


# --------------------------------------------------------------------------- sample logs


def sample_log(seconds: float = 60.0, *, seed: int = 1, speed_mps: float = 1.0) -> list[str]:
    """A FLASER + ODOM log of a drive round the simulated street grid (see the module)."""
    from platformd.sim.drive import SimulatedDrive, loop_waypoints, street_grid
    from platformd.sim.lidar import LidarWorld

    world = street_grid()
    drive = SimulatedDrive(world, loop_waypoints(), seed=seed, speed_mps=speed_mps)
    rng = random.Random(seed + 7)
    directions = np.radians(np.linspace(-90.0, 90.0, 181))
    lines = ["# brasidas simulated drive (platformd/sim/carmen.py): truth as the laser pose"]
    odometry: tuple[float, float, float] | None = None
    last = None
    last_time = 0.0
    while drive.now < seconds:
        step = drive.step()
        truth = step.truth
        if last is None or odometry is None:
            odometry = (truth.x_m, truth.y_m, truth.yaw_rad)
        else:
            # Wheel odometry: the true motion in the robot's frame, 2 % long, yaw drifting.
            c, s = math.cos(last.yaw_rad), math.sin(last.yaw_rad)
            dx, dy = truth.x_m - last.x_m, truth.y_m - last.y_m
            forward, left = c * dx + s * dy, -s * dx + c * dy
            dyaw = truth.yaw_rad - last.yaw_rad + YAW_BIAS_RAD_S * (step.time - last_time)
            dyaw += rng.gauss(0.0, 0.002)
            ox, oy, ot = odometry
            oc, os_ = math.cos(ot), math.sin(ot)
            forward *= 1.02
            odometry = (ox + oc * forward - os_ * left, oy + os_ * forward + oc * left, ot + dyaw)
        last, last_time = truth, step.time
        segments, discs = world.near(truth.x_m, truth.y_m, 30.0)
        ranges, _ = LidarWorld.cast(
            truth.x_m, truth.y_m, truth.yaw_rad + directions, segments, discs
        )
        ranges = np.where(np.isfinite(ranges), ranges, 81.9)
        noisy = [round(r + rng.gauss(0.0, 0.01), 3) if r < 81 else 81.9 for r in ranges.tolist()]
        pose = (truth.x_m, truth.y_m, truth.yaw_rad)
        lines.append(format_odom(odometry, step.speed_command_mps, truth.yaw_rate_rad_s, step.time))
        lines.append(format_flaser(noisy, pose, odometry, step.time))
    return lines


# --------------------------------------------------------------------------- the pty

LOG_END_DRAIN_S = 10.0
"""At the log's end, how long the replay waits for its reader to take what it wrote."""


async def replay_to(line: PtyLine, replay: CarmenReplay) -> None:
    """Every scan of the log as a revolution written to ``line`` at the log's pace (gaps
    clamped to :data:`MIN_GAP_S`..:data:`MAX_GAP_S`); revolutions nobody read are counted in
    the line's ``overruns``."""
    previous: float | None = None
    for scan, _prior in replay.priors():
        if previous is not None:
            await asyncio.sleep(min(MAX_GAP_S, max(MIN_GAP_S, scan.time - previous)))
        previous = scan.time
        line.write(replay.revolution(scan, time.monotonic()))


async def serve_log(path: str, config: LidarSection) -> None:
    """``brasidas-platform simulate lidar --carmen FILE``: the pty's path on stdout's first
    line, then every scan of the log as a revolution at the log's pace; a summary on stderr
    at the end (scans, lines skipped and dropped)."""
    log = await asyncio.to_thread(load, path)
    line = PtyLine("carmen replay")
    try:
        sys.stdout.write(line.path + "\n")
        sys.stdout.flush()
        for number, why in log.malformed[:5]:
            print(f"carmen: line {number} dropped: {why}", file=sys.stderr)
        await replay_to(line, CarmenReplay(log, config))
        # The last revolutions read before the line closes; a reader on a loaded machine may
        # lag seconds behind (the line's 2 s left 4 of 30 revolutions unread at five test
        # workers on two cores, and closing dropped them uncounted).
        await line.drained(LOG_END_DRAIN_S)
        print(
            f"carmen: {len(log.scans)} scans replayed from {path}; "
            f"{len(log.malformed)} lines dropped, skipped {log.skipped or 'none'}; "
            f"{line.overruns} revolutions not read",
            file=sys.stderr,
        )
    finally:
        line.close()


class CarmenSimulator(Actor):
    """In ``--sim`` with ``sim.carmen_file``: the vehicle's lidar replays a recorded CARMEN log
    on its pty (the same wire bytes as :func:`serve_log`), once; then it is silent, and the
    platform stops for a blind lidar. The simulated vehicle's motion does not move the scans
    (they are the log's), and the log's odometry is not the localizer's prior here."""

    name = "sim:lidar"

    def __init__(self, bus: Bus, path: str, config: LidarSection) -> None:
        super().__init__(bus)
        self.file = path
        self.config = config
        self.line = PtyLine("simulated lidar (CARMEN replay)")
        self.path = self.line.path
        self.scans = 0
        """Scans in the log (once loaded)."""

    async def run(self) -> None:
        try:
            log = await asyncio.to_thread(load, self.file)
            self.scans = len(log.scans)
            for number, why in log.malformed[:5]:
                _LOGGER.warning("carmen: %s line %d dropped: %s", self.file, number, why)
            _LOGGER.info("lidar replaying %s: %d scans", self.file, self.scans)
            await replay_to(self.line, CarmenReplay(log, self.config))
            _LOGGER.warning(
                "carmen: %d scans of %s replayed (%d not read): the lidar is silent now",
                self.scans,
                self.file,
                self.line.overruns,
            )
            await wait_forever()
        finally:
            self.line.close()


# --------------------------------------------------------------------------- the pipeline


def odometry_over_log(
    log: CarmenLog, config: LidarSection | None = None
) -> list[tuple[CarmenScan, Pose2D, str]]:
    """The log through the whole pipeline, sans-IO: each scan as the model's frames, the real
    decoder and scan assembler, :func:`~brasidas.perception.proximity.to_robot`, and the
    lidar odometry with the log's odometry as its prior. Each logged scan with the pose the
    odometry gives it (its frame: where the first scan was) and what that rests on."""
    from brasidas.codecs.ldlidar import LidarDecoder, ScanAssembler
    from brasidas.perception.odometry import LidarOdometry, scan_points
    from brasidas.perception.proximity import Geometry, to_robot

    config = config or LidarSection(enabled=True, mount_x_m=0.0, min_points=3)
    replay = CarmenReplay(log, config)
    decoder, assembler = LidarDecoder(), ScanAssembler()
    geometry = Geometry(config, 4.2, 2.0)
    odometry = LidarOdometry()
    pending: collections.deque[tuple[CarmenScan, Prior]] = collections.deque()
    out: list[tuple[CarmenScan, Pose2D, str]] = []
    for scan, prior in replay.priors():
        pending.append((scan, prior))
        for frame in decoder.feed(replay.revolution(scan, scan.time), scan.time):
            revolution = assembler.feed(frame)
            if revolution is None or not pending:
                continue
            logged, motion = pending.popleft()
            # A logged scan is one instant (no skew to undo): the prior is for the motion.
            points = scan_points(to_robot(revolution, geometry))
            step = odometry.update(points, logged.time, motion.speed_mps, motion.turn_rad_s)
            out.append((logged, step.pose, step.source))
    return out


def relative_translation_error(
    truth: list[tuple[float, float, float]],
    estimate: list[tuple[float, float, float]],
    segment_m: float = 1.0,
) -> list[float]:
    """For each pose, the translation error of the estimate's motion over the next
    ``segment_m`` of true travel, relative to it (a fraction: 0.01 is 1 %)."""
    travelled = [0.0]
    for a, b in itertools.pairwise(truth):
        travelled.append(travelled[-1] + math.hypot(b[0] - a[0], b[1] - a[1]))
    errors = []
    j = 0
    for i in range(len(truth)):
        j = max(j, i + 1)
        while j < len(truth) and travelled[j] - travelled[i] < segment_m:
            j += 1
        if j >= len(truth):
            break
        true_motion = _relative(truth[i], truth[j])
        estimated = _relative(estimate[i], estimate[j])
        length = travelled[j] - travelled[i]
        error = math.hypot(estimated[0] - true_motion[0], estimated[1] - true_motion[1])
        errors.append(error / length)
    return errors


def _relative(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return (c * dx + s * dy, -s * dx + c * dy)
