"""The motor controller actor: brings the AX3500 up, decides what to send next, reconnects.

See :mod:`platformd.motor` for the send priorities and the failure handling.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque

from brasidas import topics
from brasidas.actor import Actor
from brasidas.backoff import Backoff
from brasidas.clock import Clock, LoopClock, sleep
from brasidas.codecs import ax3500
from brasidas.codecs.ax3500 import Command, MotionMapping, Reply, Status
from brasidas.codecs.commands import (
    BATTERY_MONITOR,
    MAIN_LIGHTS,
    POSITIONAL_LIGHTS,
    PayloadError,
    parse_switch,
)
from brasidas.codecs.telemetry_schema import Motor
from brasidas.messages import CommandResult, ControllerStatus, Velocity
from platformd.automation import report_switch
from platformd.commands import SystemCommand
from platformd.context import PlatformContext
from platformd.motor.lights import Lights, OutputRequest, Send
from platformd.motor.link import LinkError, ReplyTimeout, SerialLink
from platformd.serial_port import PortError, PortOpener

_LOGGER = logging.getLogger(__name__)

BANNER_TIMEOUT = 3.0
"""How long to wait for ``OK`` after ten carriage returns or a reset (the device takes 1-2 s)."""
RECONNECT_INITIAL = 0.2


class MotorController(Actor):
    """Owns the controller: velocity out (latest wins), lights, status polls, reconnection."""

    name = "motor"
    stop_priority = 100
    """Stops before everything else: it commands zero while the line is still open."""

    def __init__(self, ctx: PlatformContext, *, clock: Clock | None = None) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.config = config = ctx.config.motor
        self.clock: Clock = clock or LoopClock()
        """Drives the schedule (refreshes, polls, reconnection); answers are awaited in real time."""
        self.device = ctx.motor_serial
        """The serial line to open: ``motor.*``, or in --sim the simulator's pty."""
        self.opener = PortOpener(self.device)
        self.mapping = MotionMapping(
            linear_scale=config.linear_scale,
            angular_scale=config.angular_scale,
            linear_limit=config.linear_limit,
            angular_limit=config.angular_limit,
            invert_linear=config.invert_linear,
            invert_angular=config.invert_angular,
        )
        self.refresh_period = 1.0 / max(2.0, config.refresh_hz)
        self.poll_period = 1.0 / config.poll_hz if config.poll_hz > 0 else None
        self.desired = (0, 0)
        """Channel levels to command (the newest MOTOR_COMMAND)."""
        self.sent: list[int | None] = [None, None]
        """Channel levels the controller acknowledged; None: unknown, send again."""
        self.battery_monitor = ctx.config.telemetry.battery_monitor
        outputs = {"main": config.main_lights_output, "positional": ctx.positional_lights_output}
        gpio = ctx.sim.gpio
        self.lights = Lights(ctx.bus, outputs, gpio.request_lines if gpio is not None else None)
        self.status = ControllerStatus(False, battery_monitor=self.battery_monitor)
        self.counters: dict[str, int] = dict.fromkeys(
            (
                "commands",
                "velocity_commands",
                "rejected",
                "resent",
                "refused_twice",
                "unanswered",
                "watchdog_w",
                "stray_lines",
                "garbage_lines",
                "reconnects",
                "controller_restarts",
            ),
            0,
        )
        self._link: SerialLink | None = None
        self._ready = False
        self._stopping = False
        self._wake = asyncio.Event()
        self._zero_sent = asyncio.Event()
        self._polls: deque[Command] = deque()
        self._poll_values: dict[str, tuple[int, ...]] = {}
        self._polled_at = time.monotonic()
        """When the last poll reply arrived (the age of the status's readings)."""
        self._last_velocity_at = float("-inf")
        self._next_poll = 0.0
        self._unanswered_in_row = 0
        self._reported_error = ""
        self._restore_lights = False
        self._watchdog_seen = 0
        self._refresh_both = False
        self._generation = 0
        """Bumped whenever the controller's outputs were lost (W, restart)."""

    # ------------------------------------------------------------------ lifecycle

    async def run(self) -> None:
        self.subscribe(topics.MOTOR_COMMAND, self._on_motor_command)
        self.on_remove(
            self.ctx.commands.register(
                self.name,
                {
                    BATTERY_MONITOR: self._command_battery_monitor,
                    MAIN_LIGHTS: self._command_lights,
                    POSITIONAL_LIGHTS: self._command_lights,
                },
            )
        )
        self.lights.publish()
        report_switch(self.bus, "battery_monitor", self.battery_monitor)
        try:
            async with asyncio.TaskGroup() as group:
                group.create_task(self.lights.gpio_worker(), name="motor:gpio")
                await self._connection_loop()
        finally:
            self.lights.fail_pending("motor controller stopped")

    async def _connection_loop(self) -> None:
        """Open, bring up and serve the controller; reopen with capped backoff."""
        backoff = Backoff(RECONNECT_INITIAL, max(RECONNECT_INITIAL, self.config.reconnect_max))
        failures = 0
        try:
            while True:
                try:
                    link = SerialLink.attach(await self.opener.open(), self.config.reply_timeout)
                except (PortError, LinkError) as err:
                    failures += 1
                    self._report_down(str(err), first=failures == 1)
                    await sleep(self.clock, backoff.next())
                    continue
                self._link = link
                error = ""
                try:
                    await self._bring_up(link)
                    if failures:
                        self.counters["reconnects"] += 1
                        _LOGGER.info("motor controller back on %s", self.device.path)
                    failures = 0
                    backoff.reset()
                    await self._serve(link)
                except LinkError as err:
                    failures += 1
                    error = str(err)
                    self._report_down(error, first=failures == 1)
                finally:
                    self._disconnected(link, error)
                await sleep(self.clock, backoff.next())
        finally:
            self.opener.close()
            if self._link is not None:
                self._disconnected(self._link, "driver stopped")

    async def async_stop(self) -> None:
        """Command zero and wait (briefly) for the controller to take it."""
        self._stopping = True
        if not self._ready:
            return
        self.desired = (0, 0)
        self.sent = [None, None]
        self._zero_sent.clear()
        self._wake.set()
        try:
            async with asyncio.timeout(0.5):
                await self._zero_sent.wait()
        except TimeoutError:
            _LOGGER.warning("motor controller did not acknowledge zero before shutdown")

    def _disconnected(self, link: SerialLink, error: str) -> None:
        link.close()
        self._link = None
        if self._ready:
            self._ready = False
            self._reported_error = error
            self._publish_status(connected=False, error=error)
        # Nothing from before the outage is replayed when the controller returns.
        self.desired = (0, 0)
        self.sent = [None, None]
        self._polls.clear()
        self._zero_sent.set()  # nothing more will be sent on this link

    def _report_down(self, error: str, *, first: bool) -> None:
        if first:
            _LOGGER.warning("motor controller unavailable: %s; retrying", error)
        else:
            _LOGGER.debug("motor controller still unavailable: %s", error)
        if error != self._reported_error or self.status.connected:
            self._reported_error = error
            self._publish_status(connected=False, error=error)

    # ------------------------------------------------------------------ bring-up

    async def _bring_up(self, link: SerialLink) -> None:
        """RS-232 mode (ten CRs if needed), the configured mode checked, zero commanded."""
        self._watchdog_seen = 0
        self._unanswered_in_row = 0
        link.on_unsolicited = self._wake.set
        reply = await self._probe(link)
        if reply is None:
            link.banner.clear()
            link.write_raw(b"\r" * 10)
            # A controller already in RS-232 mode only echoes them and sends no OK: asked
            # again at once, it answers (its first probe was lost). One leaving R/C mode says
            # OK when it has switched: waited for if the second probe goes unanswered too.
            reply = await self._probe(link)
            if reply is None:
                await link.wait_banner(BANNER_TIMEOUT)
                reply = await self._probe(link)
            if reply is None:
                raise LinkError("controller silent, also after ten carriage returns")
        await self._check_mode(link, reply.values[0])
        with contextlib.suppress(LinkError, ReplyTimeout):
            ident = await self._read_config(link, ax3500.PARAM_CONTROLLER_ID)
            if not ident & ax3500.CONTROLLER_ID_AX3500_BIT:
                _LOGGER.warning("controller id %02X does not say AX3500", ident)
        self.desired = (0, 0)
        self.sent = [None, None]
        for channel in (1, 2):
            await self._checked(link, ax3500.motor(channel, 0))
        self.sent = [0, 0]
        self._last_velocity_at = self.clock.time()
        self._unanswered_in_row = 0
        self._ready = True
        self._reported_error = ""
        _LOGGER.info("motor controller up on %s", self.device.path)
        self._publish_status(connected=True)
        await self.lights.restore(self._sender(link))

    async def _check_mode(self, link: SerialLink, input_mode: int) -> None:
        """Mixed open-loop mode is required (else commands mean something else); RS-232 with
        the watchdog is wanted. What differs is written and the controller reset, when
        ``configure_mode`` allows; otherwise a wrong motor mode refuses to drive."""
        motor_mode = await self._read_config(link, ax3500.PARAM_MOTOR_MODE)
        writes: list[tuple[int, int]] = []
        if input_mode != ax3500.INPUT_MODE_RS232_WATCHDOG:
            # RS-232 without the watchdog, or R/C / analog left by ten carriage returns.
            writes.append((ax3500.PARAM_INPUT_MODE, ax3500.INPUT_MODE_RS232_WATCHDOG))
        if motor_mode != ax3500.MOTOR_MODE_MIXED_OPEN_LOOP:
            writes.append((ax3500.PARAM_MOTOR_MODE, ax3500.MOTOR_MODE_MIXED_OPEN_LOOP))
        if not writes:
            return
        described = f"input mode {input_mode:02X}, motor mode {motor_mode:02X}"
        if not self.config.configure_mode:
            if motor_mode != ax3500.MOTOR_MODE_MIXED_OPEN_LOOP:
                raise LinkError(f"controller in {described}; needs motor mode 01 (mixed)")
            _LOGGER.warning(
                "controller in %s: its watchdog may be off, a lost link might not stop it",
                described,
            )
            return
        _LOGGER.warning("controller in %s: writing ^00 02, ^01 01 and resetting it", described)
        for parameter, value in writes:
            await self._checked(link, ax3500.config_write(parameter, value))
        link.banner.clear()
        await self._checked(link, ax3500.reset())
        if not await link.wait_banner(BANNER_TIMEOUT):
            raise LinkError("controller did not restart after %rrrrrr")
        modes = (
            await self._read_config(link, ax3500.PARAM_INPUT_MODE),
            await self._read_config(link, ax3500.PARAM_MOTOR_MODE),
        )
        wanted = (ax3500.INPUT_MODE_RS232_WATCHDOG, ax3500.MOTOR_MODE_MIXED_OPEN_LOOP)
        if modes != wanted:
            raise LinkError(f"controller kept modes {modes[0]:02X}/{modes[1]:02X}")

    async def _probe(self, link: SerialLink) -> Reply | None:
        try:
            reply = await link.request(ax3500.config_read(ax3500.PARAM_INPUT_MODE))
        except ReplyTimeout:
            return None
        return reply if reply.status is Status.VALUES else None

    async def _read_config(self, link: SerialLink, parameter: int) -> int:
        reply = await self._checked(link, ax3500.config_read(parameter))
        return reply.values[0]

    async def _checked(self, link: SerialLink, command: Command) -> Reply:
        """A bring-up step: it must succeed."""
        try:
            reply = await self._send(link, command)
        except ReplyTimeout:
            raise LinkError(f"no answer to {command.text}") from None
        if reply is None:
            raise LinkError(f"controller refused {command.text}")
        return reply

    # ------------------------------------------------------------------ sending

    async def _send(self, link: SerialLink, command: Command) -> Reply | None:
        """One command, resent once on ``-``; None when refused twice. Raises ReplyTimeout."""
        for attempt in (1, 2):
            self.counters["commands"] += 1
            try:
                reply = await link.request(command)
            except ReplyTimeout:
                self.counters["unanswered"] += 1
                self._unanswered_in_row += 1
                if self._unanswered_in_row >= self.config.max_unanswered:
                    raise LinkError(
                        f"controller silent ({self._unanswered_in_row} commands unanswered)"
                    ) from None
                raise
            finally:
                self._account(link)
            self._unanswered_in_row = 0
            if reply.ok:
                return reply
            self.counters["rejected"] += 1
            if attempt == 1:
                self.counters["resent"] += 1
        self.counters["refused_twice"] += 1
        count = self.counters["refused_twice"]
        if count & (count - 1) == 0:  # 1, 2, 4, 8...: reported without flooding the log
            _LOGGER.warning("controller refused %s twice (%d so far)", command.text, count)
        return None

    def _account(self, link: SerialLink) -> None:
        """Take note of what the controller said on its own: W (watchdog), OK (restart)."""
        self.counters["stray_lines"] = link.stray_lines
        self.counters["garbage_lines"] = link.parser.dropped_lines
        if link.parser.watchdog_chars > self._watchdog_seen:
            # The controller's watchdog stopped the motors: both channels must be resent.
            self.counters["watchdog_w"] += link.parser.watchdog_chars - self._watchdog_seen
            self._watchdog_seen = link.parser.watchdog_chars
            if self._ready:
                _LOGGER.warning("controller watchdog tripped (W): commanding it again")
            self._invalidate()
        if link.banners and self._ready:
            # An OK in mid-session: the controller restarted (power glitch, reset).
            _LOGGER.warning("motor controller restarted: commanding it again")
            self.counters["controller_restarts"] += link.banners
            self._invalidate()
            self._restore_lights = True
        link.banners = 0

    def _invalidate(self) -> None:
        """The controller's outputs are not what it acknowledged: send both channels again."""
        self.sent = [None, None]
        self._generation += 1

    async def _serve(self, link: SerialLink) -> None:
        after_velocity = False
        while True:
            self._wake.clear()
            self._account(link)
            now = self.clock.time()
            if self.desired[0] != self.sent[0] or self.desired[1] != self.sent[1]:
                await self._send_velocity(link)
                after_velocity = True
                continue
            if self._restore_lights:
                self._restore_lights = False
                await self.lights.restore(self._sender(link))
                continue
            if self.lights.pending:
                await self.lights.serve(self._sender(link), self.lights.pending.popleft())
                after_velocity = False
                continue
            if now - self._last_velocity_at >= self.refresh_period:
                # Channel 1 again keeps the watchdog fed; channel 2 was acknowledged and only
                # a watchdog trip or a restart (both seen: W, OK) would undo it.
                self.sent[0] = None
                if self._refresh_both:
                    self._refresh_both = False
                    self.sent[1] = None
                continue
            if self._stopping:
                pass  # zero is the last word: no polls or outputs any more
            elif self._polls or (
                after_velocity and self.poll_period is not None and now >= self._next_poll
            ):
                if not self._polls:
                    self._next_poll = now + self.poll_period  # type: ignore[operator]
                    self._polls.extend(ax3500.query(letter) for letter in "ema")
                await self._poll(link, self._polls.popleft())
                continue
            after_velocity = False
            refresh = self.clock.call_at(
                self._last_velocity_at + self.refresh_period, self._wake.set
            )
            try:
                await self._wake.wait()
            finally:
                refresh.cancel()

    async def _send_velocity(self, link: SerialLink) -> None:
        """The channel that differs (channel 1 first), from the newest desired levels."""
        channel = 1 if self.desired[0] != self.sent[0] else 2
        level = self.desired[channel - 1]
        self.counters["velocity_commands"] += 1
        generation = self._generation
        try:
            reply = await self._send(link, ax3500.motor(channel, level))
        except ReplyTimeout:
            return  # still differs: tried again at once
        if generation != self._generation:
            return  # a W or a restart during the exchange: it may not have stuck
        if reply is None:
            # Refused twice (reported): counted as sent so the line is not hammered; the
            # next refresh sends both channels again.
            self._refresh_both = True
        self.sent[channel - 1] = level
        self._last_velocity_at = self.clock.time()
        if self._stopping and self.sent == [0, 0] and self.desired == (0, 0):
            self._zero_sent.set()

    async def _poll(self, link: SerialLink, command: Command) -> None:
        try:
            reply = await self._send(link, command)
        except ReplyTimeout:
            self._polls.clear()
            return
        if reply is not None and reply.status is Status.VALUES:
            self._poll_values[command.text[1]] = reply.values
            self._polled_at = time.monotonic()
        if not self._polls:
            self._publish_status(connected=True)

    # ------------------------------------------------------------------ commands from the bus

    def _on_motor_command(self, velocity: Velocity) -> None:
        if self._stopping or not self._ready:
            return  # commands from before the link is up are never replayed
        levels = self.mapping.levels(velocity.linear, velocity.angular)
        if levels != self.desired:
            self.desired = levels
            self._wake.set()
        elif self.clock.time() - self._last_velocity_at >= 0.7 * self.refresh_period:
            # Refresh now, right behind this command, rather than at a random moment later.
            self._last_velocity_at = float("-inf")
            self._wake.set()

    async def _command_battery_monitor(self, command: SystemCommand) -> CommandResult:
        try:
            on = parse_switch(command.payload)
        except PayloadError as err:
            return CommandResult(False, str(err))
        self.battery_monitor = on
        report_switch(self.bus, "battery_monitor", on)
        self._publish_status(connected=self.status.connected, error=self.status.error)
        return CommandResult(True, result={"battery_monitor": on})

    async def _command_lights(self, command: SystemCommand) -> CommandResult:
        which = "main" if command.code == MAIN_LIGHTS else "positional"
        try:
            on = parse_switch(command.payload)
        except PayloadError as err:
            return CommandResult(False, str(err))
        if not self.lights.output(which):
            return CommandResult(False, f"no {which} lights fitted (motor.{which}_lights_output)")
        request = OutputRequest(which, on, asyncio.get_running_loop().create_future())
        if self.lights.on_gpio(which):  # a GPIO line works without the controller
            self.lights.request_gpio(request)
        elif self._ready:
            self.lights.pending.append(request)
            self._wake.set()
        else:
            return CommandResult(False, "motor controller not connected")
        return await request.reply

    def _sender(self, link: SerialLink) -> Send:
        """The line as the lights see it: one command, True when acknowledged."""

        async def send(command: Command) -> bool:
            try:
                return await self._send(link, command) is not None
            except ReplyTimeout:
                return False

        return send

    # ------------------------------------------------------------------ reporting

    def _publish_status(self, *, connected: bool, error: str = "") -> None:
        values = self._poll_values if connected else {}
        battery = values.get("e")
        heat = values.get("m")
        amps = values.get("a")
        self.status = ControllerStatus(
            connected=connected,
            battery_volts=ax3500.battery_volts(battery[0]) if battery else None,
            battery_monitor=self.battery_monitor,
            heatsink_c=(
                (ax3500.heatsink_celsius(heat[0]), ax3500.heatsink_celsius(heat[1]))
                if heat and len(heat) >= 2
                else None
            ),
            motor_amps=(
                (ax3500.motor_amps(amps[0]), ax3500.motor_amps(amps[1]))
                if amps and len(amps) >= 2
                else None
            ),
            internal_volts=(
                ax3500.internal_volts(battery[1]) if battery and len(battery) >= 2 else None
            ),
            error=error,
            stamp=self._polled_at,
        )
        if not connected:
            self._poll_values.clear()
        self.bus.publish(topics.CONTROLLER_STATUS, self.status)

    def snapshot(self) -> Motor:
        """Driver state for telemetry (``motor`` section); its counters go with diagnostics."""
        return Motor(self._ready, tuple(self.desired), tuple(self.sent), self.status.error)
