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

import serial
import serial_asyncio

from brasidas.codecs import ax3500
from brasidas.codecs.ax3500 import Command, Exchange, LineParser, Reply
from brasidas.threads import in_daemon_thread
from platformd.context import SerialDevice

_LOGGER = logging.getLogger(__name__)

OPEN_TIMEOUT = 5.0
"""Longest wait for the port to open before the attempt is reported as hung."""
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
        self._transport: asyncio.WriteTransport | None = None
        self._exchange: Exchange | None = None
        self._reply: asyncio.Future[Reply] | None = None
        self.on_unsolicited: Callable[[], None] | None = None
        """Called when a W or an OK line arrives (the owner looks at the counters)."""

    @classmethod
    def attach(cls, device: serial.Serial, reply_timeout: float) -> SerialLink:
        """A link over an open port (from :class:`PortOpener`). Must run on the event loop."""
        link = cls(reply_timeout)
        # Usable at once: the transport's connection_made comes a loop turn later.
        link._transport = _EagerSerialTransport(asyncio.get_running_loop(), link, device)
        return link

    # ------------------------------------------------------------------ protocol callbacks

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.WriteTransport)
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
        assert self._transport is not None
        self._transport.write(data)

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


class _EagerSerialTransport(serial_asyncio.SerialTransport):  # type: ignore[misc]
    """pyserial-asyncio's transport, writing at once when nothing is queued.

    The base class queues every write for the next loop turn (a writer callback and two epoll
    changes); a command fits an idle line's buffer, so the first try is made now, as asyncio's
    own socket transports do. What does not go out (or an error) takes the queued path, which
    reports a lost port through ``connection_lost``.
    """

    def write(self, data: bytes) -> None:
        if data and not self.is_closing() and self.get_write_buffer_size() == 0:
            try:
                written = self.serial.write(data)  # non-blocking: write_timeout=0
            except (serial.SerialException, OSError):
                written = 0
            data = data[written or 0 :]
            if not data:
                return
        super().write(data)


class PortOpener:
    """Opens the configured port in a daemon thread of its own, one attempt at a time.

    An open can hang in a USB adapter's driver: each call waits at most ``timeout`` and then
    reports it (LinkError); a hung attempt is not doubled but awaited again by the next call,
    and a port it opens after everyone gave up is closed. Never blocks the event loop.
    """

    def __init__(
        self, device: SerialDevice, reply_timeout: float, timeout: float = OPEN_TIMEOUT
    ) -> None:
        self.device = device
        self.reply_timeout = reply_timeout
        self.timeout = timeout
        self._attempt: asyncio.Future[serial.Serial] | None = None

    async def open(self) -> SerialLink:
        """A link on the port; raises LinkError when it cannot be opened (or hangs)."""
        port = self.device.path
        if self._attempt is None:
            self._attempt = in_daemon_thread(f"motor-open:{port}", open_port, self.device)
        attempt = self._attempt
        try:
            async with asyncio.timeout(self.timeout):
                device = await asyncio.shield(attempt)
        except TimeoutError:
            raise LinkError(
                f"opening {port} hangs (nothing after {self.timeout:g} s); still waiting"
            ) from None
        except _OPEN_ERRORS as err:
            raise LinkError(f"cannot open {port}: {err}") from None
        finally:
            if attempt.done():
                self._attempt = None
        try:
            return SerialLink.attach(device, self.reply_timeout)
        except _OPEN_ERRORS as err:
            device.close()
            raise LinkError(f"cannot set up {port}: {err}") from None

    def close(self) -> None:
        """Give up a pending attempt: what it opens later is closed. Idempotent."""
        attempt, self._attempt = self._attempt, None
        if attempt is not None:
            attempt.add_done_callback(_close_unused)


def open_port(device: SerialDevice) -> serial.Serial:
    """Open and set up the port (blocking); a pty refusing 7E1 is opened 8N1."""
    port = device.path
    framing = (device.bytesize, device.parity, device.stopbits)
    try:
        return _open_serial(port, device.baudrate, framing)
    except _OPEN_ERRORS:
        # The kernel's ptys refuse 7 bits and parity (hardware.md); same bytes in 8N1.
        if not _is_pty(port) or framing == (8, "N", 1):
            raise
    opened = _open_serial(port, device.baudrate, (8, "N", 1))
    _LOGGER.info("%s is a pty: opened 8N1 instead of %s%s%s", port, *framing)
    return opened


def _open_serial(port: str, baudrate: int, framing: tuple[int, str, int]) -> serial.Serial:
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
        # The transport sets the timeouts again, applying every setting once more: on a pty
        # that second tcsetattr is the one refusing 7E1. Here it happens in this thread.
        device.timeout = 0
    except BaseException:
        # Settings refused after the open (a pty and 7E1) leave the port open and locked.
        device.close()
        raise
    return device


def _close_unused(attempt: asyncio.Future[serial.Serial]) -> None:
    if not attempt.cancelled() and attempt.exception() is None:
        attempt.result().close()


def _is_pty(port: str) -> bool:
    return os.path.realpath(port).startswith("/dev/pts/")
