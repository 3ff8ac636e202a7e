"""The motor controller driver against the real simulator on a pty, then end to end in --sim."""

from __future__ import annotations

import asyncio
import os
import socket
import sys
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from pathlib import Path

import pytest
from conftest import hang_serial_opens, quiet_platform_config, record_loop_gaps, wait_until
from gpiod.line import Value

from brasidas import topics
from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.clock import ManualClock
from brasidas.codecs import ax3500, pvel
from brasidas.codecs.commands import BATTERY_MONITOR, MAIN_LIGHTS, POSITIONAL_LIGHTS
from brasidas.codecs.jsonrpc import Dispatcher
from brasidas.codecs.telemetry_schema import Motor
from brasidas.config import PlatformConfig, StationConfig, load_config
from brasidas.messages import ControllerStatus, LightsState, Velocity
from platformd import motor
from platformd.app import PlatformDaemon
from platformd.context import PlatformContext
from platformd.motor import MotorController
from platformd.motor import controller as motor_controller
from platformd.sim import SimulatedDevices
from platformd.sim.ax3500 import Ax3500Simulator, SimOptions
from platformd.sim.gpio import SimulatedGpio
from platformd.sim.vehicle import VehicleModel
from stationd.client import PlatformConnection
from stationd.daemon import StationDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]


@asynccontextmanager
async def driven(
    tmp_path: Path,
    *overrides: str,
    options: SimOptions | None = None,
    clock: ManualClock | None = None,
    gpio: SimulatedGpio | None = None,
) -> AsyncIterator[tuple[PlatformContext, Ax3500Simulator]]:
    """A simulator behind a stable link and the driver on it, in a bare platform context;
    with ``clock``, both keep time by it (the serial line stays real); ``gpio`` stands in
    for libgpiod's chips."""
    sim = Ax3500Simulator(
        options or SimOptions(), link=str(tmp_path / "ax3500"), clock=clock, record=True
    )
    sim.start()
    config = quiet_platform_config("motor.enabled=true", f"motor.port={sim.path}", *overrides)
    ctx = PlatformContext(
        config=config,
        bus=Bus(),
        supervisor=Supervisor(),
        rpc=Dispatcher(),
        fleet_key=None,
        sim=SimulatedDevices(gpio=gpio),
    )
    await motor.async_setup(ctx, clock=clock)
    try:
        yield ctx, sim
    finally:
        await ctx.supervisor.stop()
        sim.close()


def driver_of(ctx: PlatformContext) -> MotorController:
    actor = next(a for a in ctx.supervisor.actors if a.name == "motor")
    assert isinstance(actor, MotorController)
    return actor


def status(ctx: PlatformContext) -> ControllerStatus | None:
    return ctx.bus.last(topics.CONTROLLER_STATUS)


async def connected(ctx: PlatformContext, timeout: float = 10) -> None:
    await wait_until(lambda: (s := status(ctx)) is not None and s.connected, timeout)


def since(sim: Ax3500Simulator, mark: int) -> list[str]:
    return sim.device.received[mark:]


# --------------------------------------------------------------------------- the serial line


async def test_exact_bytes_for_velocities(tmp_path: Path) -> None:
    # 7E1 from the defaults: the driver falls back to 8N1 because the port is a pty.
    async with driven(tmp_path) as (ctx, sim):
        await connected(ctx)
        mark = len(sim.device.received_bytes)
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.5, -0.25))
        await wait_until(lambda: sim.device.channels == (0x40, -0x20))
        assert bytes(sim.device.received_bytes[mark:]).startswith(b"!A40\r!b20\r")
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(-1.0, 1.0))
        await wait_until(lambda: sim.device.channels == (-0x7F, 0x7F))
        assert b"!a7F\r!B7F\r" in sim.device.received_bytes
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.01, 0.0))
        await wait_until(lambda: sim.device.channels == (1, 0))
        assert "!A01" in sim.device.received  # two digits, always


async def test_scaling_inversion_and_limits_from_config(tmp_path: Path) -> None:
    overrides = ("motor.linear_scale=0.5", "motor.angular_limit=0.25", "motor.invert_angular=true")
    async with driven(tmp_path, *overrides, options=SimOptions(left_turn="b")) as (ctx, sim):
        await connected(ctx)
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(1.0, 1.0))
        await wait_until(lambda: sim.device.channels == (64, -32))
        assert sim.device.command[1] > 0  # on this chassis "b" turns left: still a left turn


async def test_refused_command_is_resent_once_then_reported(tmp_path: Path) -> None:
    async with driven(tmp_path, "motor.refresh_hz=2") as (ctx, sim):
        await connected(ctx)
        driver = driver_of(ctx)
        sim.device.fail_next = 1
        mark = len(sim.device.received)
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.25, 0.0))
        await wait_until(lambda: sim.device.channels == (32, 0))
        assert since(sim, mark)[:2] == ["!A20", "!A20"]
        assert driver.counters["rejected"] == 1
        assert driver.counters["resent"] == 1
        # Refused twice: reported, the driver carries on, and the refresh gets it through.
        sim.device.fail_next = 2
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.5, 0.0))
        await wait_until(lambda: driver.counters["rejected"] == 3)
        await wait_until(lambda: sim.device.channels == (64, 0))
        # Channel 2 refused twice: the refresh (channel 1 otherwise) sends both again.
        sim.device.fail_next = 2
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.5, 0.25))
        await wait_until(lambda: driver.counters["refused_twice"] == 2)
        await wait_until(lambda: sim.device.channels == (64, 32))
        assert status(ctx).connected  # type: ignore[union-attr]


async def test_ten_seconds_at_zero_without_one_watchdog_w(tmp_path: Path) -> None:
    clock = ManualClock()
    unpaced = SimOptions(char_time=0)  # the line's speed is not what this test is about
    async with driven(tmp_path, clock=clock, options=unpaced) as (ctx, sim):
        await connected(ctx)
        driver = driver_of(ctx)
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.0, 0.0))
        # Ten seconds of the driver's and the controller's time, in 0.1 s steps: each step
        # must put a refresh on the (real) line, and the controller's 1 s watchdog never trips.
        for _ in range(100):
            mark = len(sim.device.received)
            clock.advance(0.1)
            async with asyncio.timeout(5.0):
                while not (len(sim.device.received) > mark and driver.sent == [0, 0]):
                    await asyncio.sleep(0.0005)
        assert sim.device.w_sent == 0
        assert sim.device.watchdog_trips == 0
        assert driver.counters["watchdog_w"] == 0
        assert driver.counters["unanswered"] == 0
        # 10 Hz refresh, both channels: about 200 commands, never fewer than the 2 Hz minimum.
        assert sim.device.received.count("!A00") >= 20
        # Telemetry carries the state; the counters go with diagnostics (20.0), the port with
        # the capabilities: a 5 Hz datagram has no room for what does not change.
        assert ctx.telemetry.build_one(Motor) == Motor(True, (0, 0), (0, 0), "")
        counters = ctx.telemetry.counters["motor"]()
        assert counters["watchdog_w"] == 0
        assert counters["velocity_commands"] >= 20
        assert ctx.capabilities.describe()["motor"]["port"] == driver.config.port


async def test_latest_wins_no_backlog(tmp_path: Path) -> None:
    async with driven(tmp_path) as (ctx, sim):
        await connected(ctx)
        mark = len(sim.device.received)
        for step in range(1, 101):  # a burst far faster than 9600 baud can carry
            ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(step / 100, 0.0))
        await wait_until(lambda: sim.device.channels == (127, 0))
        sent = [line for line in since(sim, mark) if line[:2] in ("!A", "!a")]
        assert sent[-1] == "!A7F", sent
        assert len(sent) <= 3, sent


async def test_watchdog_w_is_stripped_and_both_channels_resent(tmp_path: Path) -> None:
    async with driven(tmp_path) as (ctx, sim):
        await connected(ctx)
        driver = driver_of(ctx)
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.5, 0.5))
        await wait_until(lambda: sim.device.channels == (64, 64))
        sim.inject(b"W")  # as if the watchdog had tripped (say, the host stalled)
        sim.device.stop_motors()
        await wait_until(lambda: sim.device.channels == (64, 64))
        assert driver.counters["watchdog_w"] >= 1
        assert status(ctx).connected  # type: ignore[union-attr]


async def test_garbage_from_the_controller_is_dropped(tmp_path: Path) -> None:
    async with driven(tmp_path) as (ctx, sim):
        await connected(ctx)
        driver = driver_of(ctx)
        sim.inject(b"\x00\xff\xfegarbage\r:01020304\r" + b"Z" * 200 + b"\r")
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.25, 0.0))
        await wait_until(lambda: sim.device.channels == (32, 0))
        await wait_until(lambda: driver.counters["garbage_lines"] >= 2)
        assert status(ctx).connected  # type: ignore[union-attr]


async def test_unplug_and_replug_without_replaying_a_stale_command(tmp_path: Path) -> None:
    async with driven(tmp_path, "motor.reconnect_max=0.5") as (ctx, sim):
        await connected(ctx)
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.5, 0.0))
        await wait_until(lambda: sim.device.channels == (64, 0))
        sim.unplug()
        await wait_until(lambda: not status(ctx).connected)  # type: ignore[union-attr]
        assert status(ctx).error  # type: ignore[union-attr]
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.75, 0.0))  # into the void
        await asyncio.sleep(0.5)  # a few failed attempts on a missing port
        sim.replug()
        await connected(ctx)
        mark = len(sim.device.received)
        await asyncio.sleep(0.3)
        assert sim.device.channels == (0, 0)
        assert all(line in ("!A00", "!B00") for line in since(sim, mark) if line[:2] in "!A!B")
        assert driver_of(ctx).counters["reconnects"] == 1
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.25, 0.0))  # a fresh command moves it
        await wait_until(lambda: sim.device.channels == (32, 0))


async def test_silent_controller_is_reported_and_recovered(tmp_path: Path) -> None:
    async with driven(tmp_path, "motor.reply_timeout=0.1", "motor.reconnect_max=0.3") as (
        ctx,
        sim,
    ):
        await connected(ctx)
        sim.device.silent = True
        await wait_until(lambda: not status(ctx).connected)  # type: ignore[union-attr]
        assert "silent" in status(ctx).error  # type: ignore[union-attr]
        sim.device.silent = False
        await connected(ctx)


async def test_a_blocked_event_loop_is_no_silence_of_the_controller(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Synchronous work elsewhere blocks the loop while the first probe is in flight (at a
    platform's start: the other setups importing their modules): the controller's answer
    waits unread, which is no silence of the controller's. No ten carriage returns, no wait
    for a banner, no "not answering" on the way: the first status says it is up."""
    async with driven(tmp_path) as (ctx, sim):
        statuses: list[ControllerStatus] = []
        ctx.bus.subscribe(topics.CONTROLLER_STATUS, statuses.append)
        device = sim.device
        feed = device.feed
        stalled: list[bytes] = []

        def feed_then_stall(data: bytes, now: float) -> bytes:
            if not stalled:  # the first command, just read off the line
                stalled.append(data)
                # The stall itself (not a wait for anything): three reply timeouts long.
                time.sleep(3 * driver_of(ctx).config.reply_timeout)
            return feed(data, now)

        # Before the driver's first step: nothing has been awaited since it was started.
        monkeypatch.setattr(device, "feed", feed_then_stall)
        await connected(ctx)
        assert stalled == [b"^00\r"]
        assert b"\r" * 10 not in device.received_bytes, "the stalled probe counted as lost"
        assert [s.connected for s in statuses[:1]] == [True]


async def test_a_lost_first_probe_costs_no_wait_for_a_banner(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A controller in RS-232 mode that missed the first probe (noise, a stall the budget
    could not absorb) echoes the ten carriage returns and sends no ``OK``: it is asked again
    at once and answers, rather than after a wait for the banner of an R/C-mode controller."""
    monkeypatch.setattr(motor_controller, "BANNER_TIMEOUT", 60.0)  # waiting for it fails
    async with driven(tmp_path, "motor.reply_timeout=0.1") as (ctx, sim):
        device = sim.device
        feed = device.feed
        lost: list[bytes] = []

        def deaf_once(data: bytes, now: float) -> bytes:
            if not lost:
                lost.append(data)
                return b""
            return feed(data, now)

        monkeypatch.setattr(device, "feed", deaf_once)
        await connected(ctx)
        assert lost == [b"^00\r"]
        assert b"\r" * 10 in device.received_bytes
        assert device.mode == "rs232"


async def test_rc_mode_and_wrong_motor_mode_are_fixed_at_bring_up(tmp_path: Path) -> None:
    options = SimOptions(extra_config_line="00", reset_time=0.2)
    options.parameters[ax3500.PARAM_INPUT_MODE] = ax3500.INPUT_MODE_RC
    options.parameters[ax3500.PARAM_MOTOR_MODE] = 0x00  # separate channels
    overrides = ("motor.reply_timeout=0.2", "motor.configure_mode=true")
    async with driven(tmp_path, *overrides, options=options) as (ctx, sim):
        await connected(ctx)
        assert sim.device.resets == 1
        assert sim.device.mixed
        assert sim.device.watchdog
        assert sim.device.parameters[ax3500.PARAM_MOTOR_MODE] == 1
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.5, 0.0))
        await wait_until(lambda: sim.device.channels == (64, 0))


async def test_wrong_mode_refused_when_not_allowed_to_configure(tmp_path: Path) -> None:
    options = SimOptions()
    options.parameters[ax3500.PARAM_MOTOR_MODE] = 0x00
    async with driven(tmp_path, "motor.configure_mode=false", options=options) as (ctx, sim):
        await wait_until(lambda: "needs motor mode 01" in getattr(status(ctx), "error", ""))
        assert not status(ctx).connected
        assert sim.device.resets == 0  # type: ignore[union-attr]


async def test_shutdown_commands_zero_first(tmp_path: Path) -> None:
    async with driven(tmp_path) as (ctx, sim):
        await connected(ctx)
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.8, -0.3))
        await wait_until(lambda: sim.device.channels == (102, -38))
        await ctx.supervisor.stop()
        assert sim.device.channels == (0, 0)
        assert sim.device.received[-2:] == ["!A00", "!B00"]


async def test_lights_and_battery_monitor_commands(tmp_path: Path) -> None:
    gpio = SimulatedGpio()
    output = "motor.positional_lights_output=gpio:/dev/gpiochip0:17"
    async with driven(tmp_path, output, gpio=gpio) as (ctx, sim):
        lights: list[LightsState] = []
        ctx.bus.subscribe(topics.LIGHTS_STATE, lights.append)
        await connected(ctx)
        result = await ctx.commands.dispatch(MAIN_LIGHTS, "ON", None)
        assert result.accepted
        assert sim.device.outputs["C"]
        assert lights[-1] == LightsState(True)
        result = await ctx.commands.dispatch(POSITIONAL_LIGHTS, "ON", None)
        assert result.accepted
        assert gpio.value("/dev/gpiochip0", 17) is Value.ACTIVE
        assert lights[-1] == LightsState(True, True)
        result = await ctx.commands.dispatch(MAIN_LIGHTS, "maybe", None)
        assert not result.accepted
        result = await ctx.commands.dispatch(MAIN_LIGHTS, "OFF", None)
        assert result.accepted
        assert not sim.device.outputs["C"]
        # A controller restart switches its outputs off: the driver puts the lights back.
        await ctx.commands.dispatch(MAIN_LIGHTS, "ON", None)
        sim.device.outputs["C"] = False
        sim.inject(b"\rOK\r")
        await wait_until(lambda: sim.device.outputs["C"])
        result = await ctx.commands.dispatch(BATTERY_MONITOR, "OFF", None)
        assert result.accepted
        assert not status(ctx).battery_monitor  # type: ignore[union-attr]
        # While the controller is away, its output cannot switch; the GPIO still can.
        sim.unplug()
        await wait_until(lambda: not status(ctx).connected)  # type: ignore[union-attr]
        assert not (await ctx.commands.dispatch(MAIN_LIGHTS, "OFF", None)).accepted
        assert (await ctx.commands.dispatch(POSITIONAL_LIGHTS, "OFF", None)).accepted
        assert gpio.value("/dev/gpiochip0", 17) is Value.INACTIVE


async def test_positional_lights_not_fitted(tmp_path: Path) -> None:
    async with driven(tmp_path) as (ctx, _sim):
        await connected(ctx)
        result = await ctx.commands.dispatch(POSITIONAL_LIGHTS, "ON", None)
        assert not result.accepted
        assert "positional_lights_output" in result.reason


async def test_status_polls_reach_telemetry_names(tmp_path: Path) -> None:
    options = SimOptions(lowercase_hex=True)  # "accept both cases in replies"
    async with driven(tmp_path, "motor.poll_hz=10", options=options) as (ctx, _sim):
        await connected(ctx)
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.5, 0.0))
        await wait_until(lambda: (s := status(ctx)) is not None and s.motor_amps is not None)
        report = status(ctx)
        assert report is not None
        assert 23.0 < report.battery_volts < 25.0  # type: ignore[operator]
        assert report.heatsink_c is not None
        assert 20.0 < report.heatsink_c[0] < 60.0
        assert report.internal_volts is not None
        assert 11.5 < report.internal_volts < 13.0
        assert report.motor_amps is not None
        assert report.motor_amps[0] > 1.0


# --------------------------------------------------------------------------- end to end, --sim


def sim_config(*overrides: str) -> PlatformConfig:
    return quiet_platform_config("motor.enabled=true", "sim.enabled=true", *overrides)


def simulated(ctx: PlatformContext) -> tuple[Ax3500Simulator, VehicleModel]:
    """The platform's simulated controller and the vehicle it drives."""
    assert ctx.sim.ax3500 is not None
    assert ctx.sim.vehicle is not None
    return ctx.sim.ax3500, ctx.sim.vehicle


async def open_connection(daemon: PlatformDaemon, key: bytes) -> PlatformConnection:
    conn = PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id="test", fleet_key=key
    )
    await conn.open()
    return conn


async def test_sim_platform_teleop_override_and_deadman(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(sim_config("velocity.deadman=0.2"), fleet_key)
    ctx = daemon.ctx
    sim, vehicle = simulated(ctx)
    sim.device.record = True  # a --sim platform keeps no record unless asked
    await connected(ctx)
    arming = ctx.arming  # disarmed at start (issue 27): armed through its checks
    assert arming is not None
    await wait_until(lambda: not arming.reasons(), 20)
    assert arming.arm("test") is None
    # Autonomous Mode: cmd_vel drives the controller.
    daemon.bus.publish(topics.CMD_VEL, Velocity(0.3, 0.0))
    await wait_until(lambda: sim.device.channels == (38, 0))
    conn = await open_connection(daemon, fleet_key)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    try:
        # Engaged: acknowledged with the motors at zero, then they follow the stream.
        assert await conn.call("set_manual_override", engaged=True) is True
        await wait_until(lambda: sim.device.channels == (0, 0))
        daemon.bus.publish(topics.CMD_VEL, Velocity(0.9, 0.0))  # ignored now
        encoder = pvel.PvelEncoder(key=conn.session_key, session_id=conn.session_id)
        target = ("127.0.0.1", daemon.ctx.velocity_port)
        for _ in range(10):
            sock.sendto(encoder.encode(1.0, 0.0), target)
            await asyncio.sleep(0.05)
        assert sim.device.channels == (127, 0)
        assert vehicle.pose().speed_mps > 0.5  # the simulated vehicle moves
        # The stream stops: the deadman brings the controller's outputs to zero.
        await wait_until(lambda: sim.device.channels == (0, 0))
        sock.sendto(encoder.encode(-0.5, 0.5), target)
        await wait_until(lambda: sim.device.channels == (-64, 64))
        # Disengaged: zero, then autonomy again.
        assert await conn.call("set_manual_override", engaged=False) is True
        await wait_until(lambda: sim.device.channels == (0, 0))
        daemon.bus.publish(topics.CMD_VEL, Velocity(0.3, 0.0))
        await wait_until(lambda: sim.device.channels == (38, 0))
        # Lights through the common protocol, into the simulated controller.
        answer = await conn.call("set_lights", which="main", on=True)
        assert answer["accepted"]
        assert sim.device.outputs["C"]
        telemetry = await conn.call("get_telemetry_report")
        assert telemetry["controller"]["connected"]
        assert telemetry["lights"]["main"]
    finally:
        sock.close()
        await conn.close()
    await daemon.stop()
    assert sim.device.channels == (0, 0)
    assert sim.device.received[-2:] == ["!A00", "!B00"]
    assert not sim.plugged  # the simulator closed after the driver


async def test_rc_mode_left_by_carriage_returns_drives_without_configuring(
    tmp_path: Path,
) -> None:
    options = SimOptions()
    options.parameters[ax3500.PARAM_INPUT_MODE] = ax3500.INPUT_MODE_RC
    overrides = ("motor.configure_mode=false", "motor.reply_timeout=0.2")
    async with driven(tmp_path, *overrides, options=options) as (ctx, sim):
        await connected(ctx)
        assert sim.device.resets == 0
        assert sim.device.mode == "rs232"
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.5, 0.0))
        await wait_until(lambda: sim.device.channels == (64, 0))


async def test_keyboard_drive_moves_the_simulated_controller(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """The whole chain as an operator uses it: 'brasidas-station drive' in a terminal, the
    station's $PVEL sender, the platform's stream, arbiter and driver, the simulated AX3500."""
    platform = await platform_factory(sim_config(), fleet_key)
    sim, vehicle = simulated(platform.ctx)
    await connected(platform.ctx)
    station = StationDaemon(load_config(StationConfig, None, ["station.api_port=0"]), fleet_key)
    await station.start()
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
        os.write(master, b"www")  # three steps forward: 0.3
        await wait_until(lambda: sim.device.channels == (38, 0))
        os.write(master, b"\x1b[D")  # left arrow: a left turn, !B on this chassis
        await wait_until(lambda: sim.device.channels == (38, 13))
        await wait_until(lambda: vehicle.pose().speed_mps > 0.3)
        os.write(master, b" ")
        await wait_until(lambda: sim.device.channels == (0, 0))
        os.write(master, b"q")
        assert await asyncio.wait_for(process.wait(), 10) == 0
        assert sim.device.w_sent == 0  # the stream and the refresh kept the watchdog fed
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()
        loop.remove_reader(master)
        os.close(master)
        await station.stop()


async def test_a_hung_port_open_is_reported_and_never_stalls_the_loop(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A USB adapter whose driver does not answer: the open blocks in the kernel. The other
    actors keep running, the hang is reported, and the port is used once the open returns."""
    release, calls = hang_serial_opens(monkeypatch)
    gaps: list[float] = []

    async with driven(tmp_path) as (ctx, sim), asyncio.TaskGroup() as group:
        driver_of(ctx).opener.timeout = 0.2
        ticking = group.create_task(record_loop_gaps(gaps))
        await wait_until(lambda: "hangs" in getattr(status(ctx), "error", ""))
        await asyncio.sleep(0.3)  # more attempts time out meanwhile
        assert len(calls) == 1  # a hung attempt is awaited again, not doubled
        release.set()
        await connected(ctx)
        ctx.bus.publish(topics.MOTOR_COMMAND, Velocity(0.25, 0.0))
        await wait_until(lambda: sim.device.channels == (32, 0))
        ticking.cancel()
    assert max(gaps) < 1.0, max(gaps)
