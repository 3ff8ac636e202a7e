"""Velocity stream: ``$PVEL`` datagram to motor command, and the platform's CPU while teleoperated.

- ``pvel_to_motor_command_*``: datagram sent (a sender thread, its own socket) to the motion
  arbiter's ``MOTOR_COMMAND`` on an in-process platform, at 20 Hz and 500 Hz.
- ``pvel_to_serial_*``: datagram sent to the first byte of the resulting motor command at the
  AX3500 simulator's pty master, through the real driver (when the driver and simulator exist).
- ``platform_cpu_*``: a ``brasidas-platform --sim`` process (no video), idle and then
  teleoperated by a 20 Hz ``$PVEL`` stream: process CPU time over wall time.
"""

from __future__ import annotations

import asyncio
import importlib.util
import socket
import time
from collections.abc import Callable
from typing import Any

from bench.support import cpu_seconds, free_port, percentiles, start_platform
from brasidas import security, topics
from brasidas.codecs.pvel import PvelEncoder
from brasidas.config import PlatformConfig, load_config
from brasidas.messages import Velocity
from platformd.app import PlatformDaemon
from stationd.client import PlatformConnection

SAMPLES = {20.0: 200, 500.0: 2500}
WARMUP = 20
CPU_IDLE_S = 5.0
CPU_TELEOP_S = 10.0


def _paced_sender(
    target: tuple[str, int],
    encoder: PvelEncoder,
    rate_hz: float,
    count: int,
    sent_at: dict[int, float],
    velocity: Callable[[int], tuple[float, float]],
) -> None:
    """Runs in a thread: ``count`` datagrams at ``rate_hz``, each send time keyed by its count."""
    period = 1.0 / rate_hz
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        deadline = time.perf_counter()
        for _ in range(count):
            deadline += period
            while (remaining := deadline - time.perf_counter()) > 0:
                time.sleep(min(remaining, 0.0005) if remaining > 0.001 else 0)
            number = encoder.next_count
            datagram = encoder.encode(*velocity(number))
            sent_at[number] = time.perf_counter()
            sock.sendto(datagram, target)


def _distinct(number: int) -> tuple[float, float]:
    """A velocity that differs from the previous one, so every sentence changes the command."""
    return (0.1 + (number % 2) * 0.4, 0.0)


async def _in_process_platform(*overrides: str) -> tuple[PlatformDaemon, PlatformConnection]:
    key = security.load_or_create_key(security.default_key_path())
    config = load_config(
        PlatformConfig,
        None,
        [
            "signaling.port=0",
            "velocity.port=0",
            "beacon.enabled=false",
            "gps.enabled=false",
            "imu.enabled=false",
            "navcam.enabled=false",
            *overrides,
        ],
    )
    daemon = PlatformDaemon(config, key)
    await daemon.start()
    connection = PlatformConnection(
        config.platform.id, daemon.ctx.signaling_url, station_id="bench", fleet_key=key
    )
    await connection.open()
    if not await connection.call("set_manual_override", engaged=True):
        raise RuntimeError("manual override refused")
    return daemon, connection


async def _motor_command_latency(rate_hz: float) -> dict[str, float]:
    """Datagram sent to MOTOR_COMMAND published, in milliseconds."""
    daemon, connection = await _in_process_platform("motor.enabled=false")
    receiver = next(a for a in daemon.supervisor.actors if a.name == "velocity")
    arrived: dict[int, float] = {}

    def on_command(_velocity: Velocity) -> None:
        count = receiver.gate.last_count  # type: ignore[attr-defined]
        if count is not None and count not in arrived:
            arrived[count] = time.perf_counter()

    daemon.bus.subscribe(topics.MOTOR_COMMAND, on_command)
    sent_at: dict[int, float] = {}
    encoder = PvelEncoder(key=connection.session_key, session_id=connection.session_id)
    target = ("127.0.0.1", daemon.config.velocity.port)
    try:
        count = SAMPLES[rate_hz] + WARMUP
        await asyncio.to_thread(_paced_sender, target, encoder, rate_hz, count, sent_at, _distinct)
        await asyncio.sleep(0.1)
    finally:
        await connection.close()
        await daemon.stop()
    samples = [(arrived[n] - sent_at[n]) * 1000 for n in sorted(sent_at)[WARMUP:] if n in arrived]
    result = percentiles(samples)
    result["lost"] = count - WARMUP - len(samples)
    return result


async def _serial_latency(rate_hz: float) -> dict[str, Any]:
    """Datagram sent to the first byte of the motor command at the simulator's pty master."""
    from bench.velocity_serial import measure  # written against the AX3500 simulator's tap

    return await measure(rate_hz, SAMPLES[rate_hz], WARMUP, _in_process_platform, _paced_sender)


async def _platform_cpu() -> dict[str, float]:
    signaling, velocity = free_port(), free_port(socket.SOCK_DGRAM)
    process = await start_platform(
        f"signaling.port={signaling}", f"velocity.port={velocity}", "navcam.enabled=false"
    )
    url = f"http://127.0.0.1:{signaling}"
    try:
        key = security.load_or_create_key(security.default_key_path())
        connection = PlatformConnection("brasidas-1", url, station_id="bench", fleet_key=key)
        deadline = time.monotonic() + 15
        while True:
            try:
                await connection.open()
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.1)
                connection = PlatformConnection(
                    "brasidas-1", url, station_id="bench", fleet_key=key
                )
        try:
            await asyncio.sleep(1.0)  # start-up settles
            cpu0, wall0 = cpu_seconds(process.pid), time.monotonic()
            await asyncio.sleep(CPU_IDLE_S)
            cpu1, wall1 = cpu_seconds(process.pid), time.monotonic()
            if not await connection.call("set_manual_override", engaged=True):
                raise RuntimeError("manual override refused")
            encoder = PvelEncoder(key=connection.session_key, session_id=connection.session_id)
            sent_at: dict[int, float] = {}
            count = int(CPU_TELEOP_S * 20)
            cpu2, wall2 = cpu_seconds(process.pid), time.monotonic()
            await asyncio.to_thread(
                _paced_sender,
                ("127.0.0.1", velocity),
                encoder,
                20.0,
                count,
                sent_at,
                lambda n: (0.3, 0.1 * (n % 3)),
            )
            cpu3, wall3 = cpu_seconds(process.pid), time.monotonic()
            report = await connection.call("get_telemetry_report")
        finally:
            await connection.close()
    finally:
        process.terminate()
        try:
            await asyncio.wait_for(process.wait(), 5)
        except TimeoutError:
            process.kill()
            await process.wait()
    link = report.get("velocity_link", {})
    return {
        "platform_cpu_idle_pct": round(100 * (cpu1 - cpu0) / (wall1 - wall0), 2),
        "platform_cpu_teleop_20hz_pct": round(100 * (cpu3 - cpu2) / (wall3 - wall2), 2),
        "teleop_accepted": int(link.get("accepted", -1)),
        "teleop_dropped": int(sum(link.get("dropped", {}).values())),
    }


async def run() -> dict[str, Any]:
    figures: dict[str, Any] = {}
    for rate in (20.0, 500.0):
        tag = f"{int(rate)}hz"
        bus = await _motor_command_latency(rate)
        figures[f"pvel_to_motor_command_{tag}_p50_ms"] = bus["p50"]
        figures[f"pvel_to_motor_command_{tag}_p99_ms"] = bus["p99"]
        figures[f"pvel_to_motor_command_{tag}_lost"] = bus["lost"]
    if importlib.util.find_spec("bench.velocity_serial") is not None:
        for rate in (20.0, 500.0):
            serial = await _serial_latency(rate)
            tag = f"{int(rate)}hz"
            for name, value in serial.items():
                figures[f"pvel_to_serial_{tag}_{name}"] = value
    else:
        figures["pvel_to_serial"] = "not measured: no AX3500 driver and simulator yet"
    figures.update(await _platform_cpu())
    figures["target"] = "20 Hz p99 < 1.5 ms to serial; <= 1 pending velocity at 500 Hz; CPU < 3 %"
    return figures
