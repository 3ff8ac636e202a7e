"""The turret's microcontroller, simulated on a pty (``brasidas-platform simulate turret``).

:class:`TurretDevice` is the firmware, pure: ``feed(bytes, now)`` answers lines, ``tick(now)``
runs the watchdog. :class:`TurretSimulator` serves it on a pty on the event loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
import tty

from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.codecs import turret
from brasidas.codecs.turret import AZIMUTH_RANGE, ELEVATION_RANGE, Line, LineDecoder
from brasidas.config import PlatformConfig
from brasidas.config.platform import PayloadSection
from platformd.sim.owner import SimulatorOwner


class TurretDevice:
    """Servos, trigger, watchdog; remembers every command it acted on (``log``)."""

    def __init__(self, watchdog_s: float = 0.5) -> None:
        self.watchdog_s = watchdog_s
        self.azimuth = 0.0
        self.elevation = 0.0
        self.trigger = False
        self.decoder = LineDecoder()
        self.log: list[str] = []
        """Commands acted on (not repeats), e.g. ``FIRE``, ``AIM,10.0,5.0``."""
        self.watchdog_releases = 0
        self.ignore_next = 0
        """Tests: drop this many valid commands without acting or answering (a lost line)."""
        self._last_valid: float | None = None
        self._answers: dict[int, bytes] = {}
        self._last_seq: int | None = None

    def feed(self, data: bytes, now: float) -> bytes:
        out = b""
        for item in self.decoder.feed(data):
            if isinstance(item, Line) and item.kind == "C":
                out += self._command(item, now)
        return out

    def tick(self, now: float) -> bytes:
        """The watchdog: no valid command for ``watchdog_s`` releases the trigger."""
        if (
            self.trigger
            and self._last_valid is not None
            and now - self._last_valid >= self.watchdog_s
        ):
            self.trigger = False
            self.watchdog_releases += 1
            self.log.append("WATCHDOG")
            return turret.encode("W", f"{self.azimuth:.1f}", f"{self.elevation:.1f}")
        return b""

    def _command(self, line: Line, now: float) -> bytes:
        if self.ignore_next > 0:
            self.ignore_next -= 1
            return b""
        try:
            seq = int(line.fields[0])
            name = line.fields[1]
        except (IndexError, ValueError):
            return b""
        self._last_valid = now
        repeat = self._answers.get(seq)
        if repeat is not None and self._last_seq == seq:
            return repeat  # a resend: its acknowledgement was lost, do not act twice
        self._last_seq = seq
        answer = self._act(seq, name, line.fields[2:])
        self._answers = {seq: answer}
        return answer

    def _act(self, seq: int, name: str, args: tuple[str, ...]) -> bytes:
        if name == "AIM":
            try:
                azimuth, elevation = float(args[0]), float(args[1])
            except (IndexError, ValueError):
                return turret.encode("A", seq, "ERR", "bad arguments")
            if not (AZIMUTH_RANGE[0] <= azimuth <= AZIMUTH_RANGE[1]) or not (
                ELEVATION_RANGE[0] <= elevation <= ELEVATION_RANGE[1]
            ):
                return turret.encode("A", seq, "ERR", "out of range")
            self.azimuth, self.elevation = azimuth, elevation
        elif name == "FIRE":
            self.trigger = True
        elif name == "SAFE":
            self.trigger = False
        elif name != "PING":
            return turret.encode("A", seq, "ERR", "unknown command")
        if name != "PING":
            self.log.append(",".join((name, *args)))
        return turret.encode(
            "A", seq, "OK", f"{self.azimuth:.1f}", f"{self.elevation:.1f}", int(self.trigger)
        )


class TurretSimulator:
    """The device on a pty: :meth:`start` on the event loop, :meth:`close` when done."""

    def __init__(self, device: TurretDevice | None = None) -> None:
        self.device = device or TurretDevice()
        self.path = ""
        self.corrupt_next = 0
        """Tests: flip a checksum digit of this many answers (noise on the line)."""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self._timer: asyncio.TimerHandle | None = None

    def start(self) -> None:
        """Create the pty. Must run on the event loop."""
        self._loop = asyncio.get_running_loop()
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.path = os.ttyname(slave)
        self._loop.add_reader(master, self._on_readable)
        self._arm()

    def close(self) -> None:
        """Remove the pty. Idempotent."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._master is not None and self._loop is not None:
            self._loop.remove_reader(self._master)
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None

    def _on_readable(self) -> None:
        assert self._loop is not None and self._master is not None
        try:
            data = os.read(self._master, 4096)
        except OSError:
            return
        self._write(self.device.feed(data, self._loop.time()))

    def _arm(self) -> None:
        assert self._loop is not None
        self._timer = self._loop.call_later(self.device.watchdog_s / 5, self._on_timer)

    def _on_timer(self) -> None:
        assert self._loop is not None
        self._write(self.device.tick(self._loop.time()))
        self._arm()

    def _write(self, data: bytes) -> None:
        if not data or self._master is None:
            return
        if self.corrupt_next > 0 and data.startswith(b"$A"):
            self.corrupt_next -= 1
            star = data.rindex(b"*")
            digit = b"0" if data[star + 1 : star + 2] != b"0" else b"1"
            data = data[: star + 1] + digit + data[star + 2 :]
        with contextlib.suppress(OSError):
            os.write(self._master, data)


async def serve(config: PlatformConfig) -> None:
    """``brasidas-platform simulate turret``: the pty path on stdout's first line, then serve."""
    simulator = TurretSimulator(TurretDevice(config.payload.turret_watchdog_s))
    simulator.start()
    try:
        sys.stdout.write(simulator.path + "\n")
        sys.stdout.flush()
        await asyncio.Event().wait()
    finally:
        simulator.close()


def start_simulator(bus: Bus, supervisor: Supervisor, payload: PayloadSection) -> TurretSimulator:
    """In ``--sim``: the turret's microcontroller on a pty (``ctx.sim.turret.path``)."""
    simulator = TurretSimulator(TurretDevice(payload.turret_watchdog_s))
    simulator.start()
    supervisor.start(SimulatorOwner(bus, "sim:turret", simulator))
    return simulator
