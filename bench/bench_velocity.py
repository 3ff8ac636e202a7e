"""Velocity stream: ``$PVEL`` datagram to motor command, and the platform's CPU while teleoperated.

- ``pvel_to_motor_command_*``: datagram sent (a sender thread, its own socket) to the motion
  arbiter's ``MOTOR_COMMAND`` on an in-process platform, at 20 Hz and 500 Hz.
- ``pvel_to_serial_*``: datagram sent to the first byte of the resulting motor command, read
  at a pty master by a tap placed between the real driver and the AX3500 simulator
  (``bench/serial_tap.py``), at 20 Hz and 500 Hz; with the most commands ever unanswered on the
  line (latest wins: never more than one).
- ``platform_cpu_*``: a ``brasidas-platform --sim`` process (no video), idle and then
  teleoperated by a station daemon's 20 Hz sender: process CPU time over wall time.
"""

from __future__ import annotations

import asyncio
import socket
import sys
import time
from collections.abc import Callable
from typing import Any

from bench.serial_tap import Command, SerialTap
from bench.support import cpu_seconds, free_port, percentiles, start_platform
from brasidas import security, topics
from brasidas.codecs.jsonrpc import RpcError
from brasidas.codecs.pvel import PvelEncoder
from brasidas.config import PlatformConfig, StationConfig, load_config
from brasidas.messages import Velocity
from platformd.app import PlatformDaemon
from platformd.sim.ax3500 import Ax3500Simulator, SimOptions
from platformd.sim.vehicle import VehicleModel
from stationd.client import PlatformConnection
from stationd.daemon import StationDaemon

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
    target = ("127.0.0.1", daemon.ctx.velocity_port)
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


LEVELS = (0.2, 0.4, 0.6, 0.8)
"""Linear commands cycled through, each a different serial value, so every sentence changes it."""


async def _platform_with_tap(
    key: bytes, *overrides: str
) -> tuple[PlatformDaemon, SerialTap, Ax3500Simulator]:
    """An in-process platform whose driver talks to a simulated AX3500 through a tap
    (``overrides``: further config settings, e.g. the recorder's or the MAVLink endpoint's)."""
    simulator = Ax3500Simulator(SimOptions(), vehicle=VehicleModel())
    simulator.start()
    tap = SerialTap(simulator.path)
    tap.start()
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
            "audio.enabled=false",
            f"motor.port={tap.driver_path}",
            "motor.bytesize=8",  # a pty refuses 7E1; the bytes are the same
            "motor.parity=N",
            *overrides,
        ],
    )
    daemon = PlatformDaemon(config, key)
    await daemon.start()
    return daemon, tap, simulator


def _velocity_commands(tap: SerialTap) -> list[Command]:
    """Channel 1 (the common forward/reverse speed in mixed mode) commands, in order."""
    return [c for c in tap.commands if c.text[:2] in ("!A", "!a")]


async def _serial_latency(key: bytes, extra: tuple[str, ...] = ()) -> dict[str, Any]:
    """``$PVEL`` sent to the first byte of the resulting command at the pty master."""
    daemon, tap, simulator = await _platform_with_tap(key, *extra)
    figures: dict[str, Any] = {}
    try:
        deadline = time.monotonic() + 10
        while len(_velocity_commands(tap)) < 3:  # the driver is up and refreshing
            if time.monotonic() > deadline:
                raise RuntimeError("the motor driver never commanded the simulator")
            await asyncio.sleep(0.05)
        connection = PlatformConnection(
            daemon.config.platform.id, daemon.ctx.signaling_url, station_id="bench", fleet_key=key
        )
        await connection.open()
        try:
            if not await connection.call("set_manual_override", engaged=True):
                raise RuntimeError("manual override refused")
            encoder = PvelEncoder(key=connection.session_key, session_id=connection.session_id)
            target = ("127.0.0.1", daemon.ctx.velocity_port)
            mapping: dict[float, str] = {}
            for rate in (20.0, 500.0):
                tag = f"{int(rate)}hz"
                sent_at: dict[int, float] = {}
                values: dict[int, float] = {}

                def level(number: int, values: dict[int, float] = values) -> tuple[float, float]:
                    values[number] = LEVELS[number % len(LEVELS)]
                    return values[number], 0.0

                already = len(_velocity_commands(tap))
                tap.reset_counters()
                count = SAMPLES[rate] + WARMUP
                await asyncio.to_thread(_paced_sender, target, encoder, rate, count, sent_at, level)
                await asyncio.sleep(0.2)
                written = _velocity_commands(tap)[already:]
                samples = _match(sent_at, values, written, mapping, learn=rate == 20.0)
                result = percentiles(samples[WARMUP:] if rate == 20.0 else samples)
                figures[f"pvel_to_serial_{tag}_p50_ms"] = result["p50"]
                figures[f"pvel_to_serial_{tag}_p99_ms"] = result["p99"]
                figures[f"pvel_to_serial_{tag}_matched"] = len(samples)
                figures[f"serial_{tag}_velocity_commands_written"] = len(written)
                figures[f"serial_{tag}_max_unanswered_commands"] = tap.max_outstanding
                figures[f"pvel_{tag}_sent"] = count
        finally:
            await connection.close()
    finally:
        await daemon.stop()
        tap.close()
        simulator.close()
    return figures


def _match(
    sent_at: dict[int, float],
    values: dict[int, float],
    written: list[Command],
    mapping: dict[float, str],
    *,
    learn: bool,
) -> list[float]:
    """Latency of each serial command that carried a new value, from the sentence it carried.

    At 20 Hz every sentence changes the value and is written before the next one: the first
    changed command after a sentence is that sentence's, which also teaches the mapping from
    level to command text. At 500 Hz the driver coalesces (latest wins): each changed command
    is matched to the latest sentence sent before it that carries its value.
    """
    changes: list[Command] = []
    previous = ""
    for command in written:
        if command.text != previous:
            changes.append(command)
        previous = command.text
    samples: list[float] = []
    order = sorted(sent_at)
    if learn:
        index = 0
        for number in order:
            while index < len(changes) and changes[index].first_byte_at < sent_at[number]:
                index += 1
            if index == len(changes):
                break
            mapping.setdefault(values[number], changes[index].text)
            samples.append((changes[index].first_byte_at - sent_at[number]) * 1000)
            index += 1
        return samples
    by_text = {text: value for value, text in mapping.items()}
    cursor = 0
    latest: dict[float, float] = {}
    for command in changes:
        while cursor < len(order) and sent_at[order[cursor]] < command.first_byte_at:
            latest[values[order[cursor]]] = sent_at[order[cursor]]
            cursor += 1
        value = by_text.get(command.text)
        if value is not None and value in latest:
            samples.append((command.first_byte_at - latest[value]) * 1000)
    return samples


async def _platform_cpu(*, teleop_path_only: bool = False) -> dict[str, float]:
    """The platform process idle, then driven by a real station daemon's 20 Hz sender.

    By default a whole ``--sim`` platform (simulated controller, GPS and IMU in the process).
    ``teleop_path_only``: what a robot's own daemon spends on teleop: the AX3500 simulator runs
    in a process of its own (as the real controller is a device), sensors off.
    """
    signaling, velocity = free_port(), free_port(socket.SOCK_DGRAM)
    controller: asyncio.subprocess.Process | None = None
    overrides = [f"signaling.port={signaling}", f"velocity.port={velocity}", "navcam.enabled=false"]
    if teleop_path_only:
        controller = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "platformd", "simulate", "ax3500",
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.DEVNULL,
        )  # fmt: skip
        assert controller.stdout is not None
        pty = (await asyncio.wait_for(controller.stdout.readline(), 10)).decode().strip()
        overrides += [
            f"motor.port={pty}",
            "motor.bytesize=8",  # a pty refuses 7E1; the bytes are the same
            "motor.parity=N",
            "gps.enabled=false",
            "imu.enabled=false",
            "audio.enabled=false",
        ]
    process = await start_platform(*overrides, sim=not teleop_path_only)
    url = f"http://127.0.0.1:{signaling}"
    key = security.load_or_create_key(security.default_key_path())
    station = StationDaemon(load_config(StationConfig, None, ["station.api_port=0"]), key)
    await station.start()
    api = station.ctx.api
    try:
        deadline = time.monotonic() + 15
        while True:
            try:
                await api.call_local("connect", platform_id="brasidas-1", url=url)
                break
            except RpcError:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.1)
        await asyncio.sleep(1.0)  # start-up settles
        cpu0, wall0 = cpu_seconds(process.pid), time.monotonic()
        await asyncio.sleep(CPU_IDLE_S)
        cpu1, wall1 = cpu_seconds(process.pid), time.monotonic()
        answer = await api.call_local("movrd", platform_id="brasidas-1", engaged=True)
        if not answer.get("accepted"):
            raise RuntimeError(f"manual override refused: {answer}")
        before = (await api.call_local("teleop_status", platform_id="brasidas-1"))["platform"]
        cpu2, wall2 = cpu_seconds(process.pid), time.monotonic()
        while time.monotonic() - wall2 < CPU_TELEOP_S:
            # What the keyboard client does: a setpoint every 100 ms.
            await api.call_local("teleop_set", platform_id="brasidas-1", linear=0.3, angular=0.1)
            await asyncio.sleep(0.1)
        cpu3, wall3 = cpu_seconds(process.pid), time.monotonic()
        after = (await api.call_local("teleop_status", platform_id="brasidas-1"))["platform"]
    finally:
        await station.stop()
        for child in (process, controller):
            if child is None:
                continue
            child.terminate()
            try:
                await asyncio.wait_for(child.wait(), 5)
            except TimeoutError:
                child.kill()
                await child.wait()
    link0, link1 = before["velocity_link"], after["velocity_link"]
    return {
        "platform_cpu_idle_pct": round(100 * (cpu1 - cpu0) / (wall1 - wall0), 2),
        "platform_cpu_teleop_20hz_pct": round(100 * (cpu3 - cpu2) / (wall3 - wall2), 2),
        "station_sender_rate_hz": round(
            (link1["accepted"] - link0["accepted"]) / (wall3 - wall2), 1
        ),
        "teleop_dropped": int(sum(link1["dropped"].values()) - sum(link0["dropped"].values())),
    }


async def run() -> dict[str, Any]:
    figures: dict[str, Any] = {}
    for rate in (20.0, 500.0):
        tag = f"{int(rate)}hz"
        bus = await _motor_command_latency(rate)
        figures[f"pvel_to_motor_command_{tag}_p50_ms"] = bus["p50"]
        figures[f"pvel_to_motor_command_{tag}_p99_ms"] = bus["p99"]
        figures[f"pvel_to_motor_command_{tag}_lost"] = bus["lost"]
    key = security.load_or_create_key(security.default_key_path())
    figures.update(await _serial_latency(key))
    figures.update(await _platform_cpu())
    own = await _platform_cpu(teleop_path_only=True)
    figures["platform_cpu_teleop_path_only_idle_pct"] = own["platform_cpu_idle_pct"]
    figures["platform_cpu_teleop_path_only_20hz_pct"] = own["platform_cpu_teleop_20hz_pct"]
    figures["target"] = "20 Hz p99 < 1.5 ms to serial; <= 1 pending velocity at 500 Hz; CPU < 3 %"
    return figures
