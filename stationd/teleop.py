"""Teleoperation from the station: one ``$PVEL`` sender per connected platform.

While this station holds a platform's manual override, its sender streams ``$PVEL`` at
``teleop.rate_hz`` (20 Hz) to the endpoint from ``get_velocity_connection_info``, tagged with
the session key; the stream is continuous, zeros included. What it sends comes from, in order:
the game controller while its enable button is held (for the platform it drives), else the
drive client's last ``teleop_set`` if newer than ``teleop.drive_timeout``, else zero.

Local API: ``teleop_set(platform_id, linear, angular)`` (the keyboard ``drive`` command and the
web console), ``teleop_status(platform_id)`` (what is streamed, and what the platform reports).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from brasidas import topics
from brasidas.actor import Actor, wait_forever
from brasidas.backoff import Backoff
from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, RpcError
from brasidas.codecs.pvel import PvelEncoder
from brasidas.codecs.telemetry_schema import Motion, Override, VelocityLink, snapshot_from_json
from brasidas.config import TeleopSection
from brasidas.messages import PlatformLink, Velocity
from stationd.client import PlatformConnection
from stationd.context import StationContext
from stationd.joystick import JoystickReader

_LOGGER = logging.getLogger(__name__)

STOP = Velocity(0.0, 0.0)
NOT_CONNECTED = -32010


class VelocitySender:
    """Streams ``$PVEL`` to one platform while this station holds its override.

    ``setpoint()`` is asked once per sentence. ``run`` ends when the connection closes.
    """

    def __init__(
        self,
        connection: PlatformConnection,
        config: TeleopSection,
        setpoint: Callable[[], tuple[Velocity, str]],
    ) -> None:
        self.connection = connection
        self.config = config
        self.setpoint = setpoint
        self.encoder = PvelEncoder(key=connection.session_key, session_id=connection.session_id)
        self.target: tuple[str, int] | None = None
        self.ticks = 0
        self.sent = 0
        self.last = STOP
        self.source = "idle"
        self.engaged = False
        self.on_engaged: Callable[[str], None] = lambda _platform_id: None
        self._transport: asyncio.DatagramTransport | None = None

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        self._transport = await self._open()
        if self._transport is None:
            return
        period = 1.0 / self.config.rate_hz
        deadline = loop.time()
        try:
            while not self.connection.closed.is_set():
                self.tick()
                deadline += period
                delay = deadline - loop.time()
                if delay < -period:  # the loop was held up: resume the rhythm, no burst
                    deadline = loop.time()
                await asyncio.sleep(max(0.0, delay))
        finally:
            self.close()

    async def _open(self) -> asyncio.DatagramTransport | None:
        """Ask for the endpoint and open the socket; retried until the connection closes."""
        backoff = Backoff(0.2, 2.0)
        while not self.connection.closed.is_set():
            try:
                info = await self.connection.call("get_velocity_connection_info")
                host = str(info.get("host") or "")
                if host in ("", "0.0.0.0", "::"):
                    host = self.connection.platform_host
                target = (host, int(info["port"]))
                transport, _ = await asyncio.get_running_loop().create_datagram_endpoint(
                    asyncio.DatagramProtocol, remote_addr=target
                )
                _expedite(transport)
            except ConnectionError:
                return None
            except (RpcError, OSError, KeyError, ValueError, TypeError) as err:
                _LOGGER.warning(
                    "no velocity endpoint for %s yet: %s", self.connection.platform_id, err
                )
                await asyncio.sleep(backoff.next())
                continue
            self.target = target
            return transport
        return None

    def tick(self) -> None:
        """Send one sentence if this station holds the override."""
        self.ticks += 1
        engaged = self.connection.manual_override
        if engaged and not self.engaged:
            self.on_engaged(self.connection.platform_id)
        self.engaged = engaged
        if not engaged or self._transport is None:
            self.source = "idle"
            return
        velocity, self.source = self.setpoint()
        # Stamped with the send time in the platform's clock (once the first heartbeat has
        # told the offset): the platform ages each packet, caps the speed by the age and
        # drops a stale one.
        sent_ms = self.connection.platform_time_ms()
        self._transport.sendto(self.encoder.encode(velocity.linear, velocity.angular, sent_ms))
        self.last = velocity
        self.sent += 1

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None

    def status(self) -> dict[str, Any]:
        return {
            "platform_id": self.connection.platform_id,
            "engaged": self.connection.manual_override,
            "streaming": self.engaged,
            "linear": self.last.linear,
            "angular": self.last.angular,
            "source": self.source,
            "sent": self.sent,
            "target": list(self.target) if self.target else None,
        }


@dataclass
class _DriveInput:
    velocity: Velocity
    at: float


class Teleop(Actor):
    """Starts a sender for each platform connection; holds the operator's inputs."""

    name = "teleop"

    def __init__(
        self,
        ctx: StationContext,
        joystick: JoystickReader | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.joystick = joystick
        self.senders: dict[str, VelocitySender] = {}
        self._drive: dict[str, _DriveInput] = {}
        self._clock = clock
        self._group: asyncio.TaskGroup | None = None
        self.last_engaged = ""

    async def run(self) -> None:
        async with asyncio.TaskGroup() as group:
            self._group = group
            self.subscribe(topics.PLATFORM_CONNECTED, self._on_connected)
            self.subscribe(topics.PLATFORM_DISCONNECTED, self._on_disconnected)
            for connection in list(self.ctx.connections.values()):
                self._start_sender(connection)
            try:
                await wait_forever()
            finally:
                self._group = None

    def _on_connected(self, link: PlatformLink) -> None:
        connection = self.ctx.connections.get(link.platform_id)
        if connection is not None and connection.session_id == link.session_id:
            self._start_sender(connection)

    def _start_sender(self, connection: PlatformConnection) -> None:
        if self._group is None or connection.closed.is_set():
            return
        platform_id = connection.platform_id
        sender = VelocitySender(
            connection, self.ctx.config.teleop, lambda: self.setpoint(platform_id)
        )
        sender.on_engaged = self._note_engaged
        self.senders[platform_id] = sender
        self._group.create_task(self._run_sender(sender), name=f"pvel:{platform_id}")

    async def _run_sender(self, sender: VelocitySender) -> None:
        try:
            await sender.run()
        finally:
            if self.senders.get(sender.connection.platform_id) is sender:
                del self.senders[sender.connection.platform_id]

    def _on_disconnected(self, link: PlatformLink) -> None:
        self._drive.pop(link.platform_id, None)

    def _note_engaged(self, platform_id: str) -> None:
        self.last_engaged = platform_id

    # ------------------------------------------------------------------ inputs

    def setpoint(self, platform_id: str) -> tuple[Velocity, str]:
        """What to stream to ``platform_id`` now, and where it came from."""
        if self.joystick is not None and self._joystick_target() == platform_id:
            velocity = self.joystick.velocity()
            if velocity is not None:
                return velocity, "joystick"
        drive = self._drive.get(platform_id)
        if drive is not None:
            if self._clock() - drive.at <= self.ctx.config.teleop.drive_timeout:
                return drive.velocity, "drive"
            return STOP, "drive timeout"
        return STOP, "idle"

    def _joystick_target(self) -> str:
        return self.ctx.config.joystick.platform or self.last_engaged

    def set_drive(self, platform_id: str, velocity: Velocity) -> None:
        self._drive[platform_id] = _DriveInput(velocity, self._clock())

    # ------------------------------------------------------------------ local API

    def _sender(self, platform_id: str) -> VelocitySender:
        sender = self.senders.get(platform_id)
        if sender is None:
            raise RpcError(NOT_CONNECTED, f"not connected to {platform_id}")
        return sender

    async def api_teleop_set(
        self, call: CallContext, platform_id: str, linear: float, angular: float
    ) -> dict[str, Any]:
        """Set the drive client's velocity for ``platform_id``; it must be repeated within
        ``teleop.drive_timeout`` or zeros are streamed. Answers what is being streamed."""
        if not (-1.0 <= linear <= 1.0 and -1.0 <= angular <= 1.0):
            raise RpcError(INVALID_PARAMS, "invalid params: linear and angular must be in [-1, 1]")
        sender = self._sender(platform_id)
        self.set_drive(platform_id, Velocity(float(linear), float(angular)))
        return sender.status()

    async def api_teleop_status(self, call: CallContext, platform_id: str) -> dict[str, Any]:
        """The local stream, and what the platform reports (its mode, motors, link counters)."""
        sender = self._sender(platform_id)
        status = sender.status()
        report = await sender.connection.call("get_telemetry_report")
        override = snapshot_from_json(report).get(Override)
        status["platform"] = {
            "mode": None if override is None else override.mode,
            "motion": report.get(Motion.NAME),
            "velocity_link": report.get(VelocityLink.NAME),
        }
        if self.joystick is not None:
            status["joystick"] = {
                "connected": self.joystick.connected.is_set(),
                "drives": self._joystick_target() == platform_id,
            }
        return status


async def async_setup(ctx: StationContext) -> None:
    joystick = JoystickReader(ctx.bus, ctx.config.joystick) if ctx.config.joystick.device else None
    teleop = Teleop(ctx, joystick)
    ctx.teleop = teleop
    ctx.api.add("teleop_set", teleop.api_teleop_set, session_required=False)
    ctx.api.add("teleop_status", teleop.api_teleop_status, session_required=False)
    if joystick is not None:
        ctx.supervisor.start(joystick)
    ctx.supervisor.start(teleop)


VELOCITY_TOS = 46 << 2
"""DSCP EF (expedited forwarding): on a link that honours DSCP (Wi-Fi WMM's voice queue) the
velocity stream goes ahead of the video (AF41), which shares the radio."""


def _expedite(transport: asyncio.DatagramTransport) -> None:
    sock = transport.get_extra_info("socket")
    if sock is not None and sock.family == socket.AF_INET:
        with contextlib.suppress(OSError):  # a platform that does not allow it still drives
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_TOS, VELOCITY_TOS)
