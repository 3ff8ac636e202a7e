"""Simulated NEO-6M: valid NMEA for the vehicle's pose; the real reader in --sim; standalone."""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import itertools
import math
import os
import random
import re
import sys
from collections.abc import Awaitable, Callable

import pynmea2
import pytest
import serial_asyncio

from brasidas import topics
from brasidas.codecs import ax3500
from brasidas.codecs.nmea import EpochAssembler, NmeaDecoder
from brasidas.codecs.telemetry_schema import Gps, GpsReader
from brasidas.config import PlatformConfig
from brasidas.messages import GpsFix
from platformd.app import PlatformDaemon
from platformd.sim.gps import RTK, NmeaGenerator
from platformd.sim.vehicle import VehicleModel
from tests.conftest import quiet_platform_config, wait_until


def metres_between(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    north = math.radians(lat2 - lat1) * 6_371_000.0
    east = math.radians(lon2 - lon1) * 6_371_000.0 * math.cos(math.radians(lat1))
    return math.hypot(north, east)


def test_every_sentence_parses_with_a_valid_checksum() -> None:
    clock = [0.0]
    vehicle = VehicleModel(latitude=-33.8568, longitude=151.2153, clock=lambda: clock[0])
    vehicle.set_command(1.0, 0.3)  # moving and turning: course and speed are filled in
    generator = NmeaGenerator(random.Random(4))
    start = dt.datetime(2026, 11, 23, 23, 59, 50, tzinfo=dt.UTC)  # across midnight
    stream = generator.banner()
    poses = []
    for second in range(600):
        clock[0] = second / 10
        pose = vehicle.pose()
        poses.append(pose)
        stream += generator.epoch(pose, start + dt.timedelta(seconds=second / 10))
    lines = stream.decode("ascii").split("\r\n")
    assert lines[-1] == ""
    assert lines[0].startswith("$GPTXT,")
    kinds = []
    for line in lines[:-1]:
        parsed = pynmea2.parse(line, check=True)  # raises on a bad checksum
        assert line.startswith("$GP")
        kinds.append(parsed.sentence_type)
    assert kinds[5:9] == ["RMC", "VTG", "GGA", "GSA"]
    decoder, assembler = NmeaDecoder(), EpochAssembler()
    fixes: list[GpsFix | None] = []
    for parsed in decoder.feed(stream):
        fixes += assembler.feed(parsed, 0.0)
    fixes += assembler.poll(1.0)
    assert decoder.dropped == {"checksum": 0, "malformed": 0, "unknown": 0, "noise": 0}
    assert len(fixes) == 600
    assert all(fix is not None for fix in fixes)
    errors = []
    for fix, pose in zip(fixes, poses, strict=True):
        assert fix is not None
        errors.append(metres_between(pose.latitude, pose.longitude, fix.latitude, fix.longitude))
        assert 8 <= (fix.satellites or 0) <= 10
        assert fix.hdop is not None
        assert 0.7 <= fix.hdop <= 1.4
    # The NEO-6M's error: metres (2.5 m CEP), wandering slowly, never a jump between epochs.
    assert 0.3 < sum(errors) / len(errors) < 8.0
    assert max(errors) < 9.0
    assert max(abs(a - b) for a, b in itertools.pairwise(errors)) < 0.2
    moving = fixes[-1]
    assert moving is not None
    assert moving.speed_mps is not None
    # Doppler speed: 0.1 m/s (the data sheet's velocity accuracy), whatever the position error.
    assert moving.speed_mps == pytest.approx(abs(poses[-1].speed_mps), abs=0.2)
    assert moving.time.startswith("2026-11-24T00:00:49.90")


def test_rtk_profile_decodes_to_centimetres_of_the_truth() -> None:
    """The RTK profile's fixes, through the real decoder, are a few centimetres from the pose:
    its 7 decimals of minutes carry them (5 would round to 1.9 cm)."""
    pose = VehicleModel(latitude=37.9415, longitude=23.6530, clock=lambda: 0.0).pose()
    generator = NmeaGenerator(random.Random(2), RTK)
    start = dt.datetime(2026, 11, 23, 12, tzinfo=dt.UTC)
    stream = b"".join(generator.epoch(pose, start + dt.timedelta(seconds=s)) for s in range(60))
    assert re.match(rb"\$GPRMC,[^,]*,A,\d{4}\.\d{7},N,\d{5}\.\d{7},E,", stream)
    decoder, assembler = NmeaDecoder(), EpochAssembler()
    fixes = [fix for parsed in decoder.feed(stream) for fix in assembler.feed(parsed, 0.0)]
    errors = [
        metres_between(pose.latitude, pose.longitude, fix.latitude, fix.longitude)
        for fix in fixes
        if fix is not None
    ]
    assert len(errors) >= 59
    assert decoder.dropped["malformed"] == 0
    assert max(errors) < 0.15
    assert sum(errors) / len(errors) < 0.06


async def test_real_reader_in_sim_platform(
    platform_factory: Callable[[PlatformConfig, bytes | None], Awaitable[PlatformDaemon]],
    fleet_key: bytes,
) -> None:
    config = quiet_platform_config(
        "sim.enabled=true",
        "gps.enabled=true",
        "gps.sim_rate_hz=10",
        "sim.latitude=44.0689",
        "sim.longitude=-121.3143",
    )
    daemon = await platform_factory(config, fleet_key)
    fixes: list[GpsFix] = []
    daemon.bus.subscribe(topics.GPS_FIX, fixes.append)
    assert daemon.ctx.sim.gps is not None
    assert daemon.ctx.gps_port == daemon.ctx.sim.gps.path
    await wait_until(lambda: len(fixes) >= 5, timeout=10.0)
    for fix in fixes:
        assert metres_between(44.0689, -121.3143, fix.latitude, fix.longitude) < 10.0
        assert fix.quality == 1
        assert fix.altitude_m is not None
    position = daemon.bus.last(topics.POSITION)
    assert position is not None
    assert abs(position.latitude - 44.0689) < 1e-4

    def gps() -> Gps:
        section = daemon.ctx.telemetry.build_one(Gps)
        assert isinstance(section, Gps)
        return section

    assert gps().fix is True
    assert gps().age_ms is not None

    def stats() -> GpsReader:
        return gps().stats or GpsReader()

    await wait_until(lambda: stats().fixes >= 5, 5.0)
    assert stats().connected is True
    assert stats().sentences >= 20
    assert stats().dropped == {}
    assert gps().lat == pytest.approx(44.0689, abs=1e-4)


async def test_simulate_gps_standalone_prints_a_pty_that_yields_nmea() -> None:
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "platformd",
        "--set",
        "gps.sim_rate_hz=5",
        "simulate",
        "gps",
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    fd = -1
    try:
        assert process.stdout is not None
        first = await asyncio.wait_for(process.stdout.readline(), 20.0)
        path = first.decode().strip()
        assert path.startswith("/dev/pts/")
        # Raw mode is the simulator's (termios belongs to the pty); setting it here would
        # flush the banner already waiting.
        fd = os.open(path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        received = b""
        loop = asyncio.get_running_loop()

        async def read_until_rmc() -> None:
            nonlocal received
            while b"$GPGGA" not in received:
                ready = loop.create_future()
                loop.add_reader(fd, ready.set_result, None)
                try:
                    await ready
                finally:
                    loop.remove_reader(fd)
                with contextlib.suppress(BlockingIOError):
                    received += os.read(fd, 4096)

        await asyncio.wait_for(read_until_rmc(), 10.0)
    finally:
        if fd >= 0:
            os.close(fd)
        with contextlib.suppress(ProcessLookupError):
            process.terminate()
        await asyncio.wait_for(process.wait(), 10.0)
    assert b"$GPTXT,01,01,02,u-blox ag - www.u-blox.com*50" in received
    lines = [line for line in received.split(b"\r\n") if line.startswith(b"$GPRMC")]
    assert lines
    assert pynmea2.parse(lines[0].decode(), check=True).status == "A"
    assert process.returncode == 0


async def test_sim_platform_reads_an_explicit_gps_port_instead(
    platform_factory: Callable[[PlatformConfig, bytes | None], Awaitable[PlatformDaemon]],
    fleet_key: bytes,
) -> None:
    master, slave = os.openpty()
    try:
        config = quiet_platform_config(
            "sim.enabled=true", "gps.enabled=true", f"gps.port={os.ttyname(slave)}"
        )
        daemon = await platform_factory(config, fleet_key)
        assert daemon.ctx.sim.gps is None
        assert daemon.ctx.gps_port == os.ttyname(slave)
        fixes: list[GpsFix] = []
        daemon.bus.subscribe(topics.GPS_FIX, fixes.append)

        def connected() -> bool:
            stats = daemon.bus.last(topics.GPS_STATS)
            return stats is not None and stats.connected

        await wait_until(connected)
        generator = NmeaGenerator(random.Random(1))
        pose = VehicleModel(latitude=-27.21, longitude=153.05).pose()
        when = dt.datetime(2026, 11, 23, 12, 0, 0, tzinfo=dt.UTC)
        os.write(
            master, generator.epoch(pose, when) + generator.epoch(pose, when.replace(second=1))
        )
        await wait_until(lambda: len(fixes) >= 1)
        assert metres_between(-27.21, 153.05, fixes[0].latitude, fixes[0].longitude) < 10.0
    finally:
        os.close(master)
        os.close(slave)


async def test_simulate_vehicle_standalone_moves_what_the_gps_reports() -> None:
    """``simulate vehicle``: the AX3500 and the NEO-6M on two ptys, one vehicle: commanding the
    controller forward makes the receiver report the speed and a position that moves."""
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "platformd", "--set", "gps.sim_rate_hz=10", "simulate", "vehicle",
        stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    try:
        assert process.stdout is not None
        motor = (await asyncio.wait_for(process.stdout.readline(), 15)).decode().strip()
        gps = (await asyncio.wait_for(process.stdout.readline(), 15)).decode().strip()
        assert motor.startswith("/dev/pts/")
        assert gps.startswith("/dev/pts/")
        assert motor != gps
        _, controller = await serial_asyncio.open_serial_connection(url=motor, baudrate=9600)
        receiver, receiver_writer = await serial_asyncio.open_serial_connection(
            url=gps, baudrate=9600
        )
        decoder, assembler = NmeaDecoder(), EpochAssembler()
        fixes: list[GpsFix] = []

        async def read_fixes() -> None:
            while True:
                data = await receiver.read(4096)
                for message in decoder.feed(data):
                    fixes.extend(f for f in assembler.feed(message, 0.0) if f is not None)

        async def drive() -> None:
            while True:  # full speed ahead, more often than the controller's 1 s watchdog
                controller.write(ax3500.motor(1, 127).encode())
                await asyncio.sleep(0.2)

        async with asyncio.TaskGroup() as group:
            tasks = [group.create_task(read_fixes()), group.create_task(drive())]
            try:
                await wait_until(lambda: len(fixes) >= 2, 10)
                first = fixes[-1]
                await wait_until(
                    lambda: (
                        (fixes[-1].speed_mps or 0.0) > 1.0
                        and metres_between(
                            first.latitude, first.longitude, fixes[-1].latitude, fixes[-1].longitude
                        )
                        > 1.0
                    ),
                    15,
                )
            finally:
                for task in tasks:
                    task.cancel()
        controller.close()
        receiver_writer.close()
    finally:
        process.terminate()
        await asyncio.wait_for(process.wait(), 10)
    assert process.returncode == 0
