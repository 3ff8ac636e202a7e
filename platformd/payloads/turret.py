"""The turret payload: driver of the microcontroller's line protocol (brasidas.codecs.turret)
and the actor that puts it on command group 100.

100.0 ``aim`` (``az=<deg>,el=<deg>``), 100.1 ``fire`` (engagement: the command authority lets it
through only from the override holder under manual override, no failsafe step in progress),
100.2 ``safe``. On override release, session loss (which releases the override) or any failsafe
step the turret is made safe at once: trigger released, servos hold. Its sight, the thermal IP
camera (``payload.turret_stream``: the ``payload_camera`` RTSP stream), is registered as its
stream when the platform has it. A line that cannot be opened or goes away (the USB adapter
unplugged) is reported (telemetry ``turret.error``) and reopened with capped backoff.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Any

import serial
import serial_asyncio

from brasidas import topics
from brasidas.actor import Actor
from brasidas.backoff import Backoff
from brasidas.codecs import turret
from brasidas.codecs.commands import CommandCode, PayloadError, parse_payload
from brasidas.codecs.telemetry_schema import Turret
from brasidas.codecs.turret import Line, LineDecoder
from brasidas.messages import CommandResult, FailsafeState, FailsafeStep, OverrideState
from platformd.commands import CommandSpec, SystemCommand
from platformd.context import PayloadInfo, PlatformContext

_LOGGER = logging.getLogger(__name__)

GROUP = 100
AIM = CommandCode(GROUP, 0)
FIRE = CommandCode(GROUP, 1)
SAFE = CommandCode(GROUP, 2)
SPECS = {
    AIM: CommandSpec("aim", "az=<deg -180..180>,el=<deg -10..60>"),
    FIRE: CommandSpec("fire", "", engagement=True),
    SAFE: CommandSpec("safe", ""),
}
TRIES = 3
RECONNECT_INITIAL = 0.2
RECONNECT_MAX = 5.0


class TurretError(Exception):
    """The microcontroller refused a command or did not acknowledge it after every try."""


class TurretDriver(asyncio.Protocol):
    """One open line to the microcontroller: one command in flight, acknowledged or resent."""

    def __init__(self, ack_timeout: float, counters: dict[str, int] | None = None) -> None:
        self.ack_timeout = ack_timeout
        self.decoder = LineDecoder()
        self.counters: dict[str, int] = counters if counters is not None else new_counters()
        """The line's counters (a payload's outlive each line it opens)."""
        self.state: tuple[float, float, bool] | None = None
        """Azimuth, elevation and trigger by the last acknowledgement."""
        self._transport: asyncio.WriteTransport | None = None
        self._seq = 0
        self._waiting: tuple[int, asyncio.Future[Line]] | None = None
        self._lock = asyncio.Lock()
        self._opened = asyncio.Event()
        """Set once the transport is there (pyserial-asyncio makes it a loop turn later)."""
        self.lost = asyncio.Event()
        """Set when the line closed (the device vanished, or :meth:`close`)."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.WriteTransport)
        self._transport = transport
        self._opened.set()

    def connection_lost(self, exc: Exception | None) -> None:
        self._transport = None
        self.lost.set()
        if self._waiting is not None and not self._waiting[1].done():
            self._waiting[1].set_exception(TurretError("serial line closed"))

    def data_received(self, data: bytes) -> None:
        for item in self.decoder.feed(data):
            if not isinstance(item, Line):
                continue  # counted by the decoder; the command is resent
            if item.kind == "W":
                self.counters["watchdog"] += 1
                _LOGGER.warning("turret watchdog released the trigger")
            elif item.kind == "A" and self._waiting is not None and item.fields:
                seq, future = self._waiting
                if item.fields[0] == str(seq) and not future.done():
                    future.set_result(item)

    async def send(self, name: str, *args: float) -> Line:
        """Send one command; its acknowledgement, or TurretError."""
        async with self._lock:
            # asyncio.timeout, not wait_for: in 3.11 wait_for returns an answer that arrives
            # with a cancellation and swallows the cancellation (the actor then never stops).
            if not self._opened.is_set():
                async with asyncio.timeout(self.ack_timeout * TRIES):
                    await self._opened.wait()
            self._seq = (self._seq + 1) % 256
            line = turret.command(self._seq, name, *args)
            for attempt in range(TRIES):
                if self._transport is None:
                    raise TurretError("serial line closed")
                future: asyncio.Future[Line] = asyncio.get_running_loop().create_future()
                self._waiting = (self._seq, future)
                self._transport.write(line)
                self.counters["sent" if attempt == 0 else "resent"] += 1
                try:
                    async with asyncio.timeout(self.ack_timeout):
                        answer = await future
                except TimeoutError:
                    continue
                finally:
                    self._waiting = None
                if answer.fields[1:2] != ("OK",):
                    self.counters["refused"] += 1
                    raise TurretError(",".join(answer.fields[2:]) or "refused")
                self.counters["acked"] += 1
                with contextlib.suppress(IndexError, ValueError):
                    az, el, trigger = answer.fields[2:5]
                    self.state = (float(az), float(el), trigger == "1")
                return answer
            self.counters["unacked"] += 1
            raise TurretError(f"{name}: no acknowledgement after {TRIES} tries")

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()


def new_counters() -> dict[str, int]:
    return dict.fromkeys(("sent", "acked", "resent", "unacked", "refused", "watchdog"), 0)


class TurretPayload(Actor):
    """Opens the line, keeps the microcontroller's watchdog fed, answers group 100."""

    name = "turret"

    def __init__(self, ctx: PlatformContext, port: str, streams: tuple[str, ...] = ()) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.port = port
        self.streams = streams
        """Its own media streams (the thermal camera), by name."""
        self.config = ctx.config.payload
        self.driver: TurretDriver | None = None
        self.error = ""
        """Why the line is not open (cannot be opened, went away); empty while it is."""
        self.counters = new_counters()
        self.safings = 0
        self._group: asyncio.TaskGroup | None = None
        self._engaged = False

    async def run(self) -> None:
        """Open the line and keep the watchdog fed; reopen with capped backoff when it fails."""
        backoff = Backoff(RECONNECT_INITIAL, RECONNECT_MAX)
        try:
            async with asyncio.TaskGroup() as group:
                self._group = group
                self.on_remove(self.ctx.commands.register(self.name, self._handlers(), SPECS))
                self.subscribe(topics.OVERRIDE_STATE, self._on_override)
                self.subscribe(topics.FAILSAFE_STATE, self._on_failsafe)
                while True:
                    try:
                        await self._serve_line(backoff)
                    except (serial.SerialException, OSError) as err:
                        self._down(f"cannot open {self.port}: {err}")
                    await asyncio.sleep(backoff.next())
        finally:
            self._group = None

    async def _serve_line(self, backoff: Backoff) -> None:
        """One open line: ping at a third of the microcontroller's watchdog until it closes."""
        _, driver = await serial_asyncio.create_serial_connection(
            asyncio.get_running_loop(),
            lambda: TurretDriver(self.config.turret_ack_timeout, self.counters),
            self.port,
            baudrate=self.config.turret_baudrate,
        )
        self.driver = driver
        if self.error:
            _LOGGER.info("turret line %s open again", self.port)
        self.error = ""
        backoff.reset()
        try:
            while not await _closed_within(driver, self.config.turret_watchdog_s / 3):
                with contextlib.suppress(TurretError):
                    await driver.send("PING")
        finally:
            self.driver = None
            driver.close()
        self._down(f"{self.port}: serial line closed")

    def _down(self, error: str) -> None:
        if error != self.error:
            _LOGGER.warning("turret line down: %s; retrying", error)
        self.error = error

    def _handlers(self) -> dict[CommandCode, Any]:
        return {AIM: self._aim, FIRE: self._fire, SAFE: self._safe}

    async def _aim(self, command: SystemCommand) -> CommandResult:
        try:
            values = parse_payload(command.payload)
            azimuth, elevation = float(values["az"]), float(values["el"])
        except (PayloadError, KeyError, ValueError):
            return CommandResult(False, f"expected {SPECS[AIM].format}")
        return await self._send("AIM", azimuth, elevation)

    async def _fire(self, command: SystemCommand) -> CommandResult:
        return await self._send("FIRE")

    async def _safe(self, command: SystemCommand) -> CommandResult:
        return await self._send("SAFE")

    async def _send(self, name: str, *args: float) -> CommandResult:
        if self.driver is None:
            return CommandResult(False, f"turret line not open: {self.error or self.port}")
        try:
            await self.driver.send(name, *args)
        except TurretError as err:
            return CommandResult(False, f"turret: {err}")
        assert self.driver.state is not None
        azimuth, elevation, trigger = self.driver.state
        return CommandResult(True, result={"az": azimuth, "el": elevation, "trigger": trigger})

    def make_safe(self, reason: str) -> None:
        """Trigger released, servos hold: at once, whatever else is in flight. Event loop."""
        self.safings += 1
        _LOGGER.warning("turret made safe: %s", reason)
        if self._group is not None:
            self._group.create_task(self._send("SAFE"), name="turret:safe")

    def section(self) -> Turret:
        """The ``turret`` telemetry section."""
        driver = self.driver
        streams = self._stream_states()
        counters = {**self.counters, "safe": self.safings}
        if driver is None:
            return Turret(False, counters=counters, streams=streams, error=self.error)
        azimuth, elevation, trigger = driver.state or (None, None, False)
        return Turret(True, azimuth, elevation, trigger, counters, streams)

    def _stream_states(self) -> dict[str, str]:
        if not self.streams or self.ctx.media is None:
            return {}
        return {
            stream["name"]: stream["state"]
            for stream in self.ctx.media.describe_streams()
            if stream["name"] in self.streams
        }

    def _on_override(self, state: OverrideState) -> None:
        engaged, self._engaged = self._engaged, state.engaged
        if engaged and not state.engaged:
            self.make_safe("manual override released")

    def _on_failsafe(self, state: FailsafeState) -> None:
        if state.step is not FailsafeStep.NORMAL:
            self.make_safe(f"failsafe {state.step.value}")


async def _closed_within(driver: TurretDriver, seconds: float) -> bool:
    """True as soon as the line closes, False after ``seconds`` with it still open."""
    try:
        async with asyncio.timeout(seconds):
            await driver.lost.wait()
    except TimeoutError:
        return False
    return True


async def async_setup(ctx: PlatformContext) -> None:
    simulator = ctx.sim.turret
    config = ctx.config.payload
    port = simulator.path if simulator is not None else config.turret_port
    have = {stream["name"] for stream in ctx.media.describe_streams()} if ctx.media else set()
    streams = (config.turret_stream,) if config.turret_stream in have else ()
    if config.turret_stream and not streams:
        _LOGGER.info(
            "turret: no %s stream on this platform ([%s] not enabled): it lists none",
            config.turret_stream,
            config.turret_stream,
        )
    ctx.payloads["turret"] = PayloadInfo("turret", (GROUP,), streams)
    payload = TurretPayload(ctx, port, streams)
    ctx.telemetry.register(Turret, payload.section)
    ctx.supervisor.start(payload)
