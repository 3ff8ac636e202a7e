"""The NavCam (and the platform's microphone) in the browser: fanned out, no re-encoding.

One :class:`H264Feed` per platform depayloads its RTP once (``udpsrc ! rtph264depay !
h264parse ! appsink``: Annex B byte-stream, one access unit per buffer, SPS/PPS in-band) and
hands every access unit, with the capture time the platform stamped into the RFC 6051 NTP-64
header extension, to :class:`FanOut`. The fan-out keeps the current GOP, so a new viewer gets
it replayed and shows a picture at once, and gives each viewer a bounded queue: a viewer that
falls behind (a slow page or link) is cut back to the next keyframe instead of drifting
seconds behind. After packet loss (a gap the depayloader flags DISCONT) delta frames are held
back until the next keyframe, so the page freezes instead of smearing.

Each access unit travels as one binary WebSocket message (:func:`encode_frame`): a 24-byte
header (big-endian) followed by the Annex B bytes.

=======  ====  ===============================================================
offset   type  meaning
=======  ====  ===============================================================
0        u8    message type: 1 video access unit, 2 platform audio (Opus packet),
               3 push-to-talk audio from the page (Opus packet)
1        u8    flags: 1 keyframe, 2 replayed from the GOP cache, 4 after a gap
2        u16   feed number (a page watching several feeds tells them apart)
4        u32   sequence number of the access unit in its feed
8        f64   capture time, Unix milliseconds, platform clock (0: unknown)
16       f64   arrival at the station, Unix milliseconds, station clock
=======  ====  ===============================================================
"""

from __future__ import annotations

import abc
import asyncio
import collections
import itertools
import logging
import struct
import time
import weakref
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from brasidas.media.audio import AUDIO_PAYLOAD_TYPE, RTP_AUDIO_CAPS
from brasidas.media.gst import NTP_UNIX_OFFSET_NS, caps, gst, link_all, make, ntp_caps
from brasidas.media.pipeline import PipelineStream
from brasidas.media.repair import RepairReceiver, add_repair_receiver
from brasidas.media.video import RTP_VIDEO_CAPS

_LOGGER = logging.getLogger(__name__)

FRAME_TYPE_VIDEO = 1
FRAME_TYPE_AUDIO = 2
"""Opus packets of a platform's microphone (``audio_out``), one per message, same header."""
FRAME_TYPE_TALK = 3
"""Opus packets from the page's microphone to the platform's speaker (page → station)."""
FLAG_KEY = 1
FLAG_REPLAYED = 2
FLAG_AFTER_GAP = 4
HEADER = struct.Struct(">BBHIdd")
"""The binary message header (see the module docstring)."""

GOP_MAX_FRAMES = 300
"""A GOP longer than this (10 s at 30 fps: the keyframes are missing) is not kept whole."""
VIEWER_QUEUE_FRAMES = 6
"""Frames a viewer may have waiting beyond its replay before it is cut back to a keyframe
(200 ms at 30 fps)."""
AUDIO_QUEUE_PACKETS = 10
"""Opus packets (20 ms each) a listener may have waiting before its queue is dropped."""


@dataclass(frozen=True, slots=True)
class AccessUnit:
    """One H.264 access unit (Annex B), or one Opus packet (always a "keyframe"), with its
    timing."""

    data: bytes
    keyframe: bool
    capture_ms: float
    """Capture time on the platform's wall clock (Unix ms); 0 when the packet had none."""
    arrival_ms: float
    """Arrival at the station (Unix ms, station clock)."""
    after_gap: bool = False


def encode_frame(
    feed: int, seq: int, unit: AccessUnit, *, replayed: bool = False, kind: int = FRAME_TYPE_VIDEO
) -> bytes:
    """The binary WebSocket message for ``unit``."""
    flags = (FLAG_KEY if unit.keyframe else 0) | (FLAG_REPLAYED if replayed else 0)
    flags |= FLAG_AFTER_GAP if unit.after_gap else 0
    header = HEADER.pack(
        kind, flags, feed & 0xFFFF, seq & 0xFFFFFFFF, unit.capture_ms, unit.arrival_ms
    )
    return header + unit.data


def decode_header(message: bytes) -> dict[str, Any]:
    """The header fields of a message from :func:`encode_frame` (tests, tools)."""
    kind, flags, feed, seq, capture_ms, arrival_ms = HEADER.unpack_from(message)
    return {
        "type": kind,
        "keyframe": bool(flags & FLAG_KEY),
        "replayed": bool(flags & FLAG_REPLAYED),
        "after_gap": bool(flags & FLAG_AFTER_GAP),
        "feed": feed,
        "seq": seq,
        "capture_ms": capture_ms,
        "arrival_ms": arrival_ms,
        "size": len(message) - HEADER.size,
    }


# --------------------------------------------------------------------------- fan-out (sans-IO)


class Viewer:
    """One page's queue of messages for one feed; its owner drains it with :meth:`next`."""

    def __init__(
        self, feed: int, limit: int = VIEWER_QUEUE_FRAMES, kind: int = FRAME_TYPE_VIDEO
    ) -> None:
        self.feed = feed
        self.kind = kind
        self.limit = limit
        self.queue: collections.deque[bytes] = collections.deque()
        self.allowance = 0
        """Replayed frames still queued: they do not count against the limit."""
        self.waiting_for_key = False
        self.sent = 0
        self.skipped = 0
        """Frames dropped because this viewer fell behind."""
        self.cutbacks = 0
        self.relay_ms: collections.deque[float] = collections.deque(maxlen=300)
        """Arrival at the station → written to the page's socket, of the last live messages."""
        self._ready = asyncio.Event()

    def offer(self, seq: int, unit: AccessUnit) -> None:
        """Queue a live access unit, or start skipping to the next keyframe if behind."""
        if self.waiting_for_key and not unit.keyframe:
            self.skipped += 1
            return
        if len(self.queue) >= self.limit + self.allowance:
            self.skipped += len(self.queue) + (0 if unit.keyframe else 1)
            self.queue.clear()
            self.allowance = 0
            self.cutbacks += 1
            if not unit.keyframe:
                self.waiting_for_key = True
                return
        self.waiting_for_key = False
        self.queue.append(encode_frame(self.feed, seq, unit, kind=self.kind))
        self._ready.set()

    def replay(self, gop: list[tuple[int, AccessUnit]]) -> None:
        """Queue the current GOP (a new viewer, or one that switched feeds)."""
        self.queue.clear()
        self.queue.extend(
            encode_frame(self.feed, seq, unit, replayed=True, kind=self.kind) for seq, unit in gop
        )
        self.allowance = len(gop)
        self.waiting_for_key = not gop
        if gop:
            self._ready.set()

    async def next(self) -> bytes:
        """The next message to send (waits for one)."""
        while not self.queue:
            self._ready.clear()
            await self._ready.wait()
        if self.allowance:
            self.allowance -= 1
        self.sent += 1
        return self.queue.popleft()

    def written(self, message: bytes, now_ms: float) -> None:
        """``message`` was written to the page's socket at ``now_ms`` (Unix ms)."""
        _, flags, _, _, _, arrival_ms = HEADER.unpack_from(message)
        if not flags & FLAG_REPLAYED:
            self.relay_ms.append(now_ms - arrival_ms)

    def stats(self) -> dict[str, Any]:
        relay = sorted(self.relay_ms)
        return {
            "sent": self.sent,
            "queued": len(self.queue),
            "skipped": self.skipped,
            "cutbacks": self.cutbacks,
            "relay_p50_ms": round(relay[len(relay) // 2], 2) if relay else None,
            "relay_p95_ms": round(relay[int(len(relay) * 0.95)], 2) if relay else None,
        }


class FanOut:
    """The current GOP of one feed and its viewers; fed access units in order."""

    def __init__(self, gop_max: int = GOP_MAX_FRAMES) -> None:
        self.gop: list[tuple[int, AccessUnit]] = []
        self.gop_max = gop_max
        self.viewers: set[Viewer] = set()
        self.units = 0
        self.keyframes = 0
        self.gaps = 0
        """Losses seen (a DISCONT delta unit); the deltas up to the next keyframe are held."""
        self.held = 0
        self.bytes = 0
        self._seq = itertools.count(1)
        self._frozen = True  # nothing decodable before the first keyframe
        self.last_passed_ms: float | None = None
        """Arrival (Unix ms, station clock) of the last unit passed to the viewers."""

    def staleness_ms(self, now_ms: float) -> float | None:
        """How long the pages' picture has waited for its next frame (None: no frame yet):
        a frozen picture ages by this much beyond the glass-to-glass of its last frame."""
        if self.last_passed_ms is None:
            return None
        return max(0.0, now_ms - self.last_passed_ms)

    def feed(self, unit: AccessUnit) -> None:
        """One access unit from the depayloader."""
        self.units += 1
        self.bytes += len(unit.data)
        if unit.keyframe:
            self.keyframes += 1
            self._frozen = False
            self.gop = []
        elif unit.after_gap:
            self.gaps += 1
            self._frozen = True
        if self._frozen:
            self.held += 1
            return
        self.last_passed_ms = unit.arrival_ms
        seq = next(self._seq)
        if len(self.gop) < self.gop_max:
            self.gop.append((seq, unit))
        for viewer in self.viewers:
            viewer.offer(seq, unit)

    def rewind(self, viewer: Viewer) -> None:
        """Queue the current GOP for ``viewer`` again (in place of what it had queued)."""
        viewer.replay(self.gop if len(self.gop) < self.gop_max else [])

    def add(self, viewer: Viewer) -> Callable[[], None]:
        """Start ``viewer`` with the current GOP; returns the way to remove it."""
        self.rewind(viewer)
        self.viewers.add(viewer)
        return lambda: self.viewers.discard(viewer)

    def stats(self) -> dict[str, Any]:
        return {
            "units": self.units,
            "keyframes": self.keyframes,
            "gaps": self.gaps,
            "held": self.held,
            "bytes": self.bytes,
            "gop": len(self.gop),
            "viewers": len(self.viewers),
        }


# --------------------------------------------------------------------------- GStreamer


class RtpDepayloader(PipelineStream, abc.ABC):
    """RTP/UDP → one encoded unit per buffer (``on_unit`` is called on the event loop)."""

    kind = "feed"
    rtp_caps = ""
    repair = False
    """Receive through rtpbin: NACK, retransmission, keyframe requests (brasidas.media.repair)."""

    def __init__(
        self, name: str, *, host: str, port: int, on_unit: Callable[[AccessUnit], None], **kw: Any
    ) -> None:
        super().__init__(name, **kw)
        self.host = host
        self.port = port
        self.on_unit = on_unit
        self._loop: asyncio.AbstractEventLoop | None = None
        self.repairs: RepairReceiver | None = None
        self._feedback: tuple[str, int] = ("", 0)

    def set_feedback(self, host: str, port: int | None) -> None:
        """Where the sender takes RTCP feedback (its ``rtcp_port``); applied live. Loop."""
        self._feedback = (host, port or 0)
        if self.repairs is not None:
            self.repairs.set_feedback(host, port or 0)

    def describe(self) -> dict[str, Any]:
        if self.repairs is None:
            return super().describe()
        return {**super().describe(), "repair": vars(self.repairs.counters())}

    def destination(self) -> str:
        return f"{self.host}:{self.port}"

    def on_torn_down(self) -> None:
        if self.repairs is not None:
            self.repairs.close()

    @abc.abstractmethod
    def depayload(self) -> list[Any]:
        """The elements between ``udpsrc`` and the appsink."""

    def build(self) -> Any:
        Gst = gst()
        self._loop = asyncio.get_running_loop()
        pipeline = Gst.Pipeline.new(f"{self.name}-feed")
        source = make(
            "udpsrc", "source", address=self.host, port=self.port, caps=caps(self.rtp_caps)
        )
        sink = make("appsink", "sink", emit_signals=True, sync=False, max_buffers=0, drop=False)
        chain = [source, *self.depayload(), sink]
        for element in chain:
            pipeline.add(element)
        if self.repair:
            link_all(*chain[1:])
            self.repairs = add_repair_receiver(pipeline, source, chain[1], self.rtp_caps)
            self.repairs.set_feedback(*self._feedback)
        else:
            link_all(*chain)
        sink.connect("new-sample", _on_sample, (weakref.ref(self), ntp_caps()))
        return pipeline

    def deliver(self, unit: AccessUnit) -> None:
        """Event loop: hand a unit to the owner."""
        try:
            self.on_unit(unit)
        except Exception:
            _LOGGER.exception("feed %s: unit handler failed", self.name)


class H264Depayloader(RtpDepayloader):
    """The NavCam: H.264 access units, Annex B byte-stream, SPS/PPS in-band."""

    kind = "video_feed"
    rtp_caps = RTP_VIDEO_CAPS
    repair = True

    def depayload(self) -> list[Any]:
        depay = make("rtph264depay", "depay")
        # After packet loss the depayloader drops delta units until a keyframe and flags the
        # next output DISCONT; the fan-out freezes on that flag too.
        depay.set_property("wait-for-keyframe", True)
        parse = make("h264parse", "parse", config_interval=-1)
        au = make("capsfilter", caps=caps("video/x-h264,stream-format=byte-stream,alignment=au"))
        return [depay, parse, au]


class OpusDepayloader(RtpDepayloader):
    """A platform's microphone: Opus packets (20 ms each), decoded in the page."""

    kind = "audio_feed"
    rtp_caps = RTP_AUDIO_CAPS

    def depayload(self) -> list[Any]:
        return [make("rtpopusdepay", "depay")]


class OpusSender(PipelineStream):
    """Opus packets pushed from the loop (the page's push-to-talk) → RTP/UDP to a platform."""

    kind = "talk"

    def __init__(self, name: str, *, host: str, port: int, **kw: Any) -> None:
        super().__init__(name, **kw)
        self.host = host
        self.port = port
        self.packets = 0
        self._source: Any = None

    def destination(self) -> str:
        return f"{self.host}:{self.port}"

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "packets": self.packets}

    def build(self) -> Any:
        pipeline = gst().Pipeline.new(f"{self.name}-talk")
        source = make(
            "appsrc",
            "source",
            is_live=True,
            do_timestamp=True,
            format="time",
            caps=caps("audio/x-opus,channel-mapping-family=0,channels=1,rate=48000"),
        )
        chain = [
            source,
            make("rtpopuspay", pt=AUDIO_PAYLOAD_TYPE),
            make("udpsink", "sink", host=self.host, port=self.port, sync=False, async_=False),
        ]
        for element in chain:
            pipeline.add(element)
        link_all(*chain)
        self._source = source
        return pipeline

    def on_torn_down(self) -> None:
        self._source = None

    def push(self, packet: bytes) -> None:
        """Event loop: send one Opus packet (dropped when the pipeline is not running)."""
        if self._source is None or not packet:
            return
        buffer = gst().Buffer.new_wrapped(packet)
        buffer.duration = 20 * gst().MSECOND
        self._source.emit("push-buffer", buffer)
        self.packets += 1


def _on_sample(sink: Any, data: tuple[weakref.ref[RtpDepayloader], Any]) -> Any:
    """Streaming thread: copy the access unit out and pass it to the loop."""
    ref, reference = data
    Gst = gst()
    sample = sink.emit("pull-sample")
    stream = ref()
    if sample is None or stream is None or stream._loop is None:
        return Gst.FlowReturn.OK
    buffer = sample.get_buffer()
    arrival_ms = time.time_ns() / 1e6
    meta = buffer.get_reference_timestamp_meta(reference)
    capture_ms = 0.0
    if meta is not None and meta.timestamp:
        capture_ms = (meta.timestamp - NTP_UNIX_OFFSET_NS) / 1e6
    unit = AccessUnit(
        data=buffer.extract_dup(0, buffer.get_size()),
        keyframe=not buffer.has_flags(Gst.BufferFlags.DELTA_UNIT),
        capture_ms=capture_ms,
        arrival_ms=arrival_ms,
        after_gap=buffer.has_flags(Gst.BufferFlags.DISCONT),
    )
    try:
        stream._loop.call_soon_threadsafe(stream.deliver, unit)
    except RuntimeError:  # loop closed: nobody to tell
        pass
    return Gst.FlowReturn.OK


class Feed:
    """One platform stream for the console: its depayloader, its fan-out, and its viewers."""

    def __init__(
        self,
        platform_id: str,
        number: int,
        *,
        host: str,
        port: int,
        stream: str = "navcam",
        audio: bool = False,
    ) -> None:
        self.platform_id = platform_id
        self.number = number
        self.stream = stream
        self.frame_type = FRAME_TYPE_AUDIO if audio else FRAME_TYPE_VIDEO
        self.fanout = FanOut()
        depayloader = OpusDepayloader if audio else H264Depayloader
        self.depayloader: RtpDepayloader = depayloader(
            f"{platform_id}/{stream}", host=host, port=port, on_unit=self.fanout.feed
        )

        self._loss_seen = (0, 0, 0)
        """Lost packets, repaired packets and held units when :meth:`loss_reason` last looked."""

    @property
    def port(self) -> int:
        return self.depayloader.port

    def loss_reason(self) -> str:
        """Why the picture froze, if the link lost it ("" when nothing was lost since the
        last look): packets given up on, or frames held back waiting for a keyframe."""
        repairs = self.depayloader.repairs
        counters = repairs.counters() if repairs is not None else None
        lost = counters.lost if counters is not None else 0
        repaired = counters.repaired if counters is not None else 0
        seen = (lost, repaired, self.fanout.held)
        new_lost, new_repaired, new_held = (
            a - b for a, b in zip(seen, self._loss_seen, strict=True)
        )
        self._loss_seen = seen
        if new_lost <= 0 and new_held <= 0:
            return ""
        return (
            f"packet loss on the link ({new_lost} packets lost, {new_repaired} repaired; "
            "waiting for a keyframe)"
        )

    def viewer(self) -> Viewer:
        """A new viewer of this feed (not yet added)."""
        if self.frame_type == FRAME_TYPE_AUDIO:
            return Viewer(self.number, limit=AUDIO_QUEUE_PACKETS, kind=FRAME_TYPE_AUDIO)
        return Viewer(self.number)

    def describe(self) -> dict[str, Any]:
        return {
            "platform_id": self.platform_id,
            "stream": self.stream,
            "feed": self.number,
            **self.depayloader.describe(),
            **self.fanout.stats(),
        }


async def pump(viewer: Viewer, send: Callable[[bytes], Awaitable[None]]) -> None:
    """Send ``viewer``'s messages as they come, until cancelled or ``send`` fails."""
    while True:
        message = await viewer.next()
        await send(message)
        viewer.written(message, time.time_ns() / 1e6)
