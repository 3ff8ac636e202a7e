"""The simulated AX3500: the device sans-IO with explicit time, then on a real pty, standalone."""

from __future__ import annotations

import asyncio
import os
import sys
from pathlib import Path

import serial_asyncio
from conftest import wait_until
from hypothesis import given
from hypothesis import strategies as st

from brasidas.codecs import ax3500
from brasidas.config import MotorSection
from brasidas.topics import CONTROLLER_STATUS
from platformd.context import SerialDevice
from platformd.sim.ax3500 import Ax3500Device, Ax3500Simulator, SimOptions
from platformd.sim.vehicle import VehicleModel

# --------------------------------------------------------------------------- the device, sans-IO


def powered(options: SimOptions | None = None) -> Ax3500Device:
    device = Ax3500Device(options, record=True)
    assert device.power_up(0.0) == b"OK\r"
    return device


def test_echo_then_answers() -> None:
    device = powered()
    assert device.feed(b"!A40\r", 0.1) == b"!A40\r+\r"
    assert device.feed(b"!b2", 0.1) == b"!b2"  # echo char by char, answer at the CR
    assert device.feed(b"0\r", 0.1) == b"0\r+\r"
    assert device.channels == (0x40, -0x20)
    assert device.command == (0x40 / 127, -0x20 / 127)
    assert device.feed(b"?e\r", 0.1) == b"?e\r71\r6E\r"
    assert device.feed(b"?i\r", 0.1) == b"?i\r00\r00\r01\r"
    assert device.feed(b"!C\r!c\r", 0.1) == b"!C\r+\r!c\r+\r"
    assert device.outputs == {"C": False}


def test_refusals() -> None:
    device = powered()
    for bad in (b"!a5\r", b"!A80\r", b"!AZZ\r", b"?t\r", b"!X\r", b"hello\r", b"^1 2\r"):
        assert device.feed(bad, 0.1).endswith(b"-\r"), bad
    assert device.errors == 7
    assert device.channels == (0, 0)
    assert device.feed(b"A" * 40 + b"\r", 0.1).endswith(b"-\r")  # overlong
    device.fail_next = 1
    assert device.feed(b"!A10\r", 0.1) == b"!A10\r-\r"
    assert device.feed(b"!A10\r", 0.1) == b"!A10\r+\r"


def test_config_write_takes_effect_at_reset() -> None:
    device = powered(SimOptions(reset_time=0.5))
    assert device.feed(b"^01\r", 0.0) == b"^01\r01\r"
    assert device.feed(b"^01 00\r", 0.0) == b"^01 00\r+\r"
    assert device.mixed  # not before the reset
    assert device.feed(b"!A10\r", 0.0) == b"!A10\r+\r"
    assert device.feed(b"%rrrrrr\r!A10\r", 1.0) == b"%rrrrrr\r"  # the rest is lost
    assert device.channels == (0, 0)
    assert device.deadline() == 1.5
    assert device.feed(b"?e\r", 1.2) == b""  # restarting: deaf
    assert device.tick(1.4) == b""
    assert device.tick(1.5) == b"\rRoboteq v1.9b AX3500\rOK\r"
    assert not device.mixed
    assert device.resets == 1


def test_extra_line_after_a_config_read_is_an_option() -> None:
    device = powered(SimOptions(extra_config_line="00"))
    assert device.feed(b"^8A\r", 0.0) == b"^8A\r08\r00\r"


def test_watchdog_stops_the_motors_and_says_w_once_a_second() -> None:
    device = powered()
    device.feed(b"!A7F\r", 0.0)
    assert device.deadline() == 1.0
    assert device.tick(1.0) == b""  # not *more* than 1 s yet
    assert device.tick(1.01) == b"W"
    assert device.channels == (0, 0)
    assert device.deadline() == 2.01
    assert device.tick(1.5) == b""
    assert device.tick(2.01) == b"W"
    assert device.w_sent == 2
    assert device.watchdog_trips == 1
    device.feed(b"\r", 2.5)  # any character resets it
    assert device.tick(3.0) == b""
    assert device.deadline() == 3.5


def test_no_watchdog_in_plain_rs232_mode() -> None:
    options = SimOptions()
    options.parameters[ax3500.PARAM_INPUT_MODE] = ax3500.INPUT_MODE_RS232
    device = powered(options)
    assert device.deadline() is None
    assert device.tick(100.0) == b""


def test_rc_mode_streams_until_ten_carriage_returns() -> None:
    options = SimOptions(rc_line_period=0.1)
    options.parameters[ax3500.PARAM_INPUT_MODE] = ax3500.INPUT_MODE_RC
    device = Ax3500Device(options, record=True)
    assert device.power_up(0.0) == b""  # no OK in R/C mode
    assert device.tick(0.1).startswith(b":")
    assert device.feed(b"?e", 0.15) == b""  # no echo, no answer
    assert device.feed(b"\r" * 9, 0.2) == b""
    assert device.feed(b"\r", 0.2) == b"OK\r"
    assert device.mode == "rs232"
    assert device.feed(b"?v\r", 0.3) == b"?v\r00\r00\r"


def test_outputs_drive_the_vehicle_with_the_configured_left() -> None:
    seen: list[tuple[float, float]] = []
    device = Ax3500Device(SimOptions(left_turn="b"), on_output=lambda *c: seen.append(c))
    device.power_up(0.0)
    device.feed(b"!A7F\r!b7F\r", 0.0)
    assert seen[-1] == (1.0, 1.0)  # "b" turns left on this chassis
    assert device.query_values("v") == [0, 127]  # mixed: one side stopped, the other full


@given(st.lists(st.binary(max_size=24), max_size=12))
def test_any_input_keeps_the_device_sane(chunks: list[bytes]) -> None:
    device = powered(SimOptions(reset_time=0.0))
    now = 0.0
    for chunk in chunks:
        now += 0.01
        device.feed(chunk, now)
        device.tick(now)
        assert all(-127 <= level <= 127 for level in device.channels)
        assert device.mode in ("rs232", "resetting")


# --------------------------------------------------------------------------- on a pty


async def read_until(reader: asyncio.StreamReader, marker: bytes, timeout: float = 5) -> bytes:
    return await asyncio.wait_for(reader.readuntil(marker), timeout)


async def test_pty_round_trip_and_watchdog_at_line_speed(tmp_path: Path) -> None:
    vehicle = VehicleModel()
    sim = Ax3500Simulator(SimOptions(), vehicle=vehicle, link=str(tmp_path / "ax3500"), record=True)
    sim.start()
    try:
        assert os.readlink(sim.path) == sim.pty_name
        reader, writer = await serial_asyncio.open_serial_connection(url=sim.path, baudrate=9600)
        try:
            writer.write(b"!A40\r")
            assert await read_until(reader, b"+\r") == b"!A40\r+\r"
            assert vehicle.command[0] > 0.5
            writer.write(b"?m\r")
            assert await read_until(reader, b"?m\r") == b"?m\r"
            celsius = ax3500.heatsink_celsius(int((await read_until(reader, b"\r"))[:2], 16))
            assert 25.0 < celsius < 45.0  # warmer under load
            await read_until(reader, b"\r")
            # Silence for more than a second: the motors stop and the W comes.
            assert await read_until(reader, b"W", timeout=3) == b"W"
            assert sim.device.channels == (0, 0)
            assert vehicle.command == (0.0, 0.0)
        finally:
            writer.close()
        # Unplugged: the path is gone. Replugged: same path, a fresh controller.
        sim.unplug()
        assert not os.access(sim.path, os.F_OK)
        assert not sim.plugged
        sim.replug()
        reader, writer = await serial_asyncio.open_serial_connection(url=sim.path, baudrate=9600)
        try:
            writer.write(b"?a\r")
            assert await read_until(reader, b"?a\r") == b"?a\r"
        finally:
            writer.close()
    finally:
        sim.close()
    assert not os.access(tmp_path / "ax3500", os.F_OK)
    sim.close()  # idempotent


async def test_simulate_ax3500_standalone() -> None:
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "platformd",
        "simulate",
        "ax3500",
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        assert process.stdout is not None
        path = (await asyncio.wait_for(process.stdout.readline(), 15)).decode().strip()
        assert path.startswith("/dev/pts/")
        reader, writer = await serial_asyncio.open_serial_connection(url=path, baudrate=9600)
        try:
            writer.write(b"?e\r")
            assert await read_until(reader, b"?e\r") == b"?e\r"
            volts = ax3500.battery_volts(int((await read_until(reader, b"\r"))[:2], 16))
            assert 23.0 < volts < 26.0
            await read_until(reader, b"\r")  # internal volts
            writer.write(b"!a5\r")  # one digit: refused
            assert await read_until(reader, b"-\r") == b"!a5\r-\r"
        finally:
            writer.close()
    finally:
        process.terminate()
        await asyncio.wait_for(process.wait(), 10)
    assert process.returncode == 0


async def test_platform_sim_gives_the_driver_its_pty(platform_factory, fleet_key: bytes) -> None:  # type: ignore[no-untyped-def]
    from conftest import quiet_platform_config

    config = quiet_platform_config("motor.enabled=true", "sim.enabled=true")
    daemon = await platform_factory(config, fleet_key)
    sim = daemon.ctx.sim.ax3500
    assert sim is not None
    # The driver opens the simulator's pty 8N1; the configuration is left as it was given.
    assert daemon.ctx.motor_serial == SerialDevice(sim.path, 9600, 8, "N", 1)
    assert daemon.config == config
    assert config.motor.port == MotorSection().port
    await wait_until(lambda: getattr(daemon.bus.last(CONTROLLER_STATUS), "connected", False))
    # A --sim platform keeps no test record: it grew for as long as the platform ran.
    assert sim.device.received == []
    assert not sim.device.received_bytes
