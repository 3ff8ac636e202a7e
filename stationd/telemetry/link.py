"""One platform's telemetry link: verify datagrams, merge the snapshot, announce warnings.

The core (:meth:`TelemetryLink.feed`, :meth:`TelemetryLink.tick`) is sans-IO with an injected
clock; the class is also the asyncio datagram protocol of the receiving socket.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import Any

from brasidas.annunciator import Annunciator, Change
from brasidas.codecs.telemetry import TelemetryDecoder
from brasidas.codecs.telemetry_schema import (
    SCHEMA_VERSION,
    Failsafe,
    Section,
    SectionValue,
    Snapshot,
    snapshot_from_wire,
    snapshot_to_json,
)
from brasidas.config import TelemetryReceiverSection
from brasidas.messages import StationNotification, TelemetrySnapshot
from stationd.telemetry.stats import LinkStats

_LOGGER = logging.getLogger(__name__)


def version_mismatch(theirs: object) -> str:
    """The operator's message when a platform speaks another telemetry schema."""
    return (
        f"the platform sends telemetry schema v{theirs}; this station reads v{SCHEMA_VERSION}"
        " (update the older of the two)"
    )


class TelemetryLink(asyncio.DatagramProtocol):
    """Receives and verifies one platform's telemetry; keeps its snapshot and warnings."""

    def __init__(
        self,
        platform_id: str,
        session_key: bytes | None,
        config: TelemetryReceiverSection,
        publish: Callable[[StationNotification], None],
        *,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
        on_controller: Callable[[str | None], None] = lambda _controller: None,
        on_snapshot: Callable[[TelemetrySnapshot], None] = lambda _snapshot: None,
    ) -> None:
        self.platform_id = platform_id
        self.decoder = TelemetryDecoder(platform_id, session_key)
        self.config = config
        self.stats = LinkStats(config.loss_window)
        self.annunciator = Annunciator(config)
        self.sections: dict[type[Section], SectionValue] = {}
        """The latest value of every section received (datagrams carry subsets)."""
        self.unknown_sections = 0
        """Section keys this station's schema does not know (counted, ignored)."""
        self.platform_time: float | None = None
        self.bytes_received = 0
        self.max_datagram = 0
        self.error = ""
        """Why there is no stream (the platform refused request_telemetry), if so."""
        self.round_trip_ms: float | None = None
        self._publish = publish
        self.on_controller = on_controller
        """Called with the station holding control whenever a datagram says who does (the
        platform pushes one at once when control changes hands)."""
        self.on_snapshot = on_snapshot
        """Called with the merged snapshot after every accepted datagram (published on the
        station's bus: what Foxglove live projects)."""
        self._clock = clock
        self._wall_clock = wall_clock
        self.transport: asyncio.DatagramTransport | None = None

    # asyncio protocol

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self.feed(data)

    def error_received(self, exc: Exception) -> None:
        _LOGGER.debug("telemetry socket of %s: %s", self.platform_id, exc)

    # sans-IO core

    def feed(self, data: bytes, now: float | None = None) -> bool:
        """One datagram; returns whether it was accepted."""
        now = self._clock() if now is None else now
        frames = self.decoder.feed(data)
        if not frames:
            return False
        frame = frames[0]
        snapshot, unknown = snapshot_from_wire(frame.sections)
        self.sections.update(snapshot.sections)
        self.unknown_sections += len(unknown)
        self.platform_time = frame.timestamp
        self.bytes_received += frame.size
        self.max_datagram = max(self.max_datagram, frame.size)
        self.stats.accepted(frame.seq, now)
        self.tick(now)
        failsafe = snapshot.get(Failsafe)
        if failsafe is not None:
            self.on_controller(failsafe.controller)
        # A copy: the link keeps merging into its own dict.
        merged = Snapshot(dict(self.sections))
        self.on_snapshot(TelemetrySnapshot(self.platform_id, merged, int(self._wall_clock() * 1e9)))
        return True

    def tick(self, now: float | None = None) -> list[Change]:
        """Re-evaluate the annunciator (silence grows without datagrams)."""
        now = self._clock() if now is None else now
        changes = self.annunciator.evaluate(
            self.snapshot, self.stats.loss_pct, self.stats.silence(now), now
        )
        self._announce(changes)
        return changes

    def close(self) -> None:
        """Clear every warning (announced) and close the socket. Idempotent."""
        self._announce(self.annunciator.clear_all())
        if self.transport is not None:
            self.transport.close()
            self.transport = None

    def _announce(self, changes: list[Change]) -> None:
        for change in changes:
            warning = change.warning
            log = _LOGGER.warning if change.active else _LOGGER.info
            log(
                "%s: %s %s",
                self.platform_id,
                "WARNING" if change.active else "cleared:",
                warning.message,
            )
            self._publish(
                StationNotification(
                    warning.code,
                    self.platform_id,
                    warning.name,
                    change.active,
                    warning.message,
                    self._wall_clock(),
                )
            )

    @property
    def snapshot(self) -> Snapshot:
        return Snapshot(self.sections)

    @property
    def schema_error(self) -> str:
        """Why this station cannot read the platform's telemetry (another schema), if so."""
        theirs = self.decoder.foreign_version
        if theirs is None or self.decoder.accepted:
            return ""
        return version_mismatch(theirs)

    def link(self, now: float | None = None) -> dict[str, Any]:
        now = self._clock() if now is None else now
        silence = self.stats.silence(now)
        return {
            "received": self.stats.received,
            "rejected": {k: v for k, v in self.decoder.rejected.items()},
            "rejected_total": sum(self.decoder.rejected.values()),
            "loss_pct": self.stats.loss_pct,
            "silence_s": None if silence is None else round(silence, 2),
            "last_seq": self.stats.last_seq,
            "bytes_received": self.bytes_received,
            "max_datagram": self.max_datagram,
            "round_trip_ms": None if self.round_trip_ms is None else round(self.round_trip_ms, 2),
            "unknown_sections": self.unknown_sections,
            "error": self.error or self.schema_error,
        }

    def report(self, now: float | None = None) -> dict[str, Any]:
        now = self._clock() if now is None else now
        self.tick(now)
        return {
            "platform_id": self.platform_id,
            "schema": SCHEMA_VERSION,
            "snapshot": snapshot_to_json(self.sections),
            "platform_time": self.platform_time,
            "link": self.link(now),
            "warnings": [w.as_dict() for w in self.annunciator.active.values()],
        }
