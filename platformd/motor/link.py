"""The serial link to the AX3500: one open connection, one command in flight.

pyserial-asyncio's callbacks only feed the sans-IO codec (:mod:`brasidas.codecs.ax3500`);
:meth:`SerialLink.request` sends one command and waits for its answer.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from enum import Enum

import serial
import serial_asyncio

from brasidas.clock import Clock, LoopClock, running_timeout
from brasidas.codecs import ax3500
from brasidas.codecs.ax3500 import Command, Exchange, LineParser, Reply
from platformd.serial_port import OPEN_ERRORS

_LOGGER = logging.getLogger(__name__)

REPLY_CHECKS = 6
"""A reply's wait is checked this many times: a stall of the event loop costs it one check."""
REPLY_MOST = 5
"""However stalled the loop, a reply is given up after this many reply timeouts."""


class LinkError(Exception):
    """The link is unusable: port gone, I/O error, controller silent or in the wrong mode."""


class ReplyTimeout(Exception):
    """One command got no complete answer in time."""


class LinkState(Enum):
    OPEN = "open"
    CLOSED = "closed"


class SerialLink(asyncio.Protocol):
    """One open serial connection to the controller; single use, one command in flight."""

    def __init__(self, reply_timeout: float, clock: Clock | None = None) -> None:
        self.reply_timeout = reply_timeout
        self.clock: Clock = clock or LoopClock()
        """Times the replies (real time: the answer comes over a real line)."""
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
    def attach(
        cls, device: serial.Serial, reply_timeout: float, clock: Clock | None = None
    ) -> SerialLink:
        """A link over an open port (from :class:`PortOpener`). Must run on the event loop."""
        link = cls(reply_timeout, clock)
        try:
            # Usable at once: the transport's connection_made comes a loop turn later.
            link._transport = _EagerSerialTransport(asyncio.get_running_loop(), link, device)
        except OPEN_ERRORS as err:
            device.close()
            raise LinkError(f"cannot set up {device.port}: {err}") from None
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
        """Send ``command`` and wait for its answer; raises ReplyTimeout or LinkError.

        The wait is ``reply_timeout`` of time the event loop could run: while something else
        blocks the loop the answer waits unread (on the real line, in the kernel's buffer; from
        the simulator, which shares the loop, not even written yet), and that is no silence of
        the controller's. A blocked loop at the start (setups importing their modules) timed
        the first probe out, and the bring-up then waited 3 s for a banner."""
        if self.state is LinkState.CLOSED or self._transport is None:
            raise LinkError(self.closed_reason or "link closed")
        if self._exchange is not None:
            raise RuntimeError("one command in flight at a time")
        self._exchange = Exchange(command)
        reply: asyncio.Future[Reply] = asyncio.get_running_loop().create_future()
        self._reply = reply
        try:
            self._write(command.encode())
            timeout = self.reply_timeout
            async with running_timeout(
                self.clock, timeout, step=timeout / REPLY_CHECKS, most=timeout * REPLY_MOST
            ):
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
