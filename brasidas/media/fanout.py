"""Streams sent to several UDP destinations at once, each station its own (``multiudpsink``).

The NavCam, the microphone and the payload camera end in one ``multiudpsink`` whose
``clients`` are every destination asked for: adding or removing one changes the property
live, so a second station's start never takes the stream from the first and one station's
stop never stops another's copy, and a destination that fails (no route) fails its own packets
only, never the sink.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from brasidas.media.gst import make
from brasidas.media.pipeline import PipelineStream


@dataclass
class Destinations:
    """Where a fan-out stream goes: ``host:port`` first, then ``extra``. Settings inherit it."""

    host: str = "127.0.0.1"
    port: int = 5600
    extra: tuple[tuple[str, int], ...] = ()
    """Further destinations (other stations), each sent the same packets."""

    def clients(self) -> str:
        """Every destination as ``multiudpsink``'s ``clients``: ``host:port,host:port``."""
        return ",".join(f"{host}:{port}" for host, port in ((self.host, self.port), *self.extra))


D = TypeVar("D", bound=Destinations)


class FanOutStream(PipelineStream, Generic[D]):
    """A stream whose pipeline ends in :meth:`make_sink`; destinations change live."""

    def __init__(self, name: str, settings: D, **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        self.settings = settings
        self.nowhere = False
        """Sent to nobody: the pipeline runs for a local consumer (the recorder's copy)."""
        self._sink: Any = None

    def destination(self) -> str:
        if self.nowhere:
            return "nowhere (recorded only)"
        return f"{self.settings.host}:{self.settings.port}"

    def set_destinations(self, destinations: list[tuple[str, int]]) -> None:
        """Send to each of ``destinations`` (none: to nobody, for a local consumer such as the
        recorder; the settings keep the last ones); applied live. Event loop."""
        s = self.settings
        self.nowhere = not destinations
        if destinations:
            (s.host, s.port), s.extra = destinations[0], tuple(destinations[1:])
        if self._sink is not None:
            self._sink.set_property("clients", self._clients())

    def bytes_sent_to(self, host: str, port: int) -> int:
        """Bytes sent to ``host:port`` since it became a destination (``multiudpsink``'s own
        count; 0 when it is none or the pipeline is down)."""
        sink = self._sink
        if sink is None:
            return 0
        stats = sink.emit("get-stats", host, port)
        if stats is None:
            return 0
        found, value = stats.get_uint64("bytes-sent")
        return int(value) if found else 0

    def _clients(self) -> str:
        return "" if self.nowhere else self.settings.clients()

    def describe(self) -> dict[str, Any]:
        s = self.settings
        return {
            **super().describe(),
            "host": s.host,
            "port": s.port,
            "destinations": self._clients().split(",") if not self.nowhere else [],
        }

    def make_sink(self) -> Any:
        """The pipeline's last element, sending to every destination (kept for live changes)."""
        # auto-multicast off: a sender needs no group membership, and joining one the host has
        # no route for fails the whole sink, every station's copy with it.
        self._sink = make(
            "multiudpsink",
            "sink",
            clients=self._clients(),
            sync=False,
            async_=False,
            auto_multicast=False,
        )
        return self._sink

    def on_torn_down(self) -> None:
        self._sink = None
