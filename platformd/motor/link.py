"""The serial link to the AX3500: one open connection, one command in flight.

pyserial-asyncio's callbacks only feed the sans-IO codec (:mod:`brasidas.codecs.ax3500`);
:meth:`SerialLink.request` sends one command and waits for its answer.
"""

from __future__ import annotations

import asyncio
import logging
import os
import termios
from collections.abc import Callable
from enum import Enum
from typing import Any

import serial
import serial_asyncio

from brasidas.codecs import ax3500
from brasidas.codecs.ax3500 import Command, Exchange, LineParser, Reply
from brasidas.config import MotorSection

_LOGGER = logging.getLogger(__name__)

_OPEN_ERRORS = (serial.SerialException, OSError, ValueError, termios.error)
"""What opening a port raises: missing device, busy, refused settings (a pty and 7E1)."""


class LinkError(Exception):
    """The link is unusable: port gone, I/O error, controller silent or in the wrong mode."""


class ReplyTimeout(Exception):
    """One command got no complete answer in time."""


class LinkState(Enum):
    OPEN = "open"
    CLOSED = "closed"


class SerialLink(asyncio.Protocol):
    """One open serial connection to the controller; single use, one command in flight."""

    def __init__(self, reply_timeout: float) -> None:
        self.reply_timeout = reply_timeout
        self.state = LinkState.OPEN
        self.parser = LineParser()
        self.banner = asyncio.Event()
        """Set when an ``OK`` line arrives outside an answer (power-up, reset, RS-232 switch)."""
        self.closed_reason = ""
        self.stray_lines = 0
        self.banners = 0
        self._transport: asyncio.BaseTransport | None = None
        self._device: serial.Serial | None = None
        self._exchange: Exchange | None = None
        self._reply: asyncio.Future[Reply] | None = None
        self.on_unsolicited: Callable[[], None] | None = None
        """Called when a W or an OK line arrives (the owner looks at the counters)."""

    @classmethod
    async def open(cls, config: MotorSection) -> SerialLink:
        """Open the configured port (a pty refusing 7E1 is opened 8N1); raises LinkError."""
        loop = asyncio.get_running_loop()
        link = cls(config.reply_timeout)
        framing = (config.bytesize, config.parity, config.stopbits)
        try:
            await _create(loop, link, config.port, config.baudrate, framing)
        except _OPEN_ERRORS as err:
            # The kernel's ptys refuse 7 bits and parity (hardware.md); same bytes in 8N1.
            if not _is_pty(config.port) or framing == (8, "N", 1):
                raise LinkError(f"cannot open {config.port}: {err}") from None
            try:
                await _create(loop, link, config.port, config.baudrate, (8, "N", 1))
            except _OPEN_ERRORS as second:
                raise LinkError(f"cannot open {config.port}: {second}") from None
            _LOGGER.info("%s is a pty: opened 8N1 instead of %s%s%s", config.port, *framing)
        return link

    # ------------------------------------------------------------------ protocol callbacks

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = transport

    def data_received(self, data: bytes) -> None:
        watchdog, banners = self.parser.watchdog_chars, self.banners
        for line in self.parser.feed(data):
            self._on_line(line)
        changed = self.parser.watchdog_chars != watchdog or self.banners != banners
        if changed and self.on_unsolicited is not None:
            self.on_unsolicited()

    def connection_lost(self, exc: Exception | None) -> None:
        self._closed(f"port lost: {exc}" if exc else "port closed")

    def _on_line(self, line: str) -> None:
        exchange = self._exchange
        if exchange is not None:
            strays = len(exchange.stray)
            reply = exchange.feed_line(line)
            if len(exchange.stray) == strays:  # the line was the exchange's
                if reply is not None and self._reply is not None and not self._reply.done():
                    self._reply.set_result(reply)
                return
        self.stray_lines += 1
        if line == ax3500.BANNER_OK:
            self.banners += 1
            self.banner.set()

    # ------------------------------------------------------------------ requests

    async def request(self, command: Command) -> Reply:
        """Send ``command`` and wait for its answer; raises ReplyTimeout or LinkError."""
        if self.state is LinkState.CLOSED or self._transport is None:
            raise LinkError(self.closed_reason or "link closed")
        if self._exchange is not None:
            raise RuntimeError("one command in flight at a time")
        self._exchange = Exchange(command)
        reply: asyncio.Future[Reply] = asyncio.get_running_loop().create_future()
        self._reply = reply
        try:
            self._write(command.encode())
            async with asyncio.timeout(self.reply_timeout):
                return await reply
        except TimeoutError:
            raise ReplyTimeout(command.text) from None
        finally:
            self._exchange = None
            self._reply = None

    def write_raw(self, data: bytes) -> None:
        """Bytes that expect no answer (the ten carriage returns)."""
        if self._transport is None or self.state is LinkState.CLOSED:
            raise LinkError(self.closed_reason or "link closed")
        self._write(data)

    def _write(self, data: bytes) -> None:
        transport: Any = self._transport
        device = self._device
        if device is not None and transport.get_write_buffer_size() == 0:
            # pyserial-asyncio queues every write for the next loop turn (a writer callback
            # and two epoll changes); a command fits the idle line's buffer, so write now.
            try:
                written = device.write(data)  # non-blocking: write_timeout=0
            except serial.SerialException as err:
                self._closed(f"port lost: {err}")  # fails the pending answer, if any
                return
            data = data[written or 0 :]
            if not data:
                return
        transport.write(data)

    async def wait_banner(self, timeout: float) -> bool:
        """Wait for an ``OK`` line (clear :attr:`banner` before provoking it)."""
        try:
            async with asyncio.timeout(timeout):
                await self.banner.wait()
        except TimeoutError:
            return False
        return True

    def close(self) -> None:
        """Close the port, failing a pending request. Idempotent."""
        self._closed("closed by the driver")

    def _closed(self, reason: str) -> None:
        if self.state is LinkState.CLOSED:
            return
        self.state = LinkState.CLOSED
        self.closed_reason = reason
        if self._reply is not None and not self._reply.done():
            self._reply.set_exception(LinkError(reason))
        if self._transport is not None:
            self._transport.close()


async def _create(
    loop: asyncio.AbstractEventLoop,
    link: SerialLink,
    port: str,
    baudrate: int,
    framing: tuple[int, str, int],
) -> None:
    bytesize, parity, stopbits = framing
    device = serial.serial_for_url(
        port,
        baudrate=baudrate,
        bytesize=bytesize,
        parity=parity,
        stopbits=stopbits,
        timeout=0,
        write_timeout=0,
        # flock: a second daemon (or any program asking for exclusivity) cannot drive the
        # same controller at the same time.
        exclusive=True,
        do_not_open=True,
    )
    try:
        device.open()
        transport, _ = await serial_asyncio.connection_for_serial(loop, lambda: link, device)
    except BaseException:
        # Settings refused after the open (a pty and 7E1) leave the port open and locked.
        device.close()
        raise
    link._transport = transport  # connection_made comes a loop turn later: usable at once
    link._device = device


def _is_pty(port: str) -> bool:
    return os.path.realpath(port).startswith("/dev/pts/")
