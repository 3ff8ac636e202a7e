"""systemd's notify protocol (``Type=notify``): READY, STOPPING and watchdog pings.

The protocol is one datagram per message to the AF_UNIX socket named by ``NOTIFY_SOCKET``
(a leading ``@`` means the abstract namespace). The watchdog is pinged from the event loop,
so a loop that stops turning misses its pings and systemd restarts the daemon.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
from collections.abc import Mapping

from brasidas.actor import Actor
from brasidas.bus import Bus

_LOGGER = logging.getLogger(__name__)


class Notifier:
    """Sends notify messages; every method is a no-op when not run under systemd."""

    def __init__(self, environ: Mapping[str, str] = os.environ) -> None:
        address = environ.get("NOTIFY_SOCKET", "")
        self.address = "\0" + address[1:] if address.startswith("@") else address
        self.watchdog_interval: float | None = None
        usec = environ.get("WATCHDOG_USEC", "")
        pid = environ.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.watchdog_interval = int(usec) / 1e6 / 2  # ping at half the timeout
        self.errors = 0
        self.stopping_sent = False
        """STOPPING=1 went out: READY=1 must not follow it."""

    @property
    def enabled(self) -> bool:
        return bool(self.address)

    def notify(self, message: str) -> bool:
        if not self.address:
            return False
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
                sock.setblocking(False)  # a datagram to a local socket never blocks for long
                sock.sendto(message.encode(), self.address)
        except OSError as err:
            self.errors += 1
            _LOGGER.debug("sd_notify %r failed: %s", message, err)
            return False
        return True

    def ready(self, status: str = "") -> bool:
        """READY=1, unless the daemon was told to stop meanwhile."""
        if self.stopping_sent:
            return False
        return self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def stopping(self) -> bool:
        """STOPPING=1, once (on SIGTERM, before anything slow; again on the way down: no-op)."""
        if self.stopping_sent:
            return False
        self.stopping_sent = True
        return self.notify("STOPPING=1")

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")


class WatchdogPinger(Actor):
    """Pings systemd's watchdog from the event loop while the daemon runs."""

    name = "sd-watchdog"

    def __init__(self, bus: Bus, notifier: Notifier) -> None:
        super().__init__(bus)
        self.notifier = notifier

    async def run(self) -> None:
        interval = self.notifier.watchdog_interval
        if interval is None:
            return
        while True:
            self.notifier.watchdog()
            await asyncio.sleep(interval)
