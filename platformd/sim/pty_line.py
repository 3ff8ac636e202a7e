"""The device end of a simulated serial line that only sends (a GPS receiver, a lidar)."""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import logging
import os
import struct
import termios
import tty

_LOGGER = logging.getLogger(__name__)
DRAIN_TIMEOUT_S = 2.0
DRAIN_POLL_S = 0.02
DRAIN_SETTLE_S = 0.1


class PtyLine:
    """A raw pty: the driver opens ``path``; :meth:`write` never blocks. Bytes nobody reads
    are lost and counted in ``overruns``, as on a UART."""

    def __init__(self, device: str) -> None:
        self.device = device
        """What sends, for the log ("simulated GPS")."""
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        self.overruns = 0
        self.closed = False

    def write(self, data: bytes) -> None:
        if self.closed or not data:
            return
        try:
            os.write(self._master, data)
        except BlockingIOError:
            self.overruns += 1  # nobody reads the line
        except OSError as err:
            self.overruns += 1
            _LOGGER.debug("%s write failed: %s", self.device, err)

    async def drained(self, timeout: float = DRAIN_TIMEOUT_S) -> None:
        """Until the driver has read what was written (at most ``timeout``): closing drops
        what is still queued for it, which a driver slowed by a busy CPU had not read yet."""
        # What was just written reaches the other end's queue through the kernel's work
        # queue, not at once (~1 ms, more on a busy CPU): counted from there. Then polled:
        # the kernel tells no one when the other end reads.
        await asyncio.sleep(DRAIN_SETTLE_S)
        for _ in range(max(1, round(timeout / DRAIN_POLL_S))):
            if self.closed or not self.queued():
                return
            await asyncio.sleep(DRAIN_POLL_S)

    def queued(self) -> int:
        """Bytes written and not read yet."""
        try:
            answer = fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0")
        except OSError:
            return 0
        return int(struct.unpack("i", answer)[0])

    def close(self) -> None:
        """Close the pty (idempotent)."""
        if self.closed:
            return
        self.closed = True
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
