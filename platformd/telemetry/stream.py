"""The push streams: one authenticated datagram stream per station session, paused while the
session is silent (its link lost) and resumed with its next call."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from collections.abc import Callable
from typing import Any

from brasidas.codecs.jsonrpc import UNAVAILABLE, RpcError
from brasidas.codecs.telemetry import TelemetryEncoder

_LOGGER = logging.getLogger(__name__)


@dataclasses.dataclass(eq=False)
class TelemetryStream:
    """One station's telemetry stream (one per session)."""

    session_id: str
    address: tuple[str, int]
    rate_hz: float
    encoder: TelemetryEncoder
    task: asyncio.Task[None] | None = None
    sent: int = 0
    max_size: int = 0


class StreamSender:
    """Runs the streams in the owner's task group over one UDP socket; counts what it sends.

    ``snapshot`` builds the sections of one datagram burst; ``clock`` is the wall clock
    (datagram timestamps and the first sequence number of a fresh encoder).
    """

    def __init__(
        self,
        platform_id: str,
        snapshot: Callable[[], dict[str, Any]],
        clock: Callable[[], float],
        live: Callable[[str], bool] = lambda _session_id: True,
    ) -> None:
        self.platform_id = platform_id
        self._snapshot = snapshot
        self._clock = clock
        self._live = live
        """Whether a session still hears us (its heartbeats): a silent one's stream pauses."""
        self.streams: dict[str, TelemetryStream] = {}
        self.counters: dict[str, int] = {
            "datagrams_sent": 0,
            "send_errors": 0,
            "trimmed_sections": 0,
            "paused_snapshots": 0,
        }
        self._group: asyncio.TaskGroup | None = None
        self._transport: asyncio.DatagramTransport | None = None

    def attach(self, group: asyncio.TaskGroup, transport: asyncio.DatagramTransport) -> None:
        """Streams run in ``group`` and send through ``transport`` from now on."""
        self._group = group
        self._transport = transport

    def detach(self) -> None:
        """The owner stopped: forget the streams (their tasks ended with the group)."""
        self._group = None
        self._transport = None
        self.streams.clear()

    def start_stream(
        self, session_id: str, key: bytes | None, address: tuple[str, int], rate_hz: float
    ) -> TelemetryStream:
        """(Re)start the stream of ``session_id``; must be called on the event loop."""
        if self._group is None or self._transport is None:
            raise RpcError(UNAVAILABLE, "telemetry is not running")
        previous = self.streams.get(session_id)
        self.stop_stream(session_id)
        # A new request in the same session continues the sequence: the station's replay
        # check stays meaningful across re-requests.
        # A fresh encoder (new session, or this actor restarted) starts from the wall clock in
        # ms, above any sequence number an earlier encoder of the session can have reached.
        encoder = (
            previous.encoder
            if previous is not None
            else TelemetryEncoder(self.platform_id, key, first_seq=int(self._clock() * 1000))
        )
        stream = TelemetryStream(session_id, address, rate_hz, encoder)
        stream.task = self._group.create_task(
            self._stream(stream), name=f"telemetry:{session_id[:8]}"
        )
        self.streams[session_id] = stream
        _LOGGER.info("telemetry to %s:%d at %.1f Hz", address[0], address[1], rate_hz)
        return stream

    def stop_stream(self, session_id: str) -> bool:
        stream = self.streams.pop(session_id, None)
        if stream is None:
            return False
        if stream.task is not None:
            stream.task.cancel("session closed")
        return True

    async def _stream(self, stream: TelemetryStream) -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / stream.rate_hz
        due = loop.time()
        while True:
            self._send_if_live(stream)
            due += period
            delay = due - loop.time()
            if delay < 0:  # fell behind (a stalled loop): skip, never burst
                due = loop.time()
                delay = 0.0
            await asyncio.sleep(delay)

    def push(self) -> None:
        """One snapshot to every stream now, between their periodic ones (an event)."""
        if self._transport is None:
            return
        for stream in list(self.streams.values()):
            self._send_if_live(stream)

    def _send_if_live(self, stream: TelemetryStream) -> None:
        # A session that lost its link hears nothing: no datagrams into the void until its
        # heartbeats return (the stream then resumes by itself) or it ends.
        if self._live(stream.session_id):
            self.send_snapshot(stream)
        else:
            self.counters["paused_snapshots"] += 1

    def send_snapshot(self, stream: TelemetryStream) -> int:
        """Encode and send one snapshot to ``stream``; returns the number of datagrams."""
        assert self._transport is not None
        encoder = stream.encoder
        trimmed = encoder.trimmed
        datagrams = encoder.encode(self._snapshot(), self._clock())
        self.counters["trimmed_sections"] += encoder.trimmed - trimmed
        for datagram in datagrams:
            try:
                self._transport.sendto(datagram, stream.address)
            except OSError as err:  # unreachable host and the like: count, keep going
                self.counters["send_errors"] += 1
                _LOGGER.debug("telemetry send to %s failed: %s", stream.address, err)
                continue
            self.counters["datagrams_sent"] += 1
            stream.sent += 1
            stream.max_size = max(stream.max_size, len(datagram))
        return len(datagrams)
