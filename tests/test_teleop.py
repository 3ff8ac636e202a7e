"""Teleop from the station: joystick codec and reader, keyboard, the $PVEL sender end to end."""

from __future__ import annotations

import asyncio
import functools
import os
import sys
import tty
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from pathlib import Path

import pytest
from conftest import quiet_platform_config, wait_until
from hypothesis import given
from hypothesis import strategies as st

from brasidas import topics
from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.codecs.telemetry_schema import Motion, VelocityLink
from brasidas.config import JoystickSection, StationConfig, load_config
from brasidas.messages import Velocity
from platformd.app import PlatformDaemon
from stationd.client import PlatformConnection
from stationd.daemon import StationDaemon
from stationd.drive import DriveCommand, Key, KeyDecoder, status_line
from stationd.joystick import (
    AXIS_LEFT_X,
    AXIS_LEFT_Y,
    BUTTON_A,
    BUTTON_LB,
    JS_EVENT_AXIS,
    JS_EVENT_BUTTON,
    JS_EVENT_INIT,
    Gamepad,
    JoystickReader,
    JsEvent,
    JsEventDecoder,
    gamepad_velocity,
    shape,
)
from stationd.teleop import Teleop

Factory = Callable[..., Awaitable[PlatformDaemon]]
STOP = Velocity(0.0, 0.0)


def axis(number: int, value: int, init: bool = False) -> bytes:
    return JsEvent(0, value, JS_EVENT_AXIS | (JS_EVENT_INIT if init else 0), number).encode()


def button(number: int, pressed: bool, init: bool = False) -> bytes:
    kind = JS_EVENT_BUTTON | (JS_EVENT_INIT if init else 0)
    return JsEvent(0, int(pressed), kind, number).encode()


# --------------------------------------------------------------------------- joystick, sans-IO


def test_js_event_is_the_kernel_record() -> None:
    # struct js_event { __u32 time; __s16 value; __u8 type; __u8 number; } on a little-endian host
    raw = JsEvent(1000, -32767, JS_EVENT_AXIS, 1).encode()
    assert len(raw) == 8
    if sys.byteorder == "little":
        assert raw == bytes.fromhex("e803000001800201")


events = st.builds(
    JsEvent,
    st.integers(0, 2**32 - 1),
    st.integers(-32768, 32767),
    st.sampled_from([1, 2, 0x81, 0x82]),
    st.integers(0, 255),
)


@given(batch=st.lists(events, max_size=20), cuts=st.lists(st.integers(0, 200), max_size=6))
def test_decoder_reassembles_records_split_anywhere(batch: list[JsEvent], cuts: list[int]) -> None:
    data = b"".join(event.encode() for event in batch)
    decoder = JsEventDecoder()
    decoded: list[JsEvent] = []
    start = 0
    for cut in sorted(c % (len(data) + 1) for c in cuts):
        decoded += decoder.feed(data[start:cut])
        start = cut
    decoded += decoder.feed(data[start:])
    assert decoded == batch


def test_decoder_skips_unknown_record_types() -> None:
    decoder = JsEventDecoder()
    assert decoder.feed(JsEvent(0, 5, 0x04, 0).encode() + axis(0, 7)) == [
        JsEvent(0, 7, JS_EVENT_AXIS, 0)
    ]
    assert decoder.unknown == 1


def test_enable_button_deadzone_scaling_and_inversion() -> None:
    config = JoystickSection(deadzone=0.1, linear_scale=0.5, angular_scale=1.0)
    pad = Gamepad()
    decoder = JsEventDecoder()
    init = axis(AXIS_LEFT_X, 0, True) + axis(AXIS_LEFT_Y, 0, True) + button(BUTTON_LB, False, True)
    for event in decoder.feed(init + axis(AXIS_LEFT_Y, -32767) + axis(AXIS_LEFT_X, -32767)):
        pad.apply(event)
    assert gamepad_velocity(pad, config) is None  # stick pushed, enable not held: nothing
    for event in decoder.feed(button(BUTTON_LB, True)):
        pad.apply(event)
    # Full up = forward at the configured scale; full left = turn left (positive angular z).
    assert gamepad_velocity(pad, config) == Velocity(0.5, 1.0)
    for event in decoder.feed(axis(AXIS_LEFT_Y, 3000) + axis(AXIS_LEFT_X, 32767)):
        pad.apply(event)
    assert gamepad_velocity(pad, config) == Velocity(0.0, -1.0)  # 3000 is inside the deadzone
    for event in decoder.feed(button(BUTTON_A, True) + button(BUTTON_LB, False)):
        pad.apply(event)
    assert gamepad_velocity(pad, config) is None


def test_deadzone_shape_is_continuous() -> None:
    assert shape(0.1, 0.1) == 0.0
    assert shape(0.55, 0.1) == pytest.approx(0.5)
    assert shape(-1.0, 0.1) == -1.0
    assert shape(0.10001, 0.1) == pytest.approx(0.0, abs=1e-4)


# --------------------------------------------------------------------------- joystick over a pty


def open_pty() -> tuple[int, int]:
    master, slave = os.openpty()
    tty.setraw(slave)
    return master, slave


def relink(link: Path, target: str) -> None:
    temporary = link.with_suffix(".new")
    temporary.symlink_to(target)
    os.replace(temporary, link)


@pytest.fixture
def joystick_device(tmp_path: Path) -> Iterator[tuple[Path, list[int]]]:
    """A stable device path (a symlink) to a pty; the list holds [master, slave]."""
    link = tmp_path / "js0"
    master, slave = open_pty()
    link.symlink_to(os.ttyname(slave))
    fds = [master, slave]
    yield link, fds
    for fd in fds:
        try:
            os.close(fd)
        except OSError:
            pass


async def test_joystick_reader_reads_events_and_survives_unplugging(
    joystick_device: tuple[Path, list[int]],
) -> None:
    link, fds = joystick_device
    reader = JoystickReader(Bus(), JoystickSection(device=str(link)))
    supervisor = Supervisor()
    supervisor.start(reader)
    try:
        await asyncio.wait_for(reader.connected.wait(), 5)
        os.write(fds[0], axis(AXIS_LEFT_Y, 0, True) + button(BUTTON_LB, False, True))
        os.write(fds[0], button(BUTTON_LB, True) + axis(AXIS_LEFT_Y, -32767)[:5])
        await wait_until(lambda: reader.velocity() == STOP)  # enabled, stick not yet moved
        os.write(fds[0], axis(AXIS_LEFT_Y, -32767)[5:])  # the rest of the split record
        await wait_until(lambda: reader.velocity() == Velocity(1.0, 0.0))

        # Unplugged while held: the stick and the enable button are forgotten at once.
        for fd in fds:
            os.close(fd)
        fds.clear()
        await wait_until(lambda: not reader.connected.is_set())
        assert reader.velocity() is None
        assert reader.disconnects == 1

        master, slave = open_pty()
        fds += [master, slave]
        relink(link, os.ttyname(slave))
        await asyncio.wait_for(reader.connected.wait(), 5)
        assert reader.velocity() is None
        os.write(master, button(BUTTON_LB, True) + axis(AXIS_LEFT_X, 32767))
        await wait_until(lambda: reader.velocity() == Velocity(0.0, -1.0))
    finally:
        await supervisor.stop()


# --------------------------------------------------------------------------- keyboard, sans-IO


def test_key_decoder_handles_split_escape_sequences() -> None:
    decoder = KeyDecoder()
    assert decoder.feed(b"wW\x1b[") == [Key.FORWARD, Key.FORWARD]
    assert decoder.feed(b"D") == [Key.LEFT]
    assert decoder.feed(b"\x1bOC s\x1b") == [Key.RIGHT, Key.STOP, Key.BACK]
    assert decoder.feed(b"x") == []  # a lone ESC and an unused key are ignored
    assert decoder.feed(b"\x1b[Bq\x03") == [Key.BACK, Key.QUIT, Key.QUIT]


def test_drive_command_steps_and_clamps() -> None:
    command = DriveCommand(step=0.3)
    for _ in range(5):
        command.apply(Key.FORWARD)
    command.apply(Key.LEFT)
    assert (command.linear, command.angular) == (1.0, 0.3)
    command.apply(Key.RIGHT)
    command.apply(Key.RIGHT)
    assert command.angular == -0.3
    command.apply(Key.STOP)
    assert (command.linear, command.angular) == (0.0, 0.0)
    line = status_line("r1", command, None, None)
    assert line == "r1  command +0.00 +0.00"


# --------------------------------------------------------------------------- end to end


@pytest.fixture
async def station_factory(
    fleet_key: bytes,
) -> AsyncIterator[Callable[..., Awaitable[StationDaemon]]]:
    started: list[StationDaemon] = []

    async def start(*overrides: str, key: bytes | None = fleet_key) -> StationDaemon:
        config = load_config(
            StationConfig,
            None,
            ["station.api_port=0", "station.connect_timeout=2", *overrides],
        )
        daemon = StationDaemon(config, key)
        started.append(daemon)
        await daemon.start()
        return daemon

    yield start
    for daemon in started:
        await daemon.stop()


def teleop_of(station: StationDaemon) -> Teleop:
    return next(a for a in station.supervisor.actors if isinstance(a, Teleop))


def motors(platform: PlatformDaemon) -> Callable[[], Velocity | None]:
    log: list[Velocity] = []
    platform.bus.subscribe(topics.MOTOR_COMMAND, log.append)
    return lambda: log[-1] if log else None


async def test_station_streams_only_while_it_holds_the_override(
    platform_factory: Factory,
    station_factory: Callable[..., Awaitable[StationDaemon]],
    fleet_key: bytes,
) -> None:
    platform = await platform_factory(quiet_platform_config(), fleet_key)
    station = await station_factory("teleop.drive_timeout=0.2")
    last_motor = motors(platform)
    link = functools.partial(platform.ctx.telemetry.build_one, VelocityLink)
    api = station.ctx.api
    await api.call_local("connect", platform_id="brasidas-1", url=platform.ctx.signaling_url)
    teleop = teleop_of(station)
    await wait_until(lambda: "brasidas-1" in teleop.senders)
    sender = teleop.senders["brasidas-1"]
    await wait_until(lambda: sender.ticks >= 3)
    assert sender.sent == 0
    assert link().accepted == 0  # not engaged: nothing on the wire

    answer = await api.call_local("movrd", platform_id="brasidas-1", engaged=True)
    assert answer["accepted"] is True
    # Zeros are streamed too: the platform keeps accepting, the deadman never trips.
    await wait_until(lambda: link().accepted >= 10)
    assert last_motor() == STOP
    assert platform.ctx.telemetry.build_one(Motion).deadman is False

    status = await api.call_local("teleop_set", platform_id="brasidas-1", linear=0.5, angular=-0.2)
    assert status["engaged"] is True
    assert status["target"][1] == platform.ctx.velocity_port
    await wait_until(lambda: last_motor() == Velocity(0.5, -0.2))

    # The drive client goes quiet: zeros, still streamed (not the platform's deadman).
    await wait_until(lambda: last_motor() == STOP)
    accepted = link().accepted
    await wait_until(lambda: link().accepted >= accepted + 5)
    assert platform.ctx.telemetry.build_one(Motion).deadman is False
    assert link().dropped["bad_tag"] == 0
    assert link().dropped["not_holder"] == 0

    report = await api.call_local("teleop_status", platform_id="brasidas-1")
    assert report["platform"]["mode"] == "teleop"
    assert report["source"] == "drive timeout"

    with pytest.raises(Exception, match=r"\[-1, 1\]"):
        await api.call_local("teleop_set", platform_id="brasidas-1", linear=1.5, angular=0.0)

    assert (await api.call_local("movrd", platform_id="brasidas-1", engaged=False))["accepted"]
    await wait_until(lambda: sender.source == "idle")
    sent = sender.sent
    ticks = sender.ticks
    await wait_until(lambda: sender.ticks >= ticks + 3)
    assert sender.sent == sent


async def test_another_station_is_not_told_it_holds_the_override(
    platform_factory: Factory,
    station_factory: Callable[..., Awaitable[StationDaemon]],
    fleet_key: bytes,
) -> None:
    platform = await platform_factory(quiet_platform_config(), fleet_key)
    station = await station_factory()
    api = station.ctx.api
    await api.call_local("connect", platform_id="brasidas-1", url=platform.ctx.signaling_url)
    assert (await api.call_local("movrd", platform_id="brasidas-1", engaged=True))["accepted"]
    other = PlatformConnection(
        "brasidas-1", platform.ctx.signaling_url, station_id="station-2", fleet_key=fleet_key
    )
    await other.open()
    try:
        beat = await other.call("heartbeat")
        assert beat["manual_override"] is False
        assert beat["override_engaged"] is True
        mine = station.ctx.connections["brasidas-1"]
        assert (await mine.call("heartbeat"))["manual_override"] is True
    finally:
        await other.close()


async def test_joystick_drives_the_platform_this_station_engaged(
    platform_factory: Factory,
    station_factory: Callable[..., Awaitable[StationDaemon]],
    fleet_key: bytes,
    joystick_device: tuple[Path, list[int]],
) -> None:
    link, fds = joystick_device
    platform = await platform_factory(quiet_platform_config(), fleet_key)
    station = await station_factory(f"joystick.device={link}")
    last_motor = motors(platform)
    api = station.ctx.api
    await api.call_local("connect", platform_id="brasidas-1", url=platform.ctx.signaling_url)
    teleop = teleop_of(station)
    assert teleop.joystick is not None
    await asyncio.wait_for(teleop.joystick.connected.wait(), 5)
    os.write(fds[0], button(BUTTON_LB, False, True) + axis(AXIS_LEFT_Y, -16384))
    assert (await api.call_local("movrd", platform_id="brasidas-1", engaged=True))["accepted"]
    await wait_until(lambda: teleop.last_engaged == "brasidas-1")
    await wait_until(lambda: platform.ctx.telemetry.build_one(VelocityLink).accepted >= 3)
    assert last_motor() == STOP  # stick deflected, enable not held

    os.write(fds[0], button(BUTTON_LB, True))
    half_up = -shape(-16384 / 32767, 0.1)  # stick up reads negative; forward is positive
    await wait_until(
        lambda: (
            (m := last_motor()) is not None and abs(m.linear - half_up) < 1e-5 and m.angular == 0
        )
    )
    status = await api.call_local("teleop_status", platform_id="brasidas-1")
    assert status["source"] == "joystick"
    assert status["joystick"]["connected"] is True

    os.write(fds[0], button(BUTTON_LB, False))  # let go of the enable button: stop
    await wait_until(lambda: last_motor() == STOP)


# --------------------------------------------------------------------------- the drive command


async def test_drive_command_through_a_pty(
    platform_factory: Factory,
    station_factory: Callable[..., Awaitable[StationDaemon]],
    fleet_key: bytes,
) -> None:
    platform = await platform_factory(quiet_platform_config(), fleet_key)
    station = await station_factory()
    last_motor = motors(platform)
    master, slave = os.openpty()
    output = bytearray()
    loop = asyncio.get_running_loop()

    def drain() -> None:
        try:
            output.extend(os.read(master, 4096))
        except OSError:
            loop.remove_reader(master)

    loop.add_reader(master, drain)
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "stationd",
        "drive",
        "brasidas-1",
        "--url",
        platform.ctx.signaling_url,
        "--set",
        f"station.api_port={station.api_port}",
        stdin=slave,
        stdout=slave,
        stderr=slave,
    )
    os.close(slave)
    try:
        await wait_until(lambda: b"platform teleop" in output, timeout=15)
        assert last_motor() == STOP
        os.write(master, b"www")
        await wait_until(lambda: last_motor() == Velocity(0.3, 0.0))
        os.write(master, b"\x1b[D")  # left arrow
        await wait_until(lambda: last_motor() == Velocity(0.3, 0.1))
        await wait_until(lambda: b"motors +0.30 +0.10" in output)  # the platform's own report
        os.write(master, b" ")
        await wait_until(lambda: last_motor() == STOP)
        os.write(master, b"q")
        assert await asyncio.wait_for(process.wait(), 10) == 0
        await wait_until(lambda: b"override released" in output)
        assert not platform.bus.last(topics.OVERRIDE_STATE).engaged
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()
        loop.remove_reader(master)
        os.close(master)
