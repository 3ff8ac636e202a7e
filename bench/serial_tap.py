"""A pty in the middle of a serial line, for benchmarks: timestamps what the driver writes.

The driver opens :attr:`SerialTap.driver_path`; a thread copies bytes between that pty's
master and the device (the simulator's pty), and records, for every ``!`` run-time command the
driver writes, the ``perf_counter`` time at which its first byte was read at the master, and
how many run-time commands were on the line unanswered (``+``/``-``) at any moment. The thread
blocks in ``select``, so its timestamps do not wait for any event loop.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from dataclasses import dataclass


@dataclass(frozen=True)
class Command:
    first_byte_at: float
    text: str


class SerialTap:
    """Start with :meth:`start`, read :attr:`commands` and :attr:`max_outstanding`, then close."""

    def __init__(self, device_path: str) -> None:
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.driver_path = os.ttyname(self._slave)
        self.device = os.open(device_path, os.O_RDWR | os.O_NOCTTY)
        tty.setraw(self.device)
        self.commands: list[Command] = []
        self.outstanding = 0
        self.max_outstanding = 0
        self._stop_r, self._stop_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="serial-tap", daemon=True)
        self._partial = ""
        self._started_at = 0.0
        self._reply = ""

    def start(self) -> None:
        self._thread.start()

    def reset_counters(self) -> None:
        """Start counting the unanswered commands afresh (after warm-up)."""
        self.max_outstanding = self.outstanding

    def _run(self) -> None:
        fds = [self.master, self.device, self._stop_r]
        while True:
            readable, _, _ = select.select(fds, [], [])
            now = time.perf_counter()
            if self._stop_r in readable:
                return
            if self.master in readable:
                try:
                    data = os.read(self.master, 4096)
                except OSError:
                    data = b""
                if data:
                    self._from_driver(data, now)
                    os.write(self.device, data)
            if self.device in readable:
                try:
                    data = os.read(self.device, 4096)
                except OSError:
                    return
                self._from_device(data)
                os.write(self.master, data)

    def _from_driver(self, data: bytes, now: float) -> None:
        for char in data.decode("ascii", "replace"):
            if not self._partial and char == "!":
                self._started_at = now
            if self._partial or char == "!":
                if char == "\r":
                    self.commands.append(Command(self._started_at, self._partial))
                    self._partial = ""
                    self.outstanding += 1
                    self.max_outstanding = max(self.max_outstanding, self.outstanding)
                else:
                    self._partial += char

    def _from_device(self, data: bytes) -> None:
        for char in data.decode("ascii", "replace"):
            if char in "\r\n":
                if self._reply in ("+", "-") and self.outstanding > 0:
                    self.outstanding -= 1
                self._reply = ""
            elif char != "W":  # the watchdog's unsolicited W
                self._reply += char

    def close(self) -> None:
        """Stop the thread and close every descriptor. Idempotent."""
        if self._stop_w < 0:
            return
        os.write(self._stop_w, b"x")
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        for fd in (self.master, self._slave, self.device, self._stop_r, self._stop_w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._stop_w = -1
