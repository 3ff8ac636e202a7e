"""Sensors: GPS sentence-to-fix latency, and platform CPU with GPS 10 Hz, IMU 100 Hz, telemetry 5 Hz.

Latency: an in-process GPS reader on a real pty. Each sentence of an epoch (RMC VTG GGA GSA
from the simulator's generator) is written except its last byte; after a pause the last byte
is written and its time noted. The fix is timed from the last byte written before the
``GPS_FIX`` callback ran (it runs in the publishing call): the reader publishes as soon as the
epoch holds what its cycle brings (RMC and GGA), so that byte is GGA's, not the epoch's last.

CPU: a ``brasidas-platform --sim`` child process (GPS simulator at 10 Hz on its pty and the
real reader, the emulated MPU-6050 sampled at 100 Hz and fused, the simulated motor
controller when present), a station session pulling telemetry at 5 Hz for 10 s, no media.
CPU of the child: the median of five 2 s windows from schedstat (ns; their spread shows a
shared machine's noise) and bench.support's utime+stime over the 10 s; the same with GPS and
IMU disabled as a baseline, and with the GPS simulator in a process of its own (``simulate
gps``, read through ``gps.port``) so that only the reader's cost is the platform's.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import os
import statistics
import sys
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench.support import connect_to_platform, cpu_seconds, free_port, percentiles, start_platform
from brasidas import topics
from brasidas.bus import Bus
from brasidas.codecs.telemetry import TelemetryDecoder
from brasidas.codecs.telemetry_schema import Attitude, Gps, snapshot_from_json
from brasidas.config import GpsSection
from brasidas.messages import GpsFix
from platformd.gps import GpsReader
from platformd.sim.gps import NmeaGenerator
from platformd.sim.vehicle import VehicleModel

EPOCHS = 250
PAUSE_S = 0.01
WINDOW_S = 10.0
WINDOWS = 5
MEDIA_OFF = ("navcam.enabled=false", "audio.enabled=false", "payload_camera.enabled=false")


async def _write_all(fd: int, data: bytes) -> None:
    loop = asyncio.get_running_loop()
    view = memoryview(data)
    while view:
        try:
            view = view[os.write(fd, view) :]
        except BlockingIOError:
            ready = loop.create_future()
            loop.add_writer(fd, ready.set_result, None)
            try:
                await ready
            finally:
                loop.remove_writer(fd)


async def gps_latency() -> dict[str, Any]:
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    bus = Bus()
    reader = GpsReader(bus, GpsSection(port=os.ttyname(slave)))
    published: list[float] = []
    arrived = asyncio.Event()

    def on_fix(_fix: GpsFix) -> None:
        published.append(time.perf_counter())  # in the publishing call: no loop hop
        arrived.set()

    bus.subscribe(topics.GPS_FIX, on_fix)
    generator = NmeaGenerator()
    vehicle = VehicleModel()
    start = dt.datetime.now(dt.UTC).replace(microsecond=0)
    samples: list[float] = []
    task = asyncio.create_task(reader.run(), name="bench:gps")
    try:
        await _until(lambda: reader.connected)
        for k in range(EPOCHS + 1):
            epoch = generator.epoch(vehicle.pose(), start + dt.timedelta(seconds=k / 10))
            arrived.clear()
            sent: list[float] = []
            for line in epoch.splitlines(keepends=True):
                await _write_all(master, line[:-1])
                await asyncio.sleep(PAUSE_S)  # the reader has consumed all but the last byte
                sent.append(time.perf_counter())
                await _write_all(master, line[-1:])
            try:
                await asyncio.wait_for(arrived.wait(), 2.0)
            except TimeoutError:
                continue
            if k > 1:  # the first epochs teach the reader its cycle (then 0.3 s quiet)
                before = [t for t in sent if t <= published[-1]]
                if before:
                    samples.append((published[-1] - before[-1]) * 1000)
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        os.close(master)
        os.close(slave)
    figures = {f"gps_last_byte_to_fix_ms_{k}": v for k, v in percentiles(samples).items()}
    figures["gps_latency_epochs"] = len(samples)
    figures["gps_dropped"] = sum(reader.decoder.dropped.values())
    return figures


def _cpu_ns(pid: int) -> int:
    """CPU time of every thread of ``pid`` in ns (schedstat: finer than utime+stime's ticks)."""
    total = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):  # a thread that just ended
            total += int((task / "schedstat").read_text().split()[0])
    return total


async def _until(predicate: Callable[[], bool], timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError("condition not met")
        await asyncio.sleep(0.01)


class _Counter(asyncio.DatagramProtocol):
    def __init__(self, decoder: TelemetryDecoder) -> None:
        self.decoder = decoder
        self.accepted = 0

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.accepted += len(self.decoder.feed(data))


async def platform_cpu(*overrides: str) -> dict[str, Any]:
    port = free_port()
    process = await start_platform(
        f"signaling.port={port}", "beacon.enabled=false", *MEDIA_OFF, *overrides
    )
    try:
        connection = await connect_to_platform(port)
        loop = asyncio.get_running_loop()
        counter = _Counter(TelemetryDecoder("brasidas-1", connection.session_key))
        transport, _ = await loop.create_datagram_endpoint(
            lambda: counter, local_addr=("127.0.0.1", 0)
        )
        try:
            udp_port = transport.get_extra_info("sockname")[1]
            await connection.call("request_telemetry", port=udp_port, rate_hz=5.0)
            await asyncio.sleep(2.0)  # start-up settles
            # Several windows: a shared machine's noise shows as their spread.
            windows: list[float] = []
            received0, start = counter.accepted, time.monotonic()
            ticks0 = cpu_seconds(process.pid)
            for _ in range(WINDOWS):
                cpu0, wall0 = _cpu_ns(process.pid), time.monotonic()
                await asyncio.sleep(WINDOW_S / WINDOWS)
                used = (_cpu_ns(process.pid) - cpu0) / 1e9
                windows.append(100 * used / (time.monotonic() - wall0))
            wall = time.monotonic() - start
            ticks_pct = 100 * (cpu_seconds(process.pid) - ticks0) / wall
            received = counter.accepted - received0
            report = await connection.call("get_telemetry_report")
        finally:
            transport.close()
            await connection.close()
    finally:
        if process.returncode is None:
            process.terminate()
            try:
                await asyncio.wait_for(process.wait(), 5)
            except TimeoutError:
                process.kill()
                await process.wait()
    snapshot = snapshot_from_json(report)
    gps, attitude = snapshot.get(Gps), snapshot.get(Attitude)
    imu = attitude.imu if attitude is not None else None
    return {
        "cpu_pct": round(statistics.median(windows), 2),
        "cpu_pct_ticks": round(ticks_pct, 2),
        "cpu_pct_windows": [round(value, 1) for value in windows],
        "telemetry_hz": round(received / wall, 2),
        "gps_fix": gps.fix if gps is not None else None,
        "gps_fixes": gps.stats.fixes if gps is not None and gps.stats is not None else None,
        "imu_samples": imu.samples if imu is not None else None,
    }


async def run() -> dict[str, Any]:
    figures = await gps_latency()
    full = await platform_cpu("gps.sim_rate_hz=10", "imu.rate_hz=100", "telemetry.rate_hz=5")
    base = await platform_cpu("gps.enabled=false", "imu.enabled=false", "telemetry.rate_hz=5")
    # The GPS simulator in its own process (as a receiver would be): the platform's share is
    # the reader's alone.
    receiver = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "platformd",
        "--set",
        "gps.sim_rate_hz=10",
        "simulate",
        "gps",
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.DEVNULL,
    )
    try:
        assert receiver.stdout is not None
        pty = (await asyncio.wait_for(receiver.stdout.readline(), 15)).decode().strip()
        external = await platform_cpu(f"gps.port={pty}", "imu.rate_hz=100", "telemetry.rate_hz=5")
    finally:
        receiver.terminate()
        await receiver.wait()
    figures.update(
        {
            "platform_cpu_pct_one_core": full["cpu_pct"],
            "platform_cpu_pct_windows_2s": full["cpu_pct_windows"],
            "platform_cpu_pct_utime_stime_10s": full["cpu_pct_ticks"],
            "platform_cpu_pct_without_gps_imu": base["cpu_pct"],
            "platform_cpu_pct_gps_simulator_outside": external["cpu_pct"],
            "gps_fix_with_simulator_outside": external["gps_fix"],
            "telemetry_rate_measured_hz": full["telemetry_hz"],
            "gps_fix_in_telemetry": full["gps_fix"],
            "gps_fixes_at_end": full["gps_fixes"],
            "imu_samples_at_end": full["imu_samples"],
            "cpu_window_s": WINDOW_S,
            "target": "platform CPU < 5 % of one core (GPS 10 Hz, IMU 100 Hz, telemetry 5 Hz)",
        }
    )
    return figures
