"""CARMEN logs: the reader (FLASER, ROBOTLASER1, ODOM; bad lines dropped and counted), the
replay through the LD19 wire protocol (the real decoder and scan assembler), the whole
odometry pipeline on a sample log made from the simulator with its odometry as the prior,
and ``brasidas-platform simulate lidar --carmen FILE`` on a pty."""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import wait_until

from brasidas import topics
from brasidas.codecs.carmen import flaser_angles, format_flaser, format_odom, parse
from brasidas.codecs.ldlidar import LidarDecoder, ScanAssembler
from brasidas.config.lidar import LidarSection
from platformd.sim.carmen import (
    CarmenReplay,
    odometry_over_log,
    relative_translation_error,
    sample_log,
)

ROBOTLASER = (
    "ROBOTLASER1 0 -1.5708 3.1416 1.5708 40.0 0.01 0 3 2.0 50.0 3.0 0 "
    "1.0 2.0 0.5 1.0 2.0 0.5 0.3 0.0 0.5 0.5 0.0 1000.5 host 1000.6"
)


def test_the_reader_takes_flaser_robotlaser_and_odom_and_drops_bad_lines() -> None:
    ranges = [1.0] * 181
    ranges[90] = 3.5  # straight ahead
    lines = [
        "# a comment",
        format_odom((1.0, 2.0, 0.1), 0.5, 0.0, 10.0),
        format_flaser(ranges, (1.0, 2.0, 0.1), (1.1, 2.1, 0.2), 10.05),
        ROBOTLASER,
        "PARAM robot_width 0.5",
        "FLASER 3 1.0 2.0",  # truncated
        "FLASER 2 1.0 nan 0 0 0 0 0 0 1.0 host 1.0",  # not finite
        "FLASER 99999 1.0",  # absurd count
        "ODOM 1 2 three 0 0 0 1.0 host 1.0",
    ]
    log = parse(lines)
    assert len(log.scans) == 2
    assert len(log.odometry) == 1
    assert log.skipped == {"PARAM": 1}
    assert [number for number, _ in log.malformed] == [6, 7, 8, 9]
    assert "too few" in log.malformed[0][1]
    assert "not finite" in log.malformed[1][1]
    flaser, robot = log.scans
    assert flaser.time == pytest.approx(10.05)
    assert flaser.pose == (1.0, 2.0, 0.1)
    assert flaser.odometry == (1.1, 2.1, 0.2)
    assert flaser.angles_rad[90] == pytest.approx(0.0)
    assert flaser.ranges_m[90] == 3.5
    assert flaser.angles_rad[0] == pytest.approx(-math.pi / 2)
    assert robot.max_range_m == 40.0
    assert robot.ranges_m == (2.0, 50.0, 3.0)
    assert robot.angles_rad == pytest.approx((-1.5708, 0.0, 1.5708))
    assert robot.odometry == (1.0, 2.0, 0.5)
    assert robot.time == pytest.approx(1000.6)
    assert len(flaser_angles(180)) == 180
    assert flaser_angles(361)[1] == pytest.approx(-math.pi / 2 + math.radians(0.5))


def test_a_logged_scan_becomes_a_revolution_of_ld19_frames() -> None:
    """Ahead 3.5 m, left (90° counter-clockwise) 2 m, right 1.25 m, nothing behind (the
    FLASER's field is the front half), and a reading past the LD19's 12 m is none."""
    ranges = [81.9] * 181
    ranges[90], ranges[180], ranges[0] = 3.5, 2.0, 1.25
    ranges[45] = 20.0
    log = parse([format_flaser(ranges, (0, 0, 0), (0, 0, 0), t) for t in (1.0, 1.1)])
    replay = CarmenReplay(log, LidarSection(enabled=True))
    decoder, assembler = LidarDecoder(), ScanAssembler()
    revolutions = []
    for scan in log.scans:
        for frame in decoder.feed(replay.revolution(scan, scan.time), scan.time):
            done = assembler.feed(frame)
            if done is not None:
                revolutions.append(done)
    assert decoder.crc_errors == 0
    assert len(revolutions) == 1
    (scan,) = revolutions
    angles = np.asarray(scan.angles_deg)
    distances = np.asarray(scan.ranges_m)

    def at(clockwise: float) -> float:
        k = int(np.argmin(np.abs((angles - clockwise + 180) % 360 - 180)))
        return float(distances[k])

    assert at(0.0) == pytest.approx(3.5, abs=0.002)
    assert at(270.0) == pytest.approx(2.0, abs=0.002)  # left = 270° clockwise
    assert at(90.0) == pytest.approx(1.25, abs=0.002)
    assert at(180.0) == 0.0
    assert at(45.0) == 0.0  # behind; 20 m (45° right) beyond reach
    assert len(angles) == replay.points == 360  # 1° readings: 1° apart, all round


def test_the_pipeline_on_a_simulated_log_uses_its_odometry_as_the_prior() -> None:
    """A 30 s drive round the street grid (odometry 2 % long, yaw drifting 0.01 rad/s):
    the lidar odometry's motion over 1 m segments is closer to the truth than the log's own
    odometry, and most scans register (the others show fewer than the odometry's 60 returns:
    a FLASER is a half circle of 181 readings, and the LD19 sees 12 m of it)."""
    log = parse(sample_log(30.0))
    assert len(log.scans) >= 290
    assert not log.malformed
    out = odometry_over_log(log)
    assert len(out) == len(log.scans) - 1  # the last revolution waits for a next one
    registered = sum(1 for _, _, source in out if source == "lidar")
    assert registered >= 0.75 * len(out)
    truth = [scan.pose for scan, _, _ in out]
    estimate = [(p.x_m, p.y_m, p.yaw_rad) for _, p, _ in out]
    lidar = relative_translation_error(truth, estimate)
    wheels = relative_translation_error(truth, [scan.odometry for scan, _, _ in out])
    assert len(lidar) > 200
    assert float(np.mean(lidar)) < 0.03
    assert float(np.mean(lidar)) < float(np.mean(wheels))


async def test_simulate_lidar_carmen_replays_a_log_on_a_pty(tmp_path: Path) -> None:
    path = tmp_path / "drive.log"
    path.write_text("\n".join(sample_log(3.0)) + "\nFLASER garbage\n")
    scans = len(parse(path.read_text().splitlines()).scans)
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "platformd",
        "simulate",
        "lidar",
        "--carmen",
        str(path),
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    fd = -1
    decoder, assembler = LidarDecoder(), ScanAssembler()
    revolutions = 0
    try:
        assert process.stdout is not None
        first = await asyncio.wait_for(process.stdout.readline(), 20.0)
        pty = first.decode().strip()
        assert pty.startswith("/dev/pts/"), first
        fd = os.open(pty, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        loop = asyncio.get_running_loop()

        async def read_revolutions() -> None:
            nonlocal revolutions
            while True:  # until the simulator closes the pty at the log's end
                ready = loop.create_future()
                loop.add_reader(fd, ready.set_result, None)
                try:
                    await ready
                finally:
                    loop.remove_reader(fd)
                try:
                    data = os.read(fd, 4096)
                except BlockingIOError:
                    continue
                except OSError:  # EIO: the other side closed
                    return
                if not data:
                    return
                for frame in decoder.feed(data, loop.time()):
                    revolutions += assembler.feed(frame) is not None

        reading = asyncio.create_task(read_revolutions())
        _out, err = await asyncio.wait_for(process.communicate(), 20.0)
        await asyncio.wait_for(reading, 5.0)
    finally:
        if fd >= 0:
            os.close(fd)
        with contextlib.suppress(ProcessLookupError):
            process.terminate()
        await asyncio.wait_for(process.wait(), 10.0)
    text = err.decode()
    lost = int(re.search(r"(\d+) revolutions not read", text).group(1))  # type: ignore[union-attr]
    # The last revolution waits for a next one; the first may go by before the pty is opened.
    assert decoder.crc_errors == 0, text
    assert scans - 2 - lost <= revolutions <= scans - 1, text
    assert lost <= 2, text
    assert f"{scans} scans replayed" in text, text
    assert "1 lines dropped" in text, text
    assert "dropped: FLASER" in text


async def test_the_sim_vehicles_lidar_replays_a_carmen_log_through_the_daemon(
    robot_factory: Any, tmp_path: Path
) -> None:
    """``sim.carmen_file``: the --sim vehicle's lidar replays the log, not the simulated
    world (empty here): a post 0.45 m ahead in every logged scan stops the robot, seen by the
    real reader; after the log's last scan the lidar is silent and the robot stays stopped."""
    angles = flaser_angles(181)
    post = [0.45 if abs(a) < math.radians(4) else 30.0 for a in angles]  # 30 m: no return
    lines = [format_flaser(post, (0, 0, 0), (0, 0, 0), 1000.0 + 0.1 * k) for k in range(30)]
    path = tmp_path / "post.log"
    path.write_text("\n".join(lines) + "\n")
    robot = await robot_factory(
        "lidar.enabled=true", "autonomy.autostart=false", f"sim.carmen_file={path}"
    )
    bus = robot.ctx.bus

    def stopped(reason: str) -> bool:
        limits = bus.last(topics.PROXIMITY)
        return limits is not None and limits.reason.startswith(reason)

    await wait_until(lambda: stopped("stopped: obstacle"), 10)
    scan = bus.last(topics.LIDAR_SCAN)
    assert scan is not None
    assert len(scan.obstacles) == 1
    (seen,) = scan.obstacles
    ahead = LidarSection().mount_x_m + 0.45  # the sensor sits forward of the robot's centre
    assert abs(seen.x_m - ahead) < 0.05
    assert abs(seen.y_m) < 0.05
    replay = robot.ctx.sim.lidar_replay
    assert replay is not None
    assert robot.ctx.sim.lidar is None
    assert replay.scans == 30
    # The log is over (3 s): the lidar goes silent and the robot is held for it.
    await wait_until(lambda: stopped("stopped: no lidar scan"), 10)
