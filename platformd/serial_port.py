"""Opening a serial port off the event loop: the one way every driver opens its line.

An open can hang in a USB adapter's driver (the call blocks in the kernel): it runs in a
daemon thread of its own, and the caller waits at most a few seconds for it.
:func:`read_line_forever` is the receive-only sensors' loop (GPS, lidar): open, read until
the line closes or fails, back off, open again.
"""

from __future__ import annotations

import asyncio
import logging
import os
import termios
from typing import NoReturn, Protocol

import serial
import serial_asyncio

from brasidas.backoff import Backoff
from brasidas.clock import Clock, sleep
from brasidas.threads import in_daemon_thread
from platformd.context import SerialDevice

_LOGGER = logging.getLogger(__name__)

OPEN_TIMEOUT = 5.0
"""Longest wait for the port to open before the attempt is reported as hung."""
OPEN_ERRORS = (serial.SerialException, OSError, ValueError, termios.error)
"""What opening a port raises: missing device, busy, refused settings (a pty and 7E1)."""
READ_BACKOFF_INITIAL = 0.2
READ_BACKOFF_MAX = 5.0
"""Seconds before a sensor's line is opened again (doubling; reset once it was open)."""


class PortError(Exception):
    """The port cannot be opened, or its open hangs (the message says which)."""


class PortOpener:
    """Opens one port in a daemon thread of its own, one attempt at a time.

    Each call waits at most ``timeout`` and then reports the hang (PortError); a hung attempt
    is not doubled but awaited again by the next call, and a port it opens after everyone
    gave up is closed. Never blocks the event loop.
    """

    def __init__(self, device: SerialDevice, timeout: float = OPEN_TIMEOUT) -> None:
        self.device = device
        self.timeout = timeout
        self._attempt: asyncio.Future[serial.Serial] | None = None

    async def open(self) -> serial.Serial:
        """The open port (non-blocking reads: ``timeout=0``); raises PortError."""
        port = self.device.path
        if self._attempt is None:
            self._attempt = in_daemon_thread(f"open:{port}", open_port, self.device)
        attempt = self._attempt
        try:
            async with asyncio.timeout(self.timeout):
                return await asyncio.shield(attempt)
        except TimeoutError:
            raise PortError(
                f"opening {port} hangs (nothing after {self.timeout:g} s); still waiting"
            ) from None
        except OPEN_ERRORS as err:
            raise PortError(f"cannot open {port}: {err}") from None
        finally:
            if attempt.done():
                self._attempt = None

    def close(self) -> None:
        """Give up a pending attempt: what it opens later is closed. Idempotent."""
        attempt, self._attempt = self._attempt, None
        if attempt is not None:
            attempt.add_done_callback(_close_unused)


class LineReader(Protocol):
    """A sensor that only listens on its line (the GPS, the lidar), as
    :func:`read_line_forever` drives it."""

    opener: PortOpener
    clock: Clock

    def line_opened(self, device: serial.Serial) -> None:
        """The line is open (``device``): reset what the last one left."""

    async def read_line(self, reader: asyncio.StreamReader) -> None:
        """Until the line closes (returns) or fails (raises OSError)."""

    def line_down(self, reason: str, *, log: bool) -> None:
        """The line cannot be opened, or is gone; ``log``: say so as a warning."""


async def read_line_forever(sensor: LineReader) -> NoReturn:
    """Open the sensor's line, read it until it closes or fails, and again after a backoff.
    ``line_down``'s ``log`` is set for the first of a row of failures to open and for every
    loss (a port that just went away: reported once, then retried quietly)."""
    backoff = Backoff(READ_BACKOFF_INITIAL, READ_BACKOFF_MAX)
    port = sensor.opener.device.path
    failures = 0
    while True:
        try:
            device = await sensor.opener.open()
        except PortError as err:
            failures += 1
            sensor.line_down(str(err), log=failures == 1)
            await sleep(sensor.clock, backoff.next())
            continue
        try:
            reader, writer = streams(device)
        except OPEN_ERRORS as err:
            device.close()
            failures += 1
            sensor.line_down(f"cannot set up {port}: {err}", log=failures == 1)
            await sleep(sensor.clock, backoff.next())
            continue
        sensor.line_opened(device)
        try:
            await sensor.read_line(reader)
            reason = f"{port} closed"
        except OSError as err:
            reason = f"{port} lost: {err}"
        finally:
            writer.close()
        failures = 1
        sensor.line_down(reason, log=True)
        backoff.reset()
        await sleep(sensor.clock, backoff.next())


def streams(device: serial.Serial) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """A reader and writer over a port already open (from :class:`PortOpener`)."""
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader(loop=loop)
    protocol = asyncio.StreamReaderProtocol(reader, loop=loop)
    transport = serial_asyncio.SerialTransport(loop, protocol, device)
    return reader, asyncio.StreamWriter(transport, protocol, reader, loop)


def open_port(device: SerialDevice) -> serial.Serial:
    """Open and set up the port (blocking); a pty refusing 7E1 is opened 8N1."""
    port = device.path
    framing = (device.bytesize, device.parity, device.stopbits)
    try:
        return _open_serial(port, device.baudrate, framing)
    except OPEN_ERRORS:
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
