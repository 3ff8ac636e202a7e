"""GPS: NMEA-0183 from the serial receiver (u-blox NEO-6M, 9600 8N1) to fixes on the bus.

The reader opens ``gps.port`` with pyserial-asyncio and hands every byte to the sans-IO
:mod:`brasidas.codecs.nmea` decoder and epoch assembler. It publishes ``GPS_FIX`` once per
epoch with a fix (and the retained ``POSITION`` the beacon carries), ``GPS_FIX_LOST`` when the
receiver says it has none, falls silent for ``gps.fix_timeout`` or its port goes away, and
``GPS_STATS`` (sentences by type, drops by reason) at most once a second. A port that is
missing or vanishes is reported and reopened with capped backoff.
"""

from __future__ import annotations

import asyncio
import dataclasses
import importlib
import logging
from typing import Any

import serial

from brasidas import topics
from brasidas.actor import Actor
from brasidas.bus import Bus
from brasidas.clock import Clock, LoopClock, sleep, timeout_at
from brasidas.codecs.nmea import EpochAssembler, NmeaDecoder
from brasidas.config import GpsSection, PlatformConfig
from brasidas.messages import GpsFix, GpsFixLost, GpsStats, Position
from platformd.context import PlatformContext, SerialDevice
from platformd.serial_port import PortOpener, read_line_forever

_LOGGER = logging.getLogger(__name__)

STATS_INTERVAL = 1.0
READ_SIZE = 4096


class GpsReader(Actor):
    """Reads the receiver, publishes fixes, fix-lost events and counters."""

    name = "gps"

    def __init__(self, bus: Bus, config: GpsSection, *, clock: Clock | None = None) -> None:
        super().__init__(bus)
        self.config = config
        self.opener = PortOpener(SerialDevice(config.port, config.baudrate))
        """Opens the port off the loop (8N1, exclusive: a second reader would steal bytes)."""
        self.clock: Clock = clock or LoopClock()
        """Drives fix timeouts, the epoch assembler's deadline, stats and retries."""
        self.decoder = NmeaDecoder()
        self.assembler = EpochAssembler()
        self.fixes = 0
        self.connected = False
        self.error = ""
        self.last_fix: GpsFix | None = None
        self._has_fix = False
        self._last_fix_at = 0.0
        self._stats: GpsStats | None = None
        self._stats_at = -STATS_INTERVAL

    async def run(self) -> None:
        try:
            async with asyncio.TaskGroup() as group:
                group.create_task(self._stats_loop(), name="gps:stats")
                await read_line_forever(self)
        finally:
            self.opener.close()

    # ------------------------------------------------------------------ serial line

    def line_opened(self, device: serial.Serial) -> None:
        _LOGGER.info("GPS reading %s at %d baud", self.config.port, self.config.baudrate)
        self.connected = True
        self.error = ""
        self.decoder.reset()
        # What the line buffered before we opened it is stale (seconds-old epochs).
        device.reset_input_buffer()
        self._publish_stats()

    async def read_line(self, reader: asyncio.StreamReader) -> None:
        """Until EOF (returns) or a read error (raises OSError)."""
        while True:
            try:
                async with timeout_at(self.clock, self._next_deadline()):
                    data = await reader.read(READ_SIZE)
            except TimeoutError:
                self._on_timer()
                continue
            if not data:
                return
            self.feed(data)

    def _next_deadline(self) -> float | None:
        deadlines = [
            d
            for d in (
                self.assembler.deadline(),
                self._last_fix_at + self.config.fix_timeout if self._has_fix else None,
            )
            if d is not None
        ]
        return min(deadlines) if deadlines else None

    # ------------------------------------------------------------------ decoding (on the loop)

    def feed(self, data: bytes) -> None:
        """Bytes from the receiver; publishes what completes. Runs on the event loop."""
        now = self.clock.time()
        self.assembler.touch(now)
        for sentence in self.decoder.feed(data):
            for fix in self.assembler.feed(sentence, now):
                self._on_epoch(fix, now)

    def _on_timer(self) -> None:
        now = self.clock.time()
        for fix in self.assembler.poll(now):
            self._on_epoch(fix, now)
        if self._has_fix and now - self._last_fix_at >= self.config.fix_timeout:
            self._lose(f"no fix for {self.config.fix_timeout:g} s")

    def _on_epoch(self, fix: GpsFix | None, now: float) -> None:
        if fix is None:
            if self._has_fix:
                self._lose("receiver reports no fix")
            return
        self.fixes += 1
        self.last_fix = fix
        self._has_fix = True
        self._last_fix_at = now
        self.bus.publish(topics.GPS_FIX, fix)
        self.bus.publish(topics.POSITION, Position(fix.latitude, fix.longitude))

    def _lose(self, reason: str) -> None:
        self._has_fix = False
        _LOGGER.info("GPS fix lost: %s", reason)
        last = self.last_fix.time if self.last_fix is not None else None
        self.bus.publish(topics.GPS_FIX_LOST, GpsFixLost(reason, last))

    def line_down(self, reason: str, *, log: bool) -> None:
        self.connected = False
        self.error = reason
        if log:
            _LOGGER.warning("GPS: %s; retrying", reason)
        else:
            _LOGGER.debug("GPS: %s; retrying", reason)
        if self._has_fix:
            self._lose(reason)
        self._publish_stats()

    # ------------------------------------------------------------------ counters

    def stats(self) -> GpsStats:
        return GpsStats(
            connected=self.connected,
            port=self.config.port,
            sentences=self.decoder.sentences,
            by_type=dict(self.decoder.by_type),
            dropped=dict(self.decoder.dropped),
            fixes=self.fixes,
            incomplete_epochs=self.assembler.incomplete,
            error=self.error,
        )

    def _publish_stats(self) -> None:
        """Publish the counters if they changed, at most about once a second."""
        if self.clock.time() - self._stats_at < 0.9 * STATS_INTERVAL:
            return  # e.g. a port flapping fast: the next tick reports it
        stats = self.stats()
        if stats != self._stats:
            self._stats = stats
            self._stats_at = self.clock.time()
            self.bus.publish(topics.GPS_STATS, stats)

    async def _stats_loop(self) -> None:
        while True:
            await sleep(self.clock, STATS_INTERVAL)
            self._publish_stats()


def capabilities(config: GpsSection) -> dict[str, Any]:
    return {"port": config.port, "baudrate": config.baudrate}


def preload(config: PlatformConfig) -> None:
    """``datetime.strptime``'s module, which it imports on its first call: pynmea2's dates."""
    if config.gps.enabled:
        importlib.import_module("_strptime")


async def async_setup(ctx: PlatformContext) -> None:
    if not ctx.config.gps.enabled:
        return
    section = dataclasses.replace(ctx.config.gps, port=ctx.gps_port)  # the simulator's in --sim
    reader = GpsReader(ctx.bus, section)
    ctx.capabilities.register("gps", lambda: capabilities(section))
    ctx.supervisor.start(reader)
