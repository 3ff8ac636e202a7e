"""The device end of a simulated serial line that only sends (a GPS receiver, a lidar)."""

from __future__ import annotations

import contextlib
import logging
import os
import tty

_LOGGER = logging.getLogger(__name__)


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

    def close(self) -> None:
        """Close the pty (idempotent)."""
        if self.closed:
            return
        self.closed = True
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
